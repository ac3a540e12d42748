"""Each script of examples/ runs as a user runs it (a fresh process, from another directory);
`oodrl.evaluate` at its "tiny" size (OODRL_EVALUATE_SIZE) so that CI runs them in seconds."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


def run_example(repo_root, tmp_path, name: str, *args: str) -> str:
    env = {**os.environ, "OODRL_EVALUATE_SIZE": "tiny", "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [sys.executable, str(repo_root / "examples" / name), *args],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, f"{name} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def test_leaderboard_ranking_plots_the_tiers_ranking(repo_root, tmp_path):
    out = tmp_path / "figures"
    stdout = run_example(repo_root, tmp_path, "leaderboard_ranking.py", "--tier", "moderate",
                         "--out", str(out))  # fmt: skip
    figure = out / "ranking_moderate_detection_rate_at_100.png"
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    board = json.loads((repo_root / "pipeline/suite/reports/leaderboard.json").read_text())
    iqm = board["iqm"]["detection_rate@100"]["moderate"]
    best = max(iqm, key=lambda d: iqm[d]["value"])
    ranking = stdout.splitlines()[1:]  # under the header: best first
    assert ranking[0].split()[0] == best
    assert f"wrote {figure}" in stdout


@pytest.mark.slow
def test_evaluate_detector_checks_and_evaluates_your_class(repo_root, tmp_path):
    stdout = run_example(repo_root, tmp_path, "evaluate_detector.py")
    assert "MaxAbsZScore passes the detector contract" in stdout
    assert "on CartPole (tiny size: 10 faulty streams a cell)" in stdout
    assert "MaxAbsZScore (yours)" in stdout and "µs per step" in stdout


def test_live_monitor_watches_a_live_fault(repo_root, tmp_path):
    stdout = run_example(repo_root, tmp_path, "live_monitor.py")
    assert "1. oodrl.run_monitor: cusum watching CartPole-v1, dynamics_scaling" in stdout
    assert "false alarms before the onset" in stdout  # run_monitor's summary line
    assert "2. oodrl.OodMonitor around gym's CartPole-v1" in stdout
    assert "episode over after" in stdout
