"""The stable command-line verbs (SPEC §10)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml
from typer.testing import CliRunner

from oodrl.cli import app

runner = CliRunner()


def test_list_shows_every_component_kind():
    result = runner.invoke(app, ["list"])
    assert result.exit_code == 0, result.output
    sections = {}
    current = None
    for line in result.output.splitlines():
        if not line.startswith(" "):
            current = line.rstrip(":")
            sections[current] = []
        else:
            sections[current].append(line.split()[0])
    assert len(sections["detectors"]) == 8
    assert len(sections["injectors"]) == 9
    assert "matched_auroc" in sections["metrics"]
    assert sections["environments"] == ["LunarLander-v3"]
    assert result.output.count("(online)") == 4 and result.output.count("(posthoc)") == 5


def test_show_refuses_a_foreign_file_with_one_line(tmp_path):
    foreign = tmp_path / "foreign.yaml"
    foreign.write_text(yaml.safe_dump({"something": 1}))
    result = runner.invoke(app, ["show", str(foreign)])
    assert result.exit_code == 1
    assert result.output.count("\n") == 1 and str(foreign) in result.output


def test_evaluate_policy_rejects_an_unknown_mode(tmp_path):
    result = runner.invoke(app, ["evaluate-policy", "--mode", "eps", "--episodes", "1"])
    assert result.exit_code == 2
    assert "--mode must be 'greedy' or 'noisy'" in result.output


def test_stage_verbs_refuse_unlisted_components(repo_root):
    result = runner.invoke(
        app, ["fit", "kde_densty", "--id", "x.zarr", "--out", "y.pkl",
              "--params", str(repo_root / "params.yaml")],
    )  # fmt: skip
    assert result.exit_code == 2
    assert "'kde_densty' is not listed in benchmark.detectors" in result.output


@pytest.mark.parametrize(
    "module", ["oodrl.detectors.kde", "oodrl.detectors.mahalanobis", "oodrl.stages.collect"]
)
def test_numpy_stages_never_import_torch(module):
    code = f"import sys, {module}; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
