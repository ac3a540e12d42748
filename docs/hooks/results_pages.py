"""The results pages, generated at build time from the committed tables: the suite's leaderboard
(pipeline/suite/reports/) and one page per environment (every policy's pipeline/<env>*/reports/),
plus the root pipeline's (reports/: the paper's protocol on LunarLander). Nothing here imports
oodrl: the tables are the pipelines' own markdown, copied with their headings moved down a level
or two so that they nest under the page's."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

#: The suite's leaderboard, as `oodrl leaderboard` writes it.
LEADERBOARD = Path("pipeline/suite/reports")
#: A pipeline's tables: the headline, the paper protocol's tables, the tier tables and figure.
TABLES = ("headline.md", "tiers/tables.md", "tables.md")
IMPACT_FIGURE = "tiers/impact_curves.png"
#: Sections of the leaderboard shown on its page; the rest are on the page of every table.
HEADLINE_SECTIONS = (
    "Tier `mild`",
    "Detects what hurts",
    "Machine independence",
    "Cells a trivial signal",
)


@dataclass
class Run:
    """One pipeline of an environment: one policy."""

    directory: Path  # relative to the project root
    policy: str


@dataclass
class Environment:
    slug: str  # the page: results/<slug>.md
    title: str
    runs: list[Run] = field(default_factory=list)


#: `env:` then `  id: VALUE`, comment lines between allowed.
ENV_ID = re.compile(r"(?m)^env:[ \t]*(?:#.*)?\n(?:[ \t]+#.*\n)*[ \t]+id:[ \t]*([^\s#]+)")


def _env_id(params: Path) -> str | None:
    """`env.id` of a params file or of the file it `extends`, read as text (no oodrl)."""
    for _ in range(10):
        if not params.is_file():
            return None
        text = params.read_text()
        match = re.search(
            r"(?m)^env:[ \t]*(?:#.*)?\n(?:[ \t]+#.*\n)*[ \t]+id:[ \t]*([^\s#]+)", text
        )
        if match:
            return match.group(1)
        parent = re.search(r"(?m)^extends:[ \t]*([^\s#]+)", text)
        if not parent:
            return None
        params = params.parent / parent.group(1)
    return None


def environments(root: Path) -> list[Environment]:
    """Every environment with committed tables, its policies in order; the root's first."""
    found: dict[str, Environment] = {}
    if (root / "reports" / "tables.md").is_file():
        title = _env_id(root / "params.yaml") or "root"
        found["root"] = Environment("root", f"{title}: the paper's protocol")
        found["root"].runs.append(Run(Path("reports").parent, "0"))
    pipelines = sorted(
        p.parent.parent.relative_to(root) for p in (root / "pipeline").glob("*/reports/tables.md")
    )
    for directory in pipelines:
        match = re.match(r"^(.*?)(?:_policy(\d+))?$", directory.name)
        slug, policy = match.group(1), match.group(2) or "0"
        if slug not in found:
            found[slug] = Environment(slug, _env_id(root / directory / "params.yaml") or slug)
        found[slug].runs.append(Run(directory, policy))
    for env in found.values():
        env.runs.sort(key=lambda run: int(run.policy))
    return list(found.values())


def demote(markdown: str, levels: int) -> str:
    """Every ATX heading `levels` deeper (outside code fences)."""
    out, fenced = [], False
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        if not fenced and re.match(r"^#{1,6} ", line):
            line = "#" * levels + line
        out.append(line)
    return "\n".join(out)


def _source(path: Path) -> str:
    return f"`{path.as_posix()}`"


#: Front matter of the pages of tables: Material's search leaves them out (their thousands of
#: numeric cells were a quarter of the build's time and find nothing a reader searches for).
UNSEARCHED = "---\nsearch:\n  exclude: true\n---\n\n"
GENERATED = (
    "<!-- Generated at build time from the committed tables (docs/hooks/results_pages.py): "
    "rebuild the pipelines, not this page. -->"
)


def environment_page(root: Path, env: Environment) -> tuple[str, dict[str, Path]]:
    """The page's markdown and the figures it shows (site path -> file)."""
    figures: dict[str, Path] = {}
    policies = ", ".join(run.policy for run in env.runs)
    lines = [
        UNSEARCHED + f"# {env.title}",
        "",
        GENERATED,
        "",
    ]
    if env.slug == "root":
        lines += [
            "The root pipeline (`dvc repro` at the project's root): the paper's protocol, eight "
            "detectors and nine faults at one fixed severity and its sweep, and the impact tiers "
            "of the same policy. Its tables, as the pipeline wrote them to "
            f"{_source(Path('reports'))}.",
            "",
        ]
    else:
        lines += [
            f"Policies {policies} of {env.title} in the suite: each policy is its own pipeline "
            "and a run of the [leaderboard](leaderboard.md)'s aggregates. Each section is one "
            "pipeline's tables, as it wrote them: its headline table (the paper protocol's mean "
            "matched AUROC), the impact tiers with detection at a false-alarm budget, then every "
            "table of the protocol at a fixed severity.",
            "",
        ]
    for run in env.runs:
        reports = run.directory / "reports"
        if env.slug != "root":
            lines += [f"## Policy {run.policy}", "", f"From {_source(reports)}.", ""]
        level = 1 if env.slug == "root" else 2
        headline = root / reports / "headline.md"
        if headline.is_file():
            lines += [
                f"{'#' * (level + 1)} Headline: mean matched AUROC and AUPRC (AP) over faults",
                "",
                headline.read_text().strip(),
                "",
            ]
        for name in ("tiers/tables.md", "tables.md"):
            path = root / reports / name
            if path.is_file():
                lines += [demote(path.read_text().strip(), level), ""]
            figure = root / reports / IMPACT_FIGURE
            if name == "tiers/tables.md" and figure.is_file():
                name = "root" if env.slug == "root" else run.directory.name
                site_path = f"results/figures/{name}_impact.png"
                figures[site_path] = figure
                lines += [
                    f"![Impact curves, {env.title}, policy {run.policy}]"
                    f"(figures/{Path(site_path).name})",
                    "",
                ]
    return "\n".join(lines).rstrip() + "\n", figures


def _sections(markdown: str) -> tuple[str, list[tuple[str, str]]]:
    """(preamble, [(## heading, its text with subsections)])."""
    parts = re.split(r"(?m)^(?=## )", markdown)
    preamble, sections = parts[0], []
    for part in parts[1:]:
        heading, _, body = part.partition("\n")
        sections.append((heading[3:].strip(), body))
    return preamble, sections


def leaderboard_pages(root: Path) -> tuple[str, str, dict[str, Path]]:
    """(the leaderboard's page, the page of all its tables, files to copy: site path -> file)."""
    directory = root / LEADERBOARD
    if not (directory / "leaderboard.md").is_file():
        missing = [
            "# Leaderboard",
            "",
            f"No leaderboard is committed ({_source(LEADERBOARD / 'leaderboard.md')} is absent): "
            "`oodrl suite run` builds it.",
            "",
        ]
        return "\n".join(missing), "\n".join(missing).replace("# Leaderboard", "# Every table"), {}
    text = (directory / "leaderboard.md").read_text()
    preamble, sections = _sections(text)
    intro = re.sub(r"(?m)^# .*\n", "", preamble).strip()
    copies = {}
    for name, site in (("leaderboard.html", "leaderboard-page.html"), ("leaderboard.png", None)):
        if (directory / name).is_file():
            copies[f"results/{site or name}"] = directory / name
    head = [
        "# Leaderboard",
        "",
        GENERATED,
        "",
        intro,
        "",
        "The ranking of every detector over the suite's environments, policies and faults at "
        "each impact tier, from the committed "
        f"{_source(LEADERBOARD / 'leaderboard.md')}. Here: the hardest tier (`mild`, 5% of "
        "the return lost) and what each detector does on harmless shifts. "
        "[Every table](leaderboard-tables.md) has the other tiers, the fixed-severity protocol "
        "and the minimum detectable impact; "
        + (
            "[the interactive page](leaderboard-page.html) (one self-contained file, sortable "
            "and filterable, every cell opening its evidence) has every cell."
            if "results/leaderboard-page.html" in copies
            else ""
        ),
        "",
    ]
    shown = [(heading, body) for heading, body in sections if heading.startswith(HEADLINE_SECTIONS)]
    if shown and (ranking := _ranking(shown[0][1])):
        title = re.sub(
            r"^Tier (`\w+`): mean (.*?) per detector and environment (\(.*\))$",
            r"Ranking at tier \1: \2 \3",
            shown[0][0],
        )
        head += [f"## {title}", "", ranking, ""]
    for k, (heading, body) in enumerate(shown):
        head += [f"## {heading}", "", body.strip(), ""]
        if k == 0 and "results/leaderboard.png" in copies:  # the ranking first, then its figure
            head += ["![The suite's leaderboard: IQM with CIs per tier](leaderboard.png)", ""]
    rest = [heading for heading, _ in sections if heading not in dict(shown)]
    if rest:
        head += ["## Every other table", ""]
        head += [f"- [{heading}](leaderboard-tables.md#{slug(heading)})" for heading in rest]
        head += [""]
    full = [
        UNSEARCHED + "# Leaderboard: every table",
        "",
        GENERATED,
        "",
        text.split("\n", 1)[1].strip(),
        "",
    ]
    return "\n".join(head).rstrip() + "\n", "\n".join(full), copies


def _ranking(section: str) -> str | None:
    """The section's first table cut to its ranking columns: detector, IQM and mean with CIs
    (the per-environment columns of the full table come after, on a wide screen)."""
    table = []
    for line in section.strip().splitlines():
        if line.startswith("|"):
            table.append([cell.strip() for cell in line.strip().strip("|").split("|")])
        elif table:
            break
    if len(table) < 3:
        return None
    header = table[0]
    wanted = [k for k, name in enumerate(header) if k == 0 or "[95% CI]" in name]
    if len(wanted) < 2:
        return None
    rows = [[row[k] for k in wanted] for row in [header, *table[2:]]]
    rows.insert(1, ["---"] + ["---:"] * (len(wanted) - 1))
    return "\n".join("| " + " | ".join(row) + " |" for row in rows)


def slug(heading: str) -> str:
    """The anchor MkDocs gives a heading (Python-Markdown's toc slugify)."""
    from markdown.extensions.toc import slugify

    return slugify(heading, "-")
