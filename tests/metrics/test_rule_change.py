"""What the time-aware rule changes: paired stratified bootstrap of the rate difference per
detector, and Kendall's τ between the rules' IQM rankings (constructed detections, exact)."""

from __future__ import annotations

import numpy as np
import pytest

from oodrl.metrics.leaderboard import Cell
from oodrl.metrics.rule_change import rule_change, rule_change_by_tier

STREAMS = 100


def _streams(detected: int) -> np.ndarray:
    """0/1 per stream: the first `detected` streams detected."""
    return (np.arange(STREAMS) < detected).astype(float)


def _cells(tier: str = "mild", n: int = 6) -> tuple[dict, dict]:
    """a: detected in 30 of 100 streams under the constant rule, the same 30 and 50 more
    time-aware (+0.5); b: 50 under both, two streams swapped (+0 exactly); c: 70 unchanged."""
    constant, time_aware = {}, {}
    b = _streams(50)
    swapped = b.copy()
    swapped[[0, STREAMS - 1]] = 1 - swapped[[0, STREAMS - 1]]
    for e in range(n):
        cell = Cell(f"env{e}", "0", "fault", tier)
        constant[cell] = {"a": _streams(30), "b": b, "c": _streams(70)}
        time_aware[cell] = {"a": _streams(80), "b": swapped, "c": _streams(70)}
    return constant, time_aware


def test_a_clear_gain_excludes_zero_and_a_swap_does_not():
    change = rule_change(*_cells(), n_boot=2000, seed=7)
    a, b, c = (change.differences[d] for d in ("a", "b", "c"))
    assert a.mean == pytest.approx(0.5) and a.n_cells == 6
    # 300 of 600 paired streams gain a detection: the replicate mean has sd √(0.25 / 600) = 0.02.
    assert 0.4 < a.ci_low < 0.5 < a.ci_high < 0.6
    assert b.mean == 0 and b.ci_low < 0 < b.ci_high and not b.excludes_zero
    assert (c.mean, c.ci_low, c.ci_high) == (0, 0, 0)
    assert change.changed == ("a",)
    assert change.iqm["constant"] == pytest.approx({"a": 0.3, "b": 0.5, "c": 0.7})
    assert change.iqm["time_aware"] == pytest.approx({"a": 0.8, "b": 0.5, "c": 0.7})
    # a goes from last to first: 1 concordant pair (b, c) and 2 discordant of 3.
    assert change.kendall_tau == pytest.approx(-1 / 3)
    # Seeded: the same seed, the same interval; another seed, another.
    assert rule_change(*_cells(), n_boot=2000, seed=7) == change
    assert rule_change(*_cells(), n_boot=2000, seed=8).differences["a"] != a


def test_identical_rules_leave_the_ranking_alone():
    constant, _ = _cells()
    change = rule_change(constant, constant, n_boot=200)
    assert change.kendall_tau == 1.0
    assert change.changed == ()
    assert all((d.mean, d.ci_low, d.ci_high) == (0, 0, 0) for d in change.differences.values())


def test_cells_are_strata_never_mixed():
    # One cell gains every stream, the other loses every stream: every replicate redraws
    # streams within each cell, so the mean difference is 0 in every replicate; pooling the
    # 200 streams would give a CI of about ±0.14 instead.
    ones, zeros = np.ones(STREAMS), np.zeros(STREAMS)
    gain, loss = Cell("e1", "0", "f", "mild"), Cell("e2", "0", "f", "mild")
    constant = {gain: {"a": zeros, "b": zeros}, loss: {"a": ones, "b": zeros}}
    time_aware = {gain: {"a": ones, "b": zeros}, loss: {"a": zeros, "b": zeros}}
    a = rule_change(constant, time_aware, n_boot=500).differences["a"]
    assert (a.mean, a.ci_low, a.ci_high) == (0, 0, 0)


def test_per_tier_and_inputs_that_do_not_pair():
    constant, time_aware = _cells("mild")
    severe_constant, severe_time_aware = _cells("severe", n=3)
    constant.update(severe_time_aware)  # severe: the rules the other way round
    time_aware.update(severe_constant)
    by_tier = rule_change_by_tier(constant, time_aware, n_boot=300)
    assert list(by_tier) == ["mild", "severe"]
    assert by_tier["mild"] == rule_change(*_cells("mild"), n_boot=300)
    assert by_tier["severe"].differences["a"].mean == pytest.approx(-0.5)
    assert by_tier["severe"].differences["a"].n_cells == 3
    # Rates without their streams: one value per rule and cell, no sampling variance.
    rates = {
        cell: {d: [float(np.mean(v))] for d, v in row.items()} for cell, row in _cells()[0].items()
    }
    assert rule_change(rates, rates, n_boot=10).kendall_tau == 1.0
    fewer = {cell: {d: v[:-1] for d, v in row.items()} for cell, row in _cells()[1].items()}
    with pytest.raises(ValueError, match="same, non-empty streams"):
        rule_change(_cells()[0], fewer)
    ragged = {cell: {**row, "a": row["a"][:-1]} for cell, row in _cells()[1].items()}
    with pytest.raises(ValueError, match="one stream count"):
        rule_change(_cells()[0], ragged)
    with pytest.raises(ValueError, match="same"):
        rule_change(_cells()[0], _cells("severe")[1])
