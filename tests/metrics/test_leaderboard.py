"""The suite's leaderboard aggregates, checked against a hand-worked example."""

from __future__ import annotations

import numpy as np
import pytest

from oodrl.metrics.leaderboard import interquartile_mean, leaderboard


def hand_cells() -> dict:
    """8 cells (2 environments × 4 anomalies), 3 episodes each.

    Detector A's cell means are 0.5 everywhere but one cell at 1.0; B is 0.5 everywhere.
    """
    cells = {}
    for env in ("E1", "E2"):
        for anomaly in ("a", "b", "c", "d"):
            a = [1.0, 1.0, 1.0] if (env, anomaly) == ("E2", "d") else [0.4, 0.5, 0.6]
            cells[(env, anomaly)] = {"A": a, "B": [0.5, 0.5, 0.5]}
    return cells


def test_hand_worked_example():
    board = leaderboard(hand_cells(), n_boot=200)
    assert board.detectors == ("A", "B") and board.environments == ("E1", "E2")
    assert board.n_cells == 8
    # Table: mean over an environment's anomalies of the cell means.
    assert board.table["A"] == pytest.approx({"E1": 0.5, "E2": (0.5 * 3 + 1.0) / 4})
    assert board.table["B"] == pytest.approx({"E1": 0.5, "E2": 0.5})
    # Mean of the 8 cell means: (7 × 0.5 + 1.0) / 8; IQM drops the 2 lowest and 2 highest.
    assert board.mean["A"].value == pytest.approx(0.5625)
    assert board.iqm["A"].value == pytest.approx(0.5)
    # P(A > B): one win, seven ties (½ each) over 8 cells.
    assert board.improvement[("A", "B")].value == pytest.approx((1 + 3.5) / 8)
    assert board.improvement[("B", "A")].value == pytest.approx((0 + 3.5) / 8)


def test_cis_come_from_resampling_episodes_within_cells():
    board = leaderboard(hand_cells(), n_boot=500)
    # B never varies within a cell: its intervals collapse to the point.
    assert board.mean["B"].ci_low == board.mean["B"].ci_high == 0.5
    # A varies in 7 cells: the interval is wide but contains the point.
    a = board.mean["A"]
    assert a.ci_low < a.value < a.ci_high
    # The win cell (1.0 > 0.5) is never resampled away: P(A > B) ≥ 1/8 in every replicate.
    assert board.improvement[("A", "B")].ci_low >= 1 / 8


def test_reproducible_and_independent_of_other_cells():
    first = leaderboard(hand_cells(), n_boot=100, seed=3)
    again = leaderboard(hand_cells(), n_boot=100, seed=3)
    assert first == again
    more = hand_cells() | {("E3", "z"): {"A": [0.9], "B": [0.1]}}
    assert leaderboard(more, n_boot=100, seed=3).mean != first.mean


def test_interquartile_mean_matches_scipy_trim_mean():
    from scipy.stats import trim_mean

    values = np.random.default_rng(0).random(37)
    assert interquartile_mean(values) == pytest.approx(trim_mean(values, 0.25))


def test_cells_must_hold_the_same_detectors():
    cells = hand_cells()
    cells[("E1", "a")] = {"A": [0.5]}
    with pytest.raises(ValueError, match="has detectors"):
        leaderboard(cells)
