"""Project-level promises: the README's two commands, CI's params, nothing host-specific."""

from __future__ import annotations

import subprocess

import yaml

from oodrl.config import load_params


def _command_after(readme: str, marker: str) -> str:
    lines = readme.splitlines()
    index = lines.index(marker)
    assert lines[index + 1] == "```bash"
    return lines[index + 2]


def test_readme_has_the_two_setup_commands(repo_root):
    readme = (repo_root / "README.md").read_text()
    run_command = _command_after(readme, "<!-- run-command -->")
    test_command = _command_after(readme, "<!-- test-command -->")
    for command in (run_command, test_command):
        assert "-c constraints.txt" in command
    assert run_command.endswith("dvc repro")
    assert "pytest" in test_command


def test_ci_runs_the_readme_test_command(repo_root):
    extract = subprocess.run(
        ["awk", "/<!-- test-command -->/{getline; getline; print; exit}", "README.md"],
        cwd=repo_root, capture_output=True, text=True, check=True,
    )  # fmt: skip
    readme = (repo_root / "README.md").read_text()
    assert extract.stdout.strip() == _command_after(readme, "<!-- test-command -->")
    assert "<!-- test-command -->" in (repo_root / ".ci" / "run").read_text()


def test_ci_params_are_valid_and_reuse_the_committed_policy(repo_root):
    ci = load_params(repo_root / "ci" / "params.yaml")
    default = load_params(repo_root / "params.yaml")
    assert ci.policy.train == default.policy.train, "CI would retrain the policy"
    assert ci.benchmark == default.benchmark, "CI must exercise every stage of the pipeline"


def test_constraints_pin_torch_to_the_cpu_build(repo_root):
    pins = (repo_root / "constraints.txt").read_text().splitlines()
    assert "torch==2.13.0" in pins
    assert not any(line.lower().startswith(("nvidia", "cuda")) for line in pins)


def test_params_yaml_is_plain_yaml(repo_root):
    data = yaml.safe_load((repo_root / "params.yaml").read_text())
    assert set(data) >= {"seed", "env", "data", "policy", "benchmark", "anomaly", "detectors"}
