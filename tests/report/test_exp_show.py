"""The docs' recipe for comparing runs fits a terminal, in a real DVC repository.

The repository has the project's params.yaml (so `dvc exp show` sees all of its params), a
collection stage per injector writing a store that changes with the headline severity (so that,
as in the real pipeline, the changed dependencies' hashes are columns DVC would show), and a
stage that writes reports/metrics.json with `metrics_json` from the realistic fake results,
their matched AUROCs scaled by the headline severity so that experiments differ. The commands
are read from the "Compare runs in a terminal" section of docs/getting-started.md and run at
100 columns with their output captured: no line may be wider, no cell may be cut to "…", and
the table shows the followed detectors and the changed param and nothing else.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import yaml

from oodrl.report.tables import HEADLINE_METRIC
from oodrl.testing.pipeline import run

WIDTH = 100
SECTION = "### Compare runs in a terminal"

WRITE_METRICS = """
import json
import yaml
from oodrl.report.tables import metrics_json

severity = yaml.safe_load(open("params.yaml"))["anomaly"]["severity"]
results = yaml.safe_load(open("results.yaml"))
for record in results["records"]:
    if record["kind"] == "anomaly":
        record["metrics"]["matched_auroc"]["mean"] *= 0.5 + severity
with open("reports/metrics.json", "w") as handle:
    json.dump(metrics_json(results), handle, indent=2, sort_keys=True)
"""


def recipe(readme: Path) -> list[str]:
    """The commands of the first bash block of the page's section, comments removed."""
    text = readme.read_text(encoding="utf-8").split(SECTION, 1)[1]
    block = re.search(r"```bash\n(.*?)```", text, re.DOTALL)
    assert block, f"{readme.name} has no bash block under {SECTION!r}"
    return [shlex.join(shlex.split(line, comments=True)) for line in block.group(1).splitlines()]


@pytest.fixture
def experiment_repo(results, repo_root, tmp_path) -> Path:
    repo = tmp_path / "repo"
    (repo / "reports").mkdir(parents=True)
    (repo / "params.yaml").write_text((repo_root / "params.yaml").read_text())
    (repo / "results.yaml").write_text(yaml.safe_dump(results))
    (repo / "write_metrics.py").write_text(WRITE_METRICS)
    injectors = yaml.safe_load((repo_root / "params.yaml").read_text())["benchmark"]["injectors"]
    collect = {
        "foreach": injectors,
        "do": {
            "cmd": "python -c \"import sys, yaml; p = yaml.safe_load(open('params.yaml')); "
            "open(sys.argv[1], 'w').write(str(p['anomaly']['severity']) + sys.argv[1])\" "
            "data/ood/${item}.zarr",
            "params": ["anomaly.severity"],
            "outs": ["data/ood/${item}.zarr"],
        },
    }
    metrics = {
        "cmd": "python write_metrics.py",
        "deps": ["write_metrics.py", "results.yaml", *(f"data/ood/{i}.zarr" for i in injectors)],
        "params": ["anomaly.severity"],
        "metrics": [{"reports/metrics.json": {"cache": False}}],
    }
    (repo / "data" / "ood").mkdir(parents=True)
    stages = {"collect_ood": collect, "metrics": metrics}
    (repo / "dvc.yaml").write_text(yaml.safe_dump({"stages": stages}))
    run(repo, "git", "init", "-q")
    run(repo, "dvc", "init", "-q")
    run(repo, "dvc", "repro", "-q")
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "baseline")
    return repo


@pytest.mark.slow
def test_the_compare_runs_recipe_fits_a_terminal(experiment_repo, repo_root):
    commands = recipe(repo_root / "docs" / "getting-started.md")
    assert [c.split()[:3] for c in commands] == [
        ["dvc", "exp", "run"],
        ["dvc", "exp", "diff"],
        ["dvc", "exp", "show"],
    ]
    outputs = []
    for command in commands:
        args = shlex.split(command)
        if args[:3] == ["dvc", "exp", "show"]:
            args.append("--no-pager")
        done = run(experiment_repo, *args, env={"COLUMNS": str(WIDTH)})
        outputs.append(done.stdout)
    _, diff, show = outputs
    # Captured, not a terminal (as piped to a file or `less`): the changed stores' hashes are
    # no columns of it.
    assert not re.search(r"\b[0-9a-f]{32}\b", show), show
    header = next(line for line in show.splitlines() if "Experiment" in line)
    columns = re.findall(r"[\w./\\-]+", header.replace("Experiment", ""))
    assert sorted(columns) == sorted(
        ["anomaly.severity", f"{HEADLINE_METRIC}.cusum", f"{HEADLINE_METRIC}.pedm"]
    ), show
    for output in (diff, show):
        lines = output.rstrip("\n").splitlines()
        assert max(len(line.rstrip()) for line in lines) <= WIDTH, output
        assert "…" not in output, output
    # The diff lists every headline figure and the changed param, one a row.
    detectors = yaml.safe_load((repo_root / "params.yaml").read_text())["benchmark"]["detectors"]
    for detector in detectors:
        assert f"{HEADLINE_METRIC}.{detector} " in diff, diff
    assert "anomaly.severity" in diff
    # The table shows the kept detectors and the changed param, for the baseline and the run.
    for column in (f"{HEADLINE_METRIC}.cusum", f"{HEADLINE_METRIC}.pedm", "anomaly.severity"):
        assert column in show, show
    assert "sev06" in show
