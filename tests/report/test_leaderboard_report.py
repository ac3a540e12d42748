"""The suite's leaderboard report from per-environment results files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from oodrl import yamlio
from oodrl.errors import StoreError
from oodrl.report.leaderboard import read_cells, run_leaderboard

DETECTORS = ("cusum", "kde_density", "pedm")


def write_results(path: Path, seed: int, strength: dict[str, float]) -> Path:
    rng = np.random.default_rng(seed)
    records = [
        {"kind": "null", "detector": d, "injector": None, "mode": "posthoc", "metrics": {}}
        for d in DETECTORS
    ]
    for anomaly in ("gaussian_state_noise", "stuck_actuator"):
        for d in DETECTORS:
            episodes = np.clip(strength[d] + 0.05 * rng.standard_normal(6), 0, 1)
            records.append({
                "kind": "anomaly", "detector": d, "injector": anomaly, "mode": "posthoc",
                "metrics": {}, "episodes": {"matched_auroc": [float(v) for v in episodes]},
            })  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yamlio.dump({"records": records}))
    return path


@pytest.fixture
def results(tmp_path: Path) -> dict[str, Path]:
    return {
        "CartPole-v1": write_results(
            tmp_path / "a" / "results.yaml", 0, {"cusum": 0.9, "kde_density": 0.6, "pedm": 0.7}
        ),
        "Pendulum-v1": write_results(
            tmp_path / "b" / "results.yaml", 1, {"cusum": 0.8, "kde_density": 0.55, "pedm": 0.9}
        ),
    }


def test_report_files_rank_detectors_and_reproduce(results, tmp_path: Path):
    board = run_leaderboard(results, tmp_path / "out", n_boot=200, ci=0.95, seed=0)
    assert board.n_cells == 4 and board.environments == ("CartPole-v1", "Pendulum-v1")
    table = (tmp_path / "out" / "leaderboard.md").read_text()
    rows = [line.split(" | ")[0].lstrip("| ") for line in table.splitlines()[4:7]]
    assert rows == ["cusum", "pedm", "kde_density"]  # by IQM
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["iqm.cusum"] > metrics["iqm.pedm"] > metrics["iqm.kde_density"]
    assert (tmp_path / "out" / "leaderboard.png").read_bytes()[:4] == b"\x89PNG"
    first = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    run_leaderboard(results, tmp_path / "again", n_boot=200, ci=0.95, seed=0)
    assert first == {p.name: p.read_bytes() for p in (tmp_path / "again").iterdir()}


def test_missing_or_old_results_are_one_line_errors(results, tmp_path: Path):
    with pytest.raises(StoreError, match="results of Hopper-v5 are missing"):
        read_cells({**results, "Hopper-v5": tmp_path / "nowhere.yaml"})
    old = tmp_path / "old.yaml"
    old.write_text(yamlio.dump({"records": [{"kind": "anomaly", "detector": "x", "anomaly": "y"}]}))
    with pytest.raises(StoreError, match="re-run Acrobot-v1's metrics stage"):
        read_cells({"Acrobot-v1": old})
