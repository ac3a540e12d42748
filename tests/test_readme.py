"""The README's and the docs' instructions, followed literally in a fresh copy of the project,
do what they say; the README stays a first screen.

The blocks are parsed out of the Markdown files at test time (by section heading and fence
language), so an edit to a page is what gets tested. The walk-through runs on tiny params
(ci/params.yaml with one injector and only the detectors the knobs name) to stay around a
minute. The sections it follows live on the docs pages the constants below name.
"""

from __future__ import annotations

import hashlib
import re
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from oodrl.config import read_params_data
from oodrl.io.layout import detector_pipeline, detector_stage
from oodrl.testing.pipeline import copy_project, lock_hashes, run

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
GETTING_STARTED = DOCS / "getting-started.md"
ADD_DETECTOR_PAGE = DOCS / "how-to" / "add-detector.md"
#: The sections the walk-through follows: (the file that holds it, its heading).
ADD_DETECTOR = (ADD_DETECTOR_PAGE, "Add a detector")
CHANGE_KNOB = (GETTING_STARTED, "Change a knob, compare runs")
READING = (GETTING_STARTED, "Reading the results")
COMPONENTS = (GETTING_STARTED, "Components")
#: The pages whose inline `oodrl …` commands the walk-through runs.
WALKTHROUGH_PAGES = (GETTING_STARTED, ADD_DETECTOR_PAGE)
#: Inline `oodrl …` commands the pages name that the walk-through runs (cheap, read-only).
INLINE_COMMANDS = ("list", "check-params", "show")


# -- parsing the Markdown --------------------------------------------------------------------------
@dataclass(frozen=True)
class Block:
    language: str
    text: str


@dataclass
class Section:
    prose: str
    blocks: list[Block]


def parse_sections(markdown: str) -> dict[str, Section]:
    """Heading title -> its prose and fenced blocks (up to the next heading of any level).

    Fences are tracked so a `# path` comment inside a code block is not taken for a heading.
    """
    sections: dict[str, Section] = {}
    current = sections.setdefault("", Section("", []))
    fence: list[str] | None = None
    language = ""
    for line in markdown.splitlines():
        if fence is not None:
            if line.startswith("```"):
                current.blocks.append(Block(language, "\n".join(fence) + "\n"))
                fence = None
            else:
                fence.append(line)
        elif line.startswith("```"):
            fence, language = [], line[3:].strip()
        elif heading := re.match(r"#{1,6} (.+)", line):
            current = sections.setdefault(heading.group(1).strip(), Section("", []))
        else:
            current.prose += line + "\n"
    assert fence is None, "the Markdown has an unclosed code fence"
    return sections


def section(where: tuple[Path, str]) -> Section:
    """The section under a heading of a Markdown file: `where` is (file, heading)."""
    path, heading = where
    sections = parse_sections(path.read_text())
    assert heading in sections, f"{path.relative_to(ROOT)} has no heading {heading!r}"
    return sections[heading]


def walkthrough_markdown() -> str:
    return "\n".join(page.read_text() for page in WALKTHROUGH_PAGES)


def blocks(section: Section, language: str) -> list[str]:
    return [b.text for b in section.blocks if b.language == language]


def shell_commands(script: str) -> list[str]:
    """A bash block split into its commands; a quoted argument may span lines."""
    commands, pending = [], ""
    for line in script.splitlines():
        pending += line + "\n"
        try:
            words = shlex.split(pending, comments=True)
        except ValueError:  # an open quote: the command goes on on the next line
            continue
        if pending.rstrip().endswith("\\"):
            continue
        if words:
            commands.append(pending.strip())
        pending = ""
    assert not pending.strip(), f"unterminated command in a README block: {pending!r}"
    return commands


def argv(command: str) -> list[str]:
    return shlex.split(command, comments=True)


def set_params(command: str) -> dict[str, str]:
    """The `-S key=value` overrides of a `dvc exp run` command."""
    words = argv(command)
    pairs = [words[i + 1] for i, w in enumerate(words[:-1]) if w in ("-S", "--set-param")]
    return dict(pair.split("=", 1) for pair in pairs)


def inline_oodrl_commands(markdown: str) -> dict[str, str]:
    """Subcommand -> the first inline `oodrl <subcommand> …` the README names."""
    found: dict[str, str] = {}
    for command in re.findall(r"`(oodrl [^`]+)`", markdown):
        found.setdefault(command.split()[1], command)
    return found


def merge_params(params: dict[str, Any], snippet: dict[str, Any]) -> None:
    """Apply a README params snippet: `[..., x]` appends to the existing list, a mapping
    merges key by key, anything else replaces."""
    for key, value in snippet.items():
        if isinstance(value, dict) and isinstance(params.get(key), dict):
            merge_params(params[key], value)
        elif isinstance(value, list) and "..." in value:
            existing = params.get(key, [])
            params[key] = existing + [v for v in value if v != "..." and v not in existing]
        else:
            params[key] = value


# -- the fresh project ---------------------------------------------------------------------------
def tiny_params(repo_root: Path, knobs: dict[str, str]) -> dict[str, Any]:
    """ci/params.yaml (merged with the params it extends) on one injector and the detectors
    the README's knobs name."""
    params = read_params_data(repo_root / "ci" / "params.yaml")
    named = [k.split(".")[1] for k in knobs if k.startswith("detectors.")]
    injectors = [k.split(".")[2] for k in knobs if k.startswith("anomaly.injectors.")]
    params["benchmark"] = {
        "detectors": list(dict.fromkeys(named)) or params["benchmark"]["detectors"][:1],
        "injectors": list(dict.fromkeys(injectors)) or params["benchmark"]["injectors"][:1],
    }
    params["executor"]["workers"] = 1
    return params


def stages_ran(output: str) -> list[str]:
    return sorted(
        line.split("'")[1] for line in output.splitlines() if line.startswith("Running stage '")
    )


def sh(repo: Path, command: str) -> str:
    """Run one README command in the project with bash, as a user would type it."""
    done = run(repo, "bash", "-c", command)
    return done.stdout + done.stderr


def policy_digest(repo: Path) -> str:
    """The committed policy's bytes: following the README must never retrain or replace it."""
    return hashlib.sha256((repo / "models" / "policy.pt").read_bytes()).hexdigest()


def readme_knobs() -> dict[str, str]:
    knobs: dict[str, str] = {}
    for script in blocks(section(CHANGE_KNOB), "bash"):
        for command in shell_commands(script):
            knobs.update(set_params(command))
    return knobs


# -- following the README ------------------------------------------------------------------------
def add_detector(repo: Path, section: Section) -> list[str]:
    """Write the python block to the file its first-line comment names, apply the params
    snippet, run the bash blocks; returns the names the snippet adds to benchmark.detectors."""
    (python,) = blocks(section, "python")
    path = re.match(r"# (\S+\.py)\n", python)
    assert path, "the README's detector code must start with a `# path/to/module.py` comment"
    target = repo / path.group(1)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(python)

    (snippet_text,) = blocks(section, "yaml")
    snippet = yaml.safe_load(snippet_text)
    params = yaml.safe_load((repo / "params.yaml").read_text())
    before = list(params["benchmark"]["detectors"])
    merge_params(params, snippet)
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    added = [d for d in params["benchmark"]["detectors"] if d not in before]
    assert added, "the README's params snippet adds no detector to benchmark.detectors"

    commands = [c for script in blocks(section, "bash") for c in shell_commands(script)]
    assert any("check_detector" in c for c in commands), "the README runs no contract check"
    for command in commands:
        output = sh(repo, command)
        words = argv(command)
        if words[:2] == ["dvc", "repro"]:
            targets = [w for w in words[2:] if not w.startswith("-")]
            ran = stages_ran(output)  # a DVC file as target: its stages are `<file>:<stage>`
            missing = {t for t in targets if not any(s == t or s.startswith(f"{t}:") for s in ran)}
            assert not missing, f"`{command}` did not run {sorted(missing)}:\n{output}"
    return added


def check_inline_commands(repo: Path, markdown: str) -> None:
    """`oodrl list` prints every component the docs list; check-params passes; `oodrl show`
    prints every benchmarked detector, the walk-through's new one included."""
    commands = inline_oodrl_commands(markdown)
    for name in INLINE_COMMANDS:
        assert name in commands, f"the docs name no `oodrl {name}` command"
    listed = sh(repo, commands["list"])
    components = re.findall(r"`([a-z][a-z0-9_]+)`", section(COMPONENTS).prose)
    assert components, "the Components section lists no component names"
    for component in components:
        assert component in listed, f"`oodrl list` does not print {component}"
    assert ": ok (" in sh(repo, commands["check-params"])
    shown = sh(repo, commands["show"])
    for detector in yaml.safe_load((repo / "params.yaml").read_text())["benchmark"]["detectors"]:
        assert detector in shown, f"`{commands['show']}` does not show {detector}"


def check_figures_and_plots(repo: Path, section: Section) -> None:
    """The figures the README names exist; its word on the plots page's network use is true."""
    for figure in re.findall(r"`(?:reports/figures/)?([a-z_]+\.png)`", section.prose):
        assert (repo / "reports" / "figures" / figure).is_file(), figure
    output = sh(repo, "dvc plots show")
    page = re.search(r"(\S+\.html)", output)
    assert page, f"`dvc plots show` named no page:\n{output}"
    html = Path(page.group(1).removeprefix("file://")).read_text()
    remote = bool(re.search(r"<script[^>]+src=\"https?://", html))
    says_network = "network" in section.prose
    assert remote == says_network, (
        f"the README says the plots page {'needs' if says_network else 'does not need'} a "
        f"network; the page {'loads' if remote else 'does not load'} remote scripts"
    )


def change_knobs(repo: Path, section: Section) -> None:
    """Each `dvc exp run -S` changes a scored output (a detector knob: only that detector's
    stages run); `dvc metrics diff` then reports a difference from the committed run."""
    for script in blocks(section, "bash"):
        for command in shell_commands(script):
            before = lock_hashes(repo)
            output = sh(repo, command)
            after = lock_hashes(repo)
            knobs = set_params(command)
            if knobs:
                changed = [p for p in after if p.startswith("scores/") and after[p] != before[p]]
                assert changed, f"`{command}` changed no scores:\n{output}"
                check_detector_knob(command, knobs, stages_ran(output))
            elif argv(command)[:3] == ["dvc", "metrics", "diff"]:
                assert "reports/metrics.json" in output, f"`{command}` shows no change:\n{output}"


def check_detector_knob(command: str, knobs: dict[str, str], ran: list[str]) -> None:
    for key in knobs:
        if not key.startswith("detectors."):
            continue
        detector = key.split(".")[1]
        assert detector_stage(detector, "fit") in ran, (
            f"`{command}` did not refit {detector}: {ran}"
        )
        # Per-item stages: a detector's file, collect_*@injector; shared: these four.
        shared = ("check_params", "metrics", "render", "tier_metrics")
        own = detector_pipeline(detector)
        others = [s for s in ran if s not in shared and not s.startswith(own)]
        assert not others, f"`{command}` re-ran stages of other components: {others}"


# -- tests: the walk-through ---------------------------------------------------------------------
def test_the_docs_have_the_blocks_this_test_follows():
    add = section(ADD_DETECTOR)
    assert len(blocks(add, "python")) == 1 and len(blocks(add, "yaml")) == 1
    assert blocks(add, "bash"), "Add a detector shows no commands"
    assert readme_knobs(), "Change a knob shows no `dvc exp run -S` command"
    assert set(INLINE_COMMANDS) <= set(inline_oodrl_commands(walkthrough_markdown()))


def test_shell_commands_keep_a_quoted_argument_across_lines():
    script = 'python -c "\nprint(1)\n"\n# a comment\ndvc repro a b  # why\n'
    assert shell_commands(script) == ['python -c "\nprint(1)\n"', "dvc repro a b  # why"]


def test_merge_params_appends_to_an_elided_list():
    params = {"benchmark": {"detectors": ["a", "b"]}, "detectors": {"a": {"x": 1}}}
    merge_params(params, {"benchmark": {"detectors": ["...", "c"]}, "detectors": {"c": {}}})
    assert params == {
        "benchmark": {"detectors": ["a", "b", "c"]},
        "detectors": {"a": {"x": 1}, "c": {}},
    }


def test_kde_bandwidth_knob_differs_from_the_default_runs_bandwidth(repo_root):
    """A bandwidth knob equal to what Scott's rule gives on the default run changes nothing."""
    from oodrl.config import load_params
    from oodrl.detectors.kde import bandwidth_of
    from oodrl.envs import ENVIRONMENTS

    knobs = readme_knobs()
    values = [float(v) for k, v in knobs.items() if k == "detectors.kde_density.bandwidth"]
    if not values:
        pytest.skip("the docs turn no kde_density bandwidth knob")
    params = load_params(repo_root / "params.yaml")
    kde = params.detectors["kde_density"]
    assert kde.get("features", "state") == "state"
    fit_rows = (params.data.n_id - params.data.n_calibration) * params.env.T
    n = min(kde.get("max_reference", 4096), fit_rows)
    default = bandwidth_of(
        kde.get("bandwidth", "scott"), n, ENVIRONMENTS.get(params.env.id)().state_dim
    )
    assert values[0] != pytest.approx(default), f"bandwidth {values[0]} is the default run's own"


@pytest.mark.slow
def test_following_the_docs_in_a_fresh_project(tmp_path, repo_root):
    if not (repo_root / "models" / "policy.pt").is_file():
        pytest.skip("models/policy.pt is not committed yet")
    # The project as committed, on tiny params: the DVC files for them are written by the
    # docs' own `oodrl pipeline write` (add_detector), which renders them all anew and drops
    # the files of detectors left out. (copy_project's params= wrote them once more before it:
    # 17 s of the test's 162 s on a loaded machine.)
    repo = copy_project(repo_root, tmp_path / "project")
    params = tiny_params(repo_root, readme_knobs())
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    run(repo, "git", "commit", "-q", "-m", "tiny params", "params.yaml")
    policy = policy_digest(repo)

    added = add_detector(repo, section(ADD_DETECTOR))
    results = yaml.safe_load((repo / "reports" / "results.yaml").read_text())
    for detector in added:
        assert any(r["detector"] == detector for r in results["records"]), detector
    status = run(repo, "dvc", "status", "-q", "--with-deps", "dvc.yaml", check=False)
    assert status.returncode == 0, "the docs' repro left stages pending"
    check_inline_commands(repo, walkthrough_markdown())
    check_figures_and_plots(repo, section(READING))

    # A fresh clone's HEAD holds a complete run: the baseline `dvc metrics diff` compares with.
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "the docs' detector added and run")
    change_knobs(repo, section(CHANGE_KNOB))
    assert policy_digest(repo) == policy


# -- tests: the README is a first screen --------------------------------------------------------
#: At most this many lines (SPEC §25).
README_MAX_LINES = 250
#: The first screen: the run command and the leaderboard's headline numbers lie within it.
FIRST_SCREEN = 40
#: README.md's sections, in this order (SPEC §25); the quickstart's heading is exact, since the
#: API's tests find its block by it.
README_SECTIONS = (
    "Run it",
    "What it measures",
    "What it finds: the `mild` tier",
    "Python quickstart",
    "Commands",
    "Documentation",
    "Citing",
)
QUICKSTART = "Python quickstart"
QUICKSTART_MAX_LINES = 12
#: Markdown files whose relative links must resolve; the docs pages among them must link only
#: inside docs/ (the site is built from it alone).
LINKED_FILES = (
    README,
    ROOT / "CHANGELOG.md",
    ROOT / "CONTRIBUTING.md",
    DOCS / "index.md",
    GETTING_STARTED,
    DOCS / "performance.md",
    *sorted((DOCS / "concepts").glob("*.md")),
    *sorted((DOCS / "how-to").glob("*.md")),
)


#: Pages docs/hooks/generate.py writes when the site is built (never in git): a docs page may
#: link them, and `mkdocs build --strict` checks those links.
GENERATED_PAGES = frozenset(
    DOCS / page
    for page in (
        "reference/cli.md",
        "reference/params.md",
        "results/leaderboard.md",
        "results/leaderboard-tables.md",
    )
)


def leaderboard() -> dict[str, Any]:
    import json

    from oodrl.report.readme import LEADERBOARD

    return json.loads((ROOT / LEADERBOARD).read_text())


def test_readme_is_at_most_250_lines_and_opens_on_the_command_and_the_ranking():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines"
    first = "\n".join(lines[:FIRST_SCREEN])
    from test_project import _command_after

    assert _command_after(README.read_text(), "<!-- run-command -->") in first
    # The lead tier's top detector and its IQM with CI, as the leaderboard computed them.
    board = leaderboard()
    scores = board["iqm"][board["lead"]["metric"]][board["lead"]["tier"]]
    top = max(scores, key=lambda d: scores[d]["value"])
    entry = scores[top]
    figure = f"{entry['value']:.3f} [{entry['ci_low']:.3f}, {entry['ci_high']:.3f}]"
    assert f"`{top}`" in first and figure in first, (top, figure)


def test_readme_sections_come_in_their_order():
    headings = [h for h in parse_sections(README.read_text()) if h and h != "oodrl"]
    assert headings == list(README_SECTIONS)


def test_the_python_quickstart_is_short_and_the_same_in_the_docs():
    (readme_block,) = blocks(parse_sections(README.read_text())[QUICKSTART], "python")
    assert len(readme_block.splitlines()) <= QUICKSTART_MAX_LINES
    assert "import oodrl" in readme_block and "oodrl.evaluate(" in readme_block
    assert 'oodrl.load_results("pipeline/suite")' in readme_block
    (docs_block,) = blocks(section((GETTING_STARTED, QUICKSTART)), "python")
    assert docs_block == readme_block


def test_every_generated_table_is_what_its_source_generates():
    """README.md's and the home page's leaderboard headline is the committed leaderboard's;
    getting started's table is the root pipeline's committed reports/headline.md."""
    from oodrl.report.readme import (
        LEADERBOARD_START,
        START,
        generated_block,
        leaderboard_headline,
    )

    headline = leaderboard_headline(leaderboard())
    for page in (README, DOCS / "index.md"):
        block = generated_block(page.read_text(), LEADERBOARD_START)
        assert block == headline, f"{page.relative_to(ROOT)} is stale: `oodrl readme-table`"
    table = (ROOT / "reports" / "headline.md").read_text().strip()
    assert generated_block(GETTING_STARTED.read_text(), START) == table


def test_the_headline_says_what_the_time_aware_rule_changes_where_the_results_hold_both():
    """Since protocol 4 the leaderboard holds both threshold rules: a last column gives each shown
    detector's paired difference with its CI, and the caption the rankings' Kendall τ. A
    leaderboard of one rule (protocol 3's, or a board whose results hold no time-aware rule) has
    no such column."""
    from oodrl.report.readme import leaderboard_headline

    board = leaderboard()
    lead = board["lead"]
    change = board["rule_change"][lead["metric"]][lead["tier"]]
    header, _, *rows = leaderboard_headline(board).split("\n\n")[0].splitlines()
    assert header.endswith("time-aware rule − constant |"), header
    for row in rows:
        detector = row.split("`")[1]
        difference = change["detectors"][detector]["difference"]
        assert row.split(" | ")[-1].startswith(f"{difference['value']:+.3f} ["), row
    assert f"Kendall τ of the two rules' IQM rankings {change['kendall_tau'][0]['tau']:.2f}" in (
        leaderboard_headline(board)
    )

    one_rule = {key: value for key, value in board.items() if key != "rule_change"}
    header = leaderboard_headline(one_rule).splitlines()[0]
    assert "time-aware" not in header and header.count(" | ") == 4, header


def test_readme_table_rewrites_a_stale_block_and_refuses_a_file_without_its_markers(tmp_path):
    from typer.testing import CliRunner

    from oodrl.cli import app
    from oodrl.report.readme import LEADERBOARD, LEADERBOARD_START, generated_block

    page = tmp_path / "page.md"
    stale = README.read_text().replace("| 1 | `", "| 1 | `stale", 1)
    page.write_text(stale)
    source = str(ROOT / LEADERBOARD)
    result = CliRunner().invoke(app, ["readme-table", source, "--readme", str(page)])
    assert result.exit_code == 0, result.output
    assert page.read_text() == README.read_text()

    # A pipeline's table into a file that holds only the leaderboard's block: one line.
    headline = str(ROOT / "reports" / "headline.md")
    result = CliRunner().invoke(app, ["readme-table", headline, "--readme", str(page)])
    assert result.exit_code != 0
    assert "no <!-- headline:start --> ... <!-- headline:end --> markers" in result.output
    assert page.read_text() == README.read_text(), "a refused rewrite changed the file"
    assert generated_block(page.read_text(), LEADERBOARD_START) is not None


def _slug(heading: str) -> str:
    """Python-Markdown's toc anchor of a heading (MkDocs' default), code spans as their text."""
    import unicodedata

    text = unicodedata.normalize("NFKD", heading.replace("`", ""))
    text = re.sub(r"[^\w\s-]", "", text.encode("ascii", "ignore").decode()).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def test_relative_links_resolve_and_the_docs_link_only_inside_docs():
    link = re.compile(r"\]\(([^)\s]+)\)")
    problems = []
    for page in LINKED_FILES:
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.DOTALL)
        for target in link.findall(text):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            path, _, anchor = target.partition("#")
            resolved = (page.parent / path).resolve()
            where = f"{page.relative_to(ROOT)}: {target}"
            if page.is_relative_to(DOCS) and resolved in GENERATED_PAGES:
                continue
            if not resolved.exists():
                problems.append(f"{where} (no such file)")
            elif page.is_relative_to(DOCS) and not resolved.is_relative_to(DOCS):
                problems.append(f"{where} (outside docs/: the site cannot link it)")
            elif anchor and resolved.suffix == ".md":
                headings = parse_sections(resolved.read_text())
                if anchor not in {_slug(h) for h in headings}:
                    problems.append(f"{where} (no heading with that anchor)")
    assert not problems, "\n".join(problems)


def test_citation_cff_is_cff_1_2_0_by_the_oodrl_developers():
    import tomllib

    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0"
    assert citation["authors"] == [{"name": "The oodrl developers"}]
    assert {"message", "title", "type"} <= set(citation)
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert str(citation["version"]) == version
