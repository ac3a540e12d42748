"""The documentation site (SPEC §25): `mkdocs build --strict` passes, and its generated
references leave nothing out: every command of the app, every key of the params schema with its
default, every public name of the Python API, every environment's results. docs/SPEC.md holds
the rules, in step with the reference text; implementation-notes.md what moved out of it."""

from __future__ import annotations

import html
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "docs" / "SPEC.md"
NOTES = ROOT / "docs" / "implementation-notes.md"
#: The reference text of the protocol, beside the project's checkout where there is one.
REFERENCE_SPEC = ROOT.parent / "shared" / "SPEC.md"


#: CI (.ci/run) names the folder its site goes to: the tests' strict build is then CI's, and CI
#: builds no second one.
SITE_VARIABLE = "OODRL_DOCS_SITE"


@pytest.fixture(scope="session")
def site(tmp_path_factory) -> Path:
    """The site, built by `mkdocs build --strict` once per test run: under pytest-xdist the first
    worker to ask builds it and the others wait and read it (a build takes half a minute of a
    core). It goes to $OODRL_DOCS_SITE where that is set, else to the run's temporary folder."""
    from filelock import FileLock

    this_run = tmp_path_factory.getbasetemp()  # under xdist: this worker's, in the run's
    shared = this_run.parent if os.environ.get("PYTEST_XDIST_WORKER") else this_run
    out = Path(os.environ.get(SITE_VARIABLE) or shared / "site")
    built = shared / "site.built"
    with FileLock(f"{built}.lock"):
        if not built.is_file():
            build_site(out)
            built.write_text(str(out))
    return out


def build_site(out: Path) -> None:
    before = sorted(p for p in (ROOT / "docs").rglob("*") if "__pycache__" not in p.parts)
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert result.returncode == 0, result.stderr[-4000:]
    assert "WARNING" not in result.stderr, result.stderr[-4000:]
    after = sorted(p for p in (ROOT / "docs").rglob("*") if "__pycache__" not in p.parts)
    assert after == before  # generated pages live in the build only, never in docs/


def page(site: Path, path: str) -> str:
    return (site / path / "index.html").read_text()


def text_of(markup: str) -> str:
    return html.unescape(re.sub(r"<[^>]+>", "", markup))


def commands(group, context, Context) -> list[str]:
    """Every command path of a click group, as `oodrl suite try`."""
    out = []
    for name in group.list_commands(context):
        command = group.get_command(context, name)
        if command.hidden:
            continue
        sub = Context(command, info_name=name, parent=context)
        if hasattr(command, "commands"):
            out += commands(command, sub, Context)
        else:
            out.append(sub.command_path)
    return out


def test_cli_reference_lists_every_command_and_option(site):
    import typer.main
    from typer._click.core import Context

    from oodrl.cli import app

    root = typer.main.get_command(app)
    context = Context(root, info_name="oodrl")
    paths = commands(root, context, Context)
    assert "oodrl suite try" in paths and "oodrl fit" in paths and len(paths) >= 25
    markup = page(site, "reference/cli")
    for path in paths:
        anchor = re.sub(r"[^a-z0-9]+", "-", path.lower()).strip("-")
        heading = re.search(rf'<h[2-6] id="{anchor}">(.*?)</h[2-6]>', markup)
        assert heading and path in text_of(heading.group(1)), path
        # Its section names every option of the command.
        section = markup[heading.end() :]
        section = section[: m.start()] if (m := re.search(r"<h[2-6] ", section)) else section
        command = root
        for name in path.split()[1:]:
            command = command.get_command(context, name)
        for param in command.params:
            if param.param_type_name == "option" and not param.hidden:
                assert f"<code>{param.opts[0]}" in section, (path, param.opts[0])
    # The panels of `oodrl --help`: the stage verbs under their own heading.
    assert re.search(r'<h2 id="[^"]*">Pipeline stages \(dvc repro runs these\)', markup)


def leaves(model, prefix=""):
    from pydantic import BaseModel

    for name, field in model.model_fields.items():
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            yield from leaves(field.annotation, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", field


def test_params_reference_lists_every_key_with_its_default(site):
    from oodrl.config import Params

    rows = {}
    for row in re.findall(r"<tr>(.*?)</tr>", page(site, "reference/params"), re.S):
        cells = [text_of(c).strip() for c in re.findall(r"<td>(.*?)</td>", row, re.S)]
        if cells:
            rows[cells[0]] = cells
    keys = list(leaves(Params))
    assert len(keys) >= 40 and "tiers.search.tolerance" in dict(keys)
    for path, field in keys:
        assert path in rows, path
        if field.is_required():
            expected = "required"
        else:
            value = field.default_factory() if field.default_factory else field.default
            expected = value if isinstance(value, str) else json.dumps(value, ensure_ascii=False)
        assert rows[path][2] == expected, (path, rows[path])
    # A range from the field's metadata: tiers.alpha is in (0, 1).
    assert rows["tiers.alpha"][3] == "0 < x < 1"
    # Each registered component's own keys, with its class's default.
    assert "detectors.cusum.slack" in rows and rows["detectors.cusum.slack"][1] == "0.5"


def test_api_reference_documents_every_public_name(site):
    import oodrl.api

    markup = page(site, "reference/api")
    for name in oodrl.api.__all__:
        assert f'id="oodrl.api.{name}"' in markup, name


def test_results_pages_every_environment_and_the_leaderboard(site):
    markup = page(site, "results/leaderboard")
    leaderboard = text_of(markup)
    assert "IQM [95% CI]" in leaderboard and "Tier mild" in leaderboard
    # It leads with the ranking: its first table is detector, IQM and mean with CIs.
    first = re.search(r"<thead>(.*?)</thead>", markup, re.S).group(1)
    assert [text_of(c).strip() for c in re.findall(r"<th[^>]*>(.*?)</th>", first, re.S)] == [
        "detector",
        "IQM [95% CI]",
        "mean [95% CI]",
    ]
    assert (site / "results" / "leaderboard-page.html").is_file()
    every_table = text_of(page(site, "results/leaderboard-tables"))
    assert "Minimum detectable impact" in every_table
    pipelines = sorted(p.parent.parent.name for p in ROOT.glob("pipeline/*/reports/tables.md"))
    assert pipelines
    for name in pipelines:
        env = re.sub(r"_policy\d+$", "", name)
        assert f"pipeline/{name}/reports" in text_of(page(site, f"results/{env}")), name
    assert "oodrl results" in text_of(page(site, "results/root"))


def sections(text: str) -> dict[int, str]:
    """`## N. Title` -> the section's text, heading included."""
    parts = re.split(r"(?m)^(?=## )", text)
    out = {}
    for part in parts:
        if m := re.match(r"## (\d+)\. ", part):
            out[int(m.group(1))] = part
    return out


#: Sections whose wording the project refined beyond the reference text (a metric's exact
#: definition, the results files' fields); every other section holds the reference's lines.
REFINED = {6, 7}


def test_spec_holds_the_rules_and_the_notes_link_back():
    spec = SPEC.read_text()
    rules = sections(spec)
    assert sorted(rules) == list(range(1, len(rules) + 1)) and len(rules) >= 25
    assert "How oodrl implements" not in "".join(
        line for line in spec.splitlines() if line.startswith("#")
    )
    notes = NOTES.read_text()
    headings = re.findall(r"(?m)^## (How oodrl implements §(\d+).*)$", notes)
    assert headings
    for heading, number in headings:
        assert int(number) in rules
        # Each block links back to its section and the section to its block.
        block = notes[notes.index(heading) :].split("\n## ")[0]
        assert f"](SPEC.md#{number}-" in block, heading
        assert "](implementation-notes.md#how-oodrl-implements-" in rules[int(number)]


@pytest.mark.skipif(not REFERENCE_SPEC.is_file(), reason="no reference SPEC beside the checkout")
def test_spec_is_in_step_with_the_reference_text():
    reference = sections(REFERENCE_SPEC.read_text())
    ours = sections(SPEC.read_text())
    assert sorted(ours) == sorted(reference)
    for number, text in reference.items():
        assert ours[number].splitlines()[0] == text.splitlines()[0]
        if number in REFINED:
            continue
        # Every line of the reference's section, in order, in ours (ours may add lines).
        remaining = iter(ours[number].splitlines())
        for line in filter(None, text.splitlines()):
            assert any(line == mine for mine in remaining), (number, line)
