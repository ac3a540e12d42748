"""The leaderboard's statistics, checked against hand-worked examples."""

from __future__ import annotations

import numpy as np
import pytest

from oodrl.metrics.leaderboard import (
    Cell,
    aggregate,
    build_board,
    detector_scopes,
    fault_family,
    interquartile_mean,
    metric_order,
    ranking_stability,
    tier_order,
    trivial_flags,
)


def hand_cells() -> dict:
    """8 cells (2 environments × 4 anomalies), one policy, 3 episodes each.

    Detector A's cell means are 0.5 everywhere but one cell at 1.0; B is 0.5 everywhere.
    """
    cells = {}
    for env in ("E1", "E2"):
        for anomaly in ("a", "b", "c", "d"):
            a = [1.0, 1.0, 1.0] if (env, anomaly) == ("E2", "d") else [0.4, 0.5, 0.6]
            cells[Cell(env, "0", anomaly, "headline")] = {"A": a, "B": [0.5, 0.5, 0.5]}
    return cells


def test_hand_worked_example():
    board = aggregate(hand_cells(), n_boot=200)
    assert board.detectors == ("A", "B") and board.environments == ("E1", "E2")
    assert board.n_cells == 8 and board.runs == (1,) * 8 and board.bootstrap == "episodes"
    # Table: mean over an environment's anomalies of the cell means.
    assert board.table["A"] == pytest.approx({"E1": 0.5, "E2": (0.5 * 3 + 1.0) / 4})
    assert board.table["B"] == pytest.approx({"E1": 0.5, "E2": 0.5})
    # Mean of the 8 cell means: (7 × 0.5 + 1.0) / 8; IQM drops the 2 lowest and 2 highest.
    assert board.mean["A"].value == pytest.approx(0.5625)
    assert board.iqm["A"].value == pytest.approx(0.5)
    assert board.optimality_gap["A"].value == pytest.approx(1 - 0.5625)
    # P(A > B): one win, seven ties (½ each) over 8 cells.
    assert board.improvement[("A", "B")].value == pytest.approx((1 + 3.5) / 8)
    assert board.improvement[("B", "A")].value == pytest.approx((0 + 3.5) / 8)
    assert board.ranked() == ["A", "B"]


def test_cis_come_from_resampling_episodes_within_cells():
    board = aggregate(hand_cells(), n_boot=500)
    # B never varies within a cell: its intervals collapse to the point.
    assert board.mean["B"].ci_low == board.mean["B"].ci_high == 0.5
    # A varies in 7 cells: the interval is wide but contains the point.
    a = board.mean["A"]
    assert a.ci_low < a.value < a.ci_high
    # The win cell (1.0 > 0.5) is never resampled away: P(A > B) ≥ 1/8 in every replicate.
    assert board.improvement[("A", "B")].ci_low >= 1 / 8


def test_reproducible_and_seeded():
    first = aggregate(hand_cells(), n_boot=100, seed=3)
    assert first == aggregate(hand_cells(), n_boot=100, seed=3)
    assert aggregate(hand_cells(), n_boot=100, seed=4).mean != first.mean
    more = hand_cells() | {Cell("E3", "0", "z", "headline"): {"A": [0.9], "B": [0.1]}}
    assert aggregate(more, n_boot=100, seed=3).mean != first.mean


def two_run_cells() -> dict:
    """2 tasks × 2 policies: A's run scores (0.9, 0.7), (0.6, 0.8); B's (0.8, 0.8), (0.6, 0.6)."""
    a = {("t1", "0"): [0.9], ("t1", "1"): [0.8, 0.6], ("t2", "0"): [0.6], ("t2", "1"): [0.8]}
    b = {("t1", "0"): [0.8], ("t1", "1"): [0.8], ("t2", "0"): [0.6], ("t2", "1"): [0.6]}
    return {Cell("E", p, f, "mild"): {"A": a[(f, p)], "B": b[(f, p)]} for f, p in a}


def test_runs_are_policies_mann_whitney_over_runs_averaged_over_cells():
    board = aggregate(two_run_cells(), n_boot=300)
    assert board.runs == (2, 2) and board.bootstrap == "runs" and board.n_scores == 4
    # A's scores: t1 (0.9, 0.7), t2 (0.6, 0.8). B's: t1 (0.8, 0.8), t2 (0.6, 0.6).
    # t1: 0.9 > both 0.8 (2 wins), 0.7 < both: 2/4. t2: 0.6 ties both (2 × ½), 0.8 wins twice: 3/4.
    assert board.improvement[("A", "B")].value == pytest.approx((2 / 4 + 3 / 4) / 2)
    assert board.improvement[("B", "A")].value == pytest.approx((2 / 4 + 1 / 4) / 2)
    # IQM of the pool (0.9, 0.7, 0.6, 0.8): the middle two, 0.7 and 0.8.
    assert board.iqm["A"].value == pytest.approx(0.75)
    assert board.mean["A"].value == pytest.approx(0.75)
    # Resampling runs: B's t1 runs are equal, t2 too: B's mean never moves.
    assert board.mean["B"].ci_low == pytest.approx(0.7) == board.mean["B"].ci_high
    assert board.mean["A"].ci_low < 0.75 < board.mean["A"].ci_high


def test_one_run_cells_fall_back_to_episodes_and_say_so():
    cells = two_run_cells() | {Cell("F", "0", "t1", "mild"): {"A": [0.5, 0.7], "B": [0.2, 0.4]}}
    board = aggregate(cells, n_boot=100)
    assert board.runs == (2, 2, 1)
    assert board.bootstrap == "runs; episodes in 1 of 3 cells with one run"


def test_profile_and_optimality_gap():
    cells = {
        Cell("E", "0", f, "mild"): {"A": [v], "B": [0.5]}
        for f, v in zip("wxyz", (1.0, 0.95, 0.8, 0.6), strict=True)
    }
    board = aggregate(cells, n_boot=50, taus=(0.5, 0.9, 1.0))
    assert board.optimality_gap["A"].value == pytest.approx(1 - (1.0 + 0.95 + 0.8 + 0.6) / 4)
    assert [p.value for p in board.profile["A"]] == [1.0, 0.5, 0.25]  # share ≥ τ
    assert [p.value for p in board.profile["B"]] == [1.0, 0.0, 0.0]


def test_interquartile_mean_matches_scipy_trim_mean():
    from scipy.stats import trim_mean

    values = np.random.default_rng(0).random(37)
    assert interquartile_mean(values) == pytest.approx(trim_mean(values, 0.25))


def test_cells_must_hold_the_same_detectors():
    cells = hand_cells()
    cells[Cell("E1", "0", "a", "headline")] = {"A": [0.5]}
    with pytest.raises(ValueError, match="has detectors"):
        aggregate(cells)


def test_a_detector_that_runs_on_some_cells_is_ranked_only_where_it_runs():
    """C runs on E1's cells only, D on E1/a and E1/b only: the lead board ranks A and B on
    every cell; each larger detector set is ranked over the cells that have all of it."""
    cells = hand_cells()
    for cell, values in cells.items():
        if cell.environment == "E1":
            values["C"] = [0.9, 0.9, 0.9]
        if cell.environment == "E1" and cell.fault in ("a", "b"):
            values["D"] = [0.2, 0.3, 0.4]
    every, with_d, with_c = detector_scopes(cells)
    assert set(every) == set(cells) and {tuple(v) for v in every.values()} == {("A", "B")}
    assert {(c.environment, c.fault) for c in with_d} == {("E1", "a"), ("E1", "b")}
    assert {tuple(v) for v in with_d.values()} == {("A", "B", "C", "D")}
    assert {c.environment for c in with_c} == {"E1"} and len(with_c) == 4
    assert {tuple(v) for v in with_c.values()} == {("A", "B", "C")}
    board = build_board({"matched_auroc": cells}, n_boot=200)
    key = ("matched_auroc", "headline")
    assert board.overall[key] == aggregate(every, n_boot=200)
    assert board.scoped[key] == (aggregate(with_d, n_boot=200), aggregate(with_c, n_boot=200))
    scope = board.scoped[key][1]
    # On E1, A's and B's cell means are all 0.5 and C's 0.9: ranked over the same four cells.
    assert scope.ranked() == ["C", "A", "B"] and scope.iqm["C"].value == pytest.approx(0.9)
    assert build_board({"matched_auroc": hand_cells()}, n_boot=200).scoped == {}
    with pytest.raises(ValueError, match="no detector has values on every cell"):
        detector_scopes({Cell("E1", "0", "a", "mild"): {"A": [1.0]},
                         Cell("E1", "0", "b", "mild"): {"B": [1.0]}})  # fmt: skip


def test_ranking_stability_across_policies():
    cells = {}
    for f in "abcd":
        cells[Cell("E", "0", f, "mild")] = {"A": [0.9], "B": [0.7], "C": [0.5]}
        cells[Cell("E", "1", f, "mild")] = {"A": [0.5], "B": [0.7], "C": [0.9]}
        cells[Cell("E", "2", f, "mild")] = {"A": [0.9], "B": [0.8], "C": [0.5]}
    stability = ranking_stability(cells)
    assert stability.policies == ("0", "1", "2")
    assert stability.winners == {"0": "A", "1": "C", "2": "A"}
    assert stability.kendall_tau == pytest.approx({("0", "1"): -1.0, ("0", "2"): 1.0,
                                                   ("1", "2"): -1.0})  # fmt: skip
    assert stability.mean_tau == pytest.approx(-1 / 3)
    one = ranking_stability({c: v for c, v in cells.items() if c.policy == "0"})
    assert one.policies == ("0",) and one.kendall_tau == {} and one.mean_tau is None


def test_ranking_stability_compares_policies_on_the_tasks_they_share():
    """An environment with one policy must not enter the comparison: policy 0's ranking on E
    and F against policy 1's on E alone would measure F, not the policies."""
    cells = {}
    for f in "ab":
        cells[Cell("E", "0", f, "mild")] = {"A": [0.9], "B": [0.5]}
        cells[Cell("E", "1", f, "mild")] = {"A": [0.8], "B": [0.6]}
        cells[Cell("F", "0", f, "mild")] = {"A": [0.0], "B": [1.0]}
    cells[Cell("E", "1", "c", "mild")] = {"A": [0.0], "B": [1.0]}  # policy 1 alone reached c
    stability = ranking_stability(cells)
    assert stability.tasks == (("E", "a", "mild"), ("E", "b", "mild"))
    assert stability.winners == {"0": "A", "1": "A"}
    assert stability.kendall_tau == pytest.approx({("0", "1"): 1.0})
    apart = {c: v for c, v in cells.items() if c.environment == "F" or c.policy == "1"}
    alone = ranking_stability(apart)
    assert alone.tasks == () and alone.kendall_tau == {} and alone.mean_tau is None


def test_trivial_flags_rule():
    cells = {
        Cell("E", "0", "a", "mild"): {"A": [0.6], "time_index": [0.95, 0.93]},
        Cell("E", "1", "a", "mild"): {"A": [0.6], "time_index": [0.91]},
        Cell("E", "0", "b", "mild"): {"A": [0.6], "time_index": [0.7]},
        Cell("F", "0", "a", "mild"): {"A": [0.6], "time_index": [0.99], "episode_return": [1.0]},
    }
    flagged = trivial_flags(cells)
    assert flagged == {
        ("E", "a", "mild"): {"time_index": pytest.approx((0.94 + 0.91) / 2)},
        ("F", "a", "mild"): {"time_index": 0.99, "episode_return": 1.0},
    }
    assert trivial_flags({c: {"A": v["A"]} for c, v in cells.items()}) == {}


def test_board_leads_with_mild_and_detection_rate_by_family():
    cells_auroc, cells_rate = {}, {}
    rng = np.random.default_rng(0)
    for tier in ("severe", "mild"):
        for fault in ("gaussian_state_noise", "stuck_actuator", "gradual_drift", "my_plugin"):
            cell = Cell("E", "0", fault, tier)
            trivial = [0.95] * 4 if fault == "gradual_drift" else [0.5] * 4
            cells_auroc[cell] = {"A": list(rng.random(4)), "B": list(rng.random(4)),
                                 "time_index": trivial}  # fmt: skip
            cells_rate[cell] = {d: [1.0, 0.0, 1.0, 1.0] for d in cells_auroc[cell]}
    board = build_board({"matched_auroc": cells_auroc, "detection_rate@100": cells_rate}, n_boot=50)
    assert board.lead == ("detection_rate@100", "mild")
    assert board.tiers == ("mild", "severe")
    assert list(board.families[board.lead]) == ["observation", "action", "dynamics", "other"]
    assert set(board.flagged) == {("E", "gradual_drift", "mild"), ("E", "gradual_drift", "severe")}
    assert board.unflagged[("matched_auroc", "mild")].n_cells == 3


def test_orders_and_families():
    assert tier_order(["headline", "benign", "severe", "mild", "moderate"]) == [
        "mild", "moderate", "severe", "benign", "headline"
    ]  # fmt: skip
    assert metric_order(["matched_auroc", "detection_rate@100"])[0] == "detection_rate@100"
    assert fault_family("correlation_break") == "observation"
    assert fault_family("action_conditioned_dynamics") == "action"
    assert fault_family("gradual_drift") == "dynamics"
    assert fault_family("my_plugin") == "other"


@pytest.mark.parametrize("runs", [2, 3, 5])
def test_replicate_wins_from_draw_counts_equal_comparing_the_drawn_scores(runs):
    from oodrl.metrics.leaderboard import _mann_whitney, _replicate_wins, _replicates

    rng = np.random.default_rng(runs)
    # Scores on a coarse grid, so that ties between detectors' runs are common.
    task = [{d: rng.integers(0, 5, size=4) / 4 for d in "abcd"} for _ in range(runs)]
    replicates, counts = _replicates(task, tuple("abcd"), 300, np.random.default_rng(1))
    scores = np.array([[run[d].mean() for run in task] for d in "abcd"])
    direct = _mann_whitney(replicates[:, None], replicates[None, :])
    assert np.array_equal(_replicate_wins(scores, replicates, counts), direct)
    assert counts.sum(axis=-1).tolist() == [[runs] * 300] * 4
