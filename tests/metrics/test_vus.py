"""VUS-PR (SPEC §20): a hand-worked example, its properties, and a brute-force oracle written
the way TSB-AD's `RangeAUC_volume_opt` loops (one prediction per threshold, labels rebuilt)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.metrics import average_precision_score

from oodrl.config import MetricsConfig
from oodrl.errors import ContractError
from oodrl.metrics.aggregate import VUS_PR, EpisodeBatch
from oodrl.metrics.ranking import (
    average_precision,
    buffered_ranges,
    label_ranges,
    range_average_precision,
    soft_labels,
    vus_pr,
    vus_pr_rows,
)

LABELS = np.array([0, 0, 0, 1, 1, 0, 0, 0], dtype=bool)
SCORES = np.array([0.1, 0.2, 0.6, 0.9, 0.4, 0.8, 0.3, 0.0])


def test_hand_worked_example():
    """T = 8, one anomaly range {3, 4}; thresholds high to low visit steps 3, 5, 2, 4, 6, 1,
    0, 7 (scores 0.9, 0.8, 0.6, 0.4, …).

    Buffers 0 and 1 (⌊w/2⌋ = 0: no softening) give the plain average precision: step 3 is
    found first (TPR ½, precision 1), step 4 fourth (TPR 1, precision 2/4):
        AP_0 = AP_1 = ½·1 + ½·½ = 0.75.
    Buffer 2 softens one step on each side, steps 2 and 5, to a = √(1 − 1/2) = 1/√2; the
    range widened by one step, [2, 6), is found from the first threshold on (existence 1).
    With TP = inside + buffer mass predicted and P' = 2 + ½·(buffer mass predicted):
        θ = 0.9 (step 3): TP = 1,       P' = 2,        TPR = ½,                  prec = 1
        θ = 0.8 (step 5): TP = 1 + a,   P' = 2 + a/2,  TPR = (1 + a)/(2 + a/2),  prec = (1 + a)/2
        θ = 0.6 (step 2): TP = 1 + 2a,  P' = 2 + a,    TPR = (1 + 2a)/(2 + a),   prec = (1 + 2a)/3
        θ = 0.4 (step 4): TP = 2 + 2a,  P' = 2 + a,    TPR = min(·, 1) = 1,      prec = (2 + 2a)/4
    and TPR stays 1 after. AP_2 = Σ ΔTPR · prec = 0.5 + 0.19233 + 0.13397 + 0.09235 = 0.91865,
    and VUS-PR with B = 2 = (0.75 + 0.75 + 0.91865)/3 = 0.80622.
    """
    a = 1 / math.sqrt(2)
    tpr = [0.5, (1 + a) / (2 + a / 2), (1 + 2 * a) / (2 + a), 1.0]
    precision = [1.0, (1 + a) / 2, (1 + 2 * a) / 3, (2 + 2 * a) / 4]
    ap_2 = sum((t - s) * p for t, s, p in zip(tpr, [0.0, *tpr[:-1]], precision, strict=True))
    assert ap_2 == pytest.approx(0.91865, abs=5e-6)
    assert range_average_precision(SCORES, LABELS, 0) == pytest.approx(0.75, abs=1e-15)
    assert range_average_precision(SCORES, LABELS, 1) == pytest.approx(0.75, abs=1e-15)
    assert range_average_precision(SCORES, LABELS, 2) == pytest.approx(ap_2, abs=1e-14)
    assert vus_pr(SCORES, LABELS, buffer=2) == pytest.approx((1.5 + ap_2) / 3, abs=1e-14)
    assert vus_pr(SCORES, LABELS, buffer=2) == pytest.approx(0.80622, abs=5e-6)


def test_a_perfect_detector_scores_one_at_every_buffer():
    labels = np.zeros(60, dtype=bool)
    labels[10:15] = labels[30:42] = True
    scores = np.where(labels, 2.0, 0.0) + np.linspace(0, 1, 60)  # anomalies all above the rest
    for buffer in (0, 1, 4, 10, 30):
        assert vus_pr(scores, labels, buffer) == 1.0


def test_buffer_zero_is_the_average_precision_for_one_range():
    rng = np.random.default_rng(0)
    labels = np.zeros(200, dtype=bool)
    labels[70:130] = True
    for _ in range(20):
        scores = rng.standard_normal(200) + labels * rng.uniform(0, 2)
        expected = average_precision_score(labels, scores)
        assert vus_pr(scores, labels, buffer=0) == pytest.approx(expected, abs=1e-12)
        assert average_precision(scores, labels) == pytest.approx(expected, abs=1e-12)


def test_buffer_zero_with_several_ranges_weights_recall_by_the_ranges_found():
    # Two ranges of two steps; TPR = recall × (share of ranges found). Thresholds 8, 7, 6, 5,
    # 3, 2 (then 1, 0: nothing new): recall ¼, ½, ½, ¾, ¾, 1 with ranges found ½, ½, ½, 1, 1, 1,
    # so TPR ⅛, ¼, ¼, ¾, ¾, 1; precision 1, 1, ⅔, ¾, ⅗, ⅔.
    labels = np.array([1, 1, 0, 0, 1, 1, 0, 0], dtype=bool)
    scores = np.array([8, 7, 1, 0, 5, 2, 6, 3], dtype=float)
    expected = 0.125 * 1 + 0.125 * 1 + 0.5 * 0.75 + 0.25 * (4 / 6)
    assert vus_pr(scores, labels, buffer=0) == pytest.approx(expected, abs=1e-15)
    # The plain average precision, (1 + 1 + ¾ + ⅔)/4, credits the first range's steps fully.
    assert average_precision(scores, labels) == pytest.approx((2 + 0.75 + 4 / 6) / 4)


def test_constant_scores_and_no_positive():
    labels = np.array([0, 0, 1, 1, 0, 0], dtype=bool)
    assert vus_pr(np.ones(6), labels, buffer=0) == pytest.approx(2 / 6)
    assert vus_pr(np.arange(6.0), np.zeros(6, dtype=bool), buffer=4) == 0.0


def test_buffered_ranges_merge_only_when_they_overlap():
    labels = np.array([0, 1, 0, 0, 1, 0, 0, 0, 0, 1], dtype=bool)
    assert buffered_ranges(labels, 0) == [(1, 2), (4, 5), (9, 10)]
    # Widened by 1: [0, 3) and [3, 6) touch but share no step; [8, 10) is clipped at T.
    assert buffered_ranges(labels, 1) == [(0, 3), (3, 6), (8, 10)]
    assert buffered_ranges(labels, 2) == [(0, 7), (7, 10)]


def test_rows_and_the_metric_use_the_temporal_buffer():
    rng = np.random.default_rng(1)
    labels = np.zeros((3, 50), dtype=bool)
    labels[:, 20:] = True
    perturbed = rng.standard_normal((3, 50)) + labels
    rows = vus_pr_rows(perturbed, labels, 6)
    assert rows.tolist() == [vus_pr(s, y, 6) for s, y in zip(perturbed, labels, strict=True)]
    batch = EpisodeBatch(perturbed, perturbed, labels, threshold=1.0, onset=20)
    values = VUS_PR.compute(batch, MetricsConfig(temporal_buffer=6))
    np.testing.assert_array_equal(values, rows)
    assert VUS_PR.higher_is_better


def test_bad_inputs():
    with pytest.raises(ContractError, match="buffer"):
        vus_pr(SCORES, LABELS, buffer=-1)
    with pytest.raises(ContractError, match="one length"):
        range_average_precision(SCORES, LABELS[:-1], 0)


def _tsb_ad_loop(scores: np.ndarray, labels: np.ndarray, window: int) -> float:
    """One window of TSB-AD's surface, written as its loop (every distinct score a threshold):
    the extended labels multiplied by the prediction inside the widened ranges, 1 on the
    anomaly ranges; P' = (P + Σ labels)/2; existence over the widened ranges."""
    positives = labels.sum()
    extended = soft_labels(labels, window)
    widened = buffered_ranges(labels, window // 2)
    tpr_before, area = 0.0, 0.0
    for threshold in np.unique(scores)[::-1]:
        pred = scores >= threshold
        rebuilt = extended.copy()
        for a, b in widened:
            rebuilt[a:b] = extended[a:b] * pred[a:b]
        for a, b in label_ranges(labels):
            rebuilt[a:b] = 1.0
        tp = float(np.dot(rebuilt, pred))
        p_new = (positives + rebuilt.sum()) / 2
        existence = sum(pred[a:b].any() for a, b in widened) / len(widened)
        tpr = min(tp / p_new, 1.0) * existence
        area += (tpr - tpr_before) * tp / pred.sum()
        tpr_before = tpr
    return area


#: A stream's scores (few distinct values: many ties), labels and a label buffer.
STREAMS = (
    st.lists(st.integers(0, 9), min_size=4, max_size=60),
    st.lists(st.booleans(), min_size=4, max_size=60),
    st.integers(0, 12),
)


def _stream(values: list[int], flags: list[bool]) -> tuple[np.ndarray, np.ndarray]:
    """Scores (divided by 7: inexact values too) and labels of one length."""
    n = min(len(values), len(flags))
    return np.array(values[:n], dtype=float) / 7, np.array(flags[:n])


@settings(max_examples=60, deadline=None)
@given(*STREAMS)
def test_matches_the_reference_loop(values, flags, window):
    scores, labels = _stream(values, flags)
    if not labels.any():
        assert range_average_precision(scores, labels, window) == 0.0
        return
    expected = _tsb_ad_loop(scores, labels, window)
    assert range_average_precision(scores, labels, window) == pytest.approx(expected, abs=1e-12)


def test_vus_pr_is_computed_only_where_params_opt_in():
    """The root's results keep the paper's metrics; the suite's params add VUS-PR (SPEC §20)."""
    from oodrl.config import MetricsConfig
    from oodrl.metrics.aggregate import episode_metrics

    rng = np.random.default_rng(0)
    scores, labels = rng.normal(size=(3, 40)), np.zeros((3, 40), dtype=bool)
    labels[:, 20:] = True
    args = (scores + labels, scores, labels, 1.0, 20, None)
    assert "vus_pr" not in episode_metrics(*args, MetricsConfig())
    opted = episode_metrics(*args, MetricsConfig(extra=["vus_pr"]))
    assert opted["vus_pr"].shape == (3,) and np.all((opted["vus_pr"] > 0) & (opted["vus_pr"] <= 1))


@settings(max_examples=60, deadline=None)
@given(*STREAMS)
def test_buffers_computed_together_are_the_bits_of_each_alone(values, flags, window):
    """VUS-PR computes its buffers together, one row each, and rows of equal labels share their
    soft labels: every value must be the same bits as one buffer of one stream alone."""
    scores, labels = _stream(values, flags)
    alone = [
        np.mean([range_average_precision(s, labels, w) for w in range(window + 1)])
        for s in (scores, scores[::-1])
    ]
    assert np.float64(vus_pr(scores, labels, window)).tobytes() == alone[0].tobytes()
    rows = vus_pr_rows(np.stack([scores, scores[::-1]]), np.stack([labels, labels]), window)
    assert rows.tobytes() == np.array(alone).tobytes()
