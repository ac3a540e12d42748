"""The environment suite: every committed policy meets its SPEC §11 bar on unseen seeds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.suite import PIPELINE_DIRS, POLICY_BARS, policy_path

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = [env for env in PIPELINE_DIRS if policy_path(env, ROOT).is_file()]


def test_every_environment_of_the_suite_has_a_bar_and_a_params_file():
    assert set(POLICY_BARS) == set(PIPELINE_DIRS)
    for env_id, directory in PIPELINE_DIRS.items():
        assert (ROOT / directory / "params.yaml").is_file(), env_id


@pytest.mark.parametrize("env_id", COMMITTED)
def test_committed_policy_report_meets_the_bar(env_id):
    report = json.loads(policy_path(env_id, ROOT).with_suffix(".json").read_text())
    assert report["env_id"] == env_id
    assert report["evaluation"]["episodes"] == 30
    assert report["evaluation"]["mean"] >= POLICY_BARS[env_id]


@pytest.mark.slow
@pytest.mark.parametrize("env_id", COMMITTED)
def test_evaluate_policy_on_unseen_seeds_meets_the_bar(env_id, monkeypatch):
    monkeypatch.chdir(ROOT)
    result = CliRunner().invoke(
        app, ["evaluate-policy", "--env", env_id, "--episodes", "30", "--seed", "2000000"]
    )
    assert result.exit_code == 0, result.output
    assert "bar" in result.output and "met" in result.output and "NOT met" not in result.output


def test_an_unknown_environment_is_a_one_line_error(monkeypatch):
    monkeypatch.chdir(ROOT)
    result = CliRunner().invoke(app, ["evaluate-policy", "--env", "CartPole-v2"])
    assert result.exit_code == 2
    assert "Did you mean 'CartPole-v1'?" in result.output
    assert result.output.strip().count("\n") == 0
