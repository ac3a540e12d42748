"""Ranking metrics against scikit-learn and against hand-worked and reference computations."""

import math
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from sklearn.metrics import average_precision_score, roc_auc_score, roc_curve

from oodrl.errors import ContractError
from oodrl.metrics.ranking import (
    auroc,
    auroc_rows,
    average_precision,
    average_precision_rows,
    fpr_at_tpr_rows,
    label_ranges,
    soft_labels,
    temporal_auroc,
    temporal_auroc_rows,
)

# Few distinct values so that ties are common.
tied_scores = st.integers(0, 4).map(float) | st.floats(-1e3, 1e3, allow_nan=False)


@st.composite
def scored_rows(draw, max_rows=4, max_len=25):
    n_rows = draw(st.integers(1, max_rows))
    n = draw(st.integers(2, max_len))
    scores = draw(arrays(np.float64, (n_rows, n), elements=tied_scores))
    labels = draw(arrays(np.bool_, (n_rows, n)))
    return scores, labels


@settings(max_examples=60, deadline=None)
@given(scored_rows())
def test_auroc_rows_matches_sklearn_with_ties(rows):
    scores, labels = rows
    result = auroc_rows(scores, labels)
    for s, y, value in zip(scores, labels, result, strict=True):
        expected = roc_auc_score(y, s) if 0 < y.sum() < y.size else 0.5
        assert value == pytest.approx(expected, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(scored_rows())
def test_average_precision_rows_matches_sklearn(rows):
    scores, labels = rows
    result = average_precision_rows(scores, labels)
    for s, y, value in zip(scores, labels, result, strict=True):
        expected = average_precision_score(y, s) if y.any() else 0.0
        assert value == pytest.approx(expected, abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(scored_rows(max_rows=3, max_len=15))
def test_masked_rows_equal_sklearn_on_the_selected_entries(rows):
    # Matched metrics: positives z̃[P] against negatives z[P] inside one [z̃ | z] row.
    perturbed, labels = rows
    clean = perturbed[:, ::-1] * 0.5
    nothing = np.zeros_like(labels)
    scores = np.concatenate([perturbed, clean], axis=1)
    positive = np.concatenate([labels, nothing], axis=1)
    negative = np.concatenate([nothing, labels], axis=1)
    aurocs = auroc_rows(scores, positive, negative)
    aps = average_precision_rows(scores, positive, negative)
    for i, y in enumerate(labels):
        if not y.any():
            assert aurocs[i] == 0.5
            continue
        s = np.concatenate([perturbed[i][y], clean[i][y]])
        truth = np.r_[np.ones(y.sum()), np.zeros(y.sum())]
        assert aurocs[i] == pytest.approx(roc_auc_score(truth, s), abs=1e-12)
        assert aps[i] == pytest.approx(average_precision_score(truth, s), abs=1e-12)


def test_auroc_degenerate_cases_are_half():
    assert auroc([1.0, 2.0, 3.0], [True, True, True]) == 0.5
    assert auroc([1.0, 2.0, 3.0], [False, False, False]) == 0.5
    assert auroc([2.0, 2.0, 2.0, 2.0], [False, True, False, True]) == 0.5
    assert auroc([0.0, 1.0], [False, True]) == 1.0
    assert auroc([1.0, 0.0], [False, True]) == 0.0


def test_average_precision_degenerate_cases():
    assert average_precision([1.0, 2.0], [False, False]) == 0.0
    # Constant scores: one threshold, precision = the positive fraction.
    assert average_precision([3.0, 3.0, 3.0, 3.0], [True, False, False, False]) == 0.25


def test_masks_must_not_overlap():
    with pytest.raises(ContractError, match="both"):
        auroc_rows([[1.0, 2.0]], [[True, False]], [[True, True]])


def test_fpr95_hand_worked():
    positives = np.arange(10, 0, -1, dtype=float)  # 10 … 1
    negatives = np.array([0.0, 0.5, 1.0, 2.0])
    scores = np.concatenate([positives, negatives])[None, :]
    positive = np.r_[np.ones(10, bool), np.zeros(4, bool)][None, :]
    # 95% of 10 positives = 9.5: the 9 above τ = 1 and half of the one at τ; the negative 2.0
    # is above τ, the negative 1.0 tied with it counts half: (1 + 0.5) / 4.
    assert fpr_at_tpr_rows(scores, positive, ~positive, 0.95)[0] == 0.375
    # 80% -> the 8th largest positive, τ = 3: no negative reaches it.
    assert fpr_at_tpr_rows(scores, positive, ~positive, 0.8)[0] == 0.0
    # A tie with τ counts as a false alarm.
    assert fpr_at_tpr_rows(scores, positive, ~positive, 0.9)[0] == 0.25


def test_fpr95_degenerate_cases():
    scores = np.array([[1.0, 2.0, 3.0]])
    none = np.zeros_like(scores, dtype=bool)
    assert fpr_at_tpr_rows(scores, none, ~none, 0.95)[0] == 0.95
    assert fpr_at_tpr_rows(scores, ~none, none, 0.9)[0] == 0.9
    # Constant scores are uninformative: the randomised threshold gives the target, not 1.
    constant = np.full((1, 4), 7.0)
    positive = np.array([[1, 1, 0, 0]], bool)
    assert fpr_at_tpr_rows(constant, positive, ~positive, 0.95)[0] == pytest.approx(0.95)
    with pytest.raises(ContractError, match="tpr_target"):
        fpr_at_tpr_rows(scores, none, ~none, 0.0)


def test_fpr95_ties_at_a_score_floor_count_as_a_fraction():
    # The CUSUM case of issue 15: 18 of 20 positives well above a floor of 0, 2 positives and
    # every negative at the floor. "≥ τ" with τ = 0 would flag every negative (FPR 1.0).
    positives = np.r_[np.arange(1.0, 19.0), 0.0, 0.0]
    negatives = np.zeros(20)
    scores = np.concatenate([positives, negatives])[None, :]
    positive = np.r_[np.ones(20, bool), np.zeros(20, bool)][None, :]
    # 95% of 20 = 19 positives: the 18 above the floor and half of the 2 tied ones, so half of
    # the tied negatives count: FPR = 0.5.
    assert fpr_at_tpr_rows(scores, positive, ~positive, 0.95)[0] == pytest.approx(0.5)
    # 90% = 18 positives: reached without the floor, no negative flagged.
    assert fpr_at_tpr_rows(scores, positive, ~positive, 0.9)[0] == 0.0


def interpolated_fpr(labels: np.ndarray, scores: np.ndarray, target: float) -> float:
    """FPR at TPR `target` on scikit-learn's ROC curve, linear between its points."""
    fpr, tpr, _ = roc_curve(labels, scores, drop_intermediate=False)
    i = int(np.argmax(tpr >= target - 1e-12))
    if tpr[i] <= target + 1e-12:
        return float(fpr[i])
    share = (target - tpr[i - 1]) / (tpr[i] - tpr[i - 1])
    return float(fpr[i - 1] + share * (fpr[i] - fpr[i - 1]))


@settings(max_examples=80, deadline=None)
@given(scored_rows(max_rows=3, max_len=30), st.sampled_from([0.5, 0.9, 0.95, 1.0]))
def test_fpr_at_tpr_matches_the_interpolated_roc_curve(rows, target):
    scores, labels = rows
    result = fpr_at_tpr_rows(scores, labels, ~labels, target)
    for s, y, value in zip(scores, labels, result, strict=True):
        if not 0 < y.sum() < y.size:
            continue
        assert value == pytest.approx(interpolated_fpr(y, s, target), abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(scored_rows(max_rows=3, max_len=30))
def test_fpr95_of_an_uninformative_tie_is_never_worse_than_chance(rows):
    # Scores that cannot tell positives from negatives, all tied: exactly the target.
    scores, labels = rows
    tied = np.zeros_like(scores)
    result = fpr_at_tpr_rows(tied, labels, ~labels, 0.95)
    np.testing.assert_allclose(result, 0.95)


def test_label_ranges_and_soft_labels():
    labels = np.zeros(12, bool)
    labels[5:8] = True
    assert label_ranges(labels) == [(5, 8)]
    soft = soft_labels(labels, buffer=4)
    expected = np.zeros(12)
    expected[5:8] = 1.0
    expected[[4, 8]] = math.sqrt(1 - 1 / 4)
    expected[[3, 9]] = math.sqrt(1 - 2 / 4)
    np.testing.assert_allclose(soft, expected)
    np.testing.assert_array_equal(soft_labels(labels, buffer=1), labels.astype(float))
    # Ramps of neighbouring ranges add up and are capped at 1.
    close = np.array([1, 0, 0, 1], bool)
    np.testing.assert_allclose(soft_labels(close, 4), [1.0, 1.0, 1.0, 1.0])


def reference_range_auc(scores, labels, buffer):
    """A direct loop over thresholds following Paparrizos et al.'s R-AUC definition."""
    soft = soft_labels(labels, buffer)
    p_new = (labels.sum() + soft.sum()) / 2
    n_new = len(labels) - p_new
    ranges = label_ranges(soft > 0)
    points = [(0.0, 0.0)]
    for threshold in sorted(set(scores.tolist()), reverse=True):
        predicted = scores >= threshold
        tp = float(np.sum(soft * predicted))
        fp = float(predicted.sum()) - tp
        found = sum(predicted[a:b].any() for a, b in ranges) / len(ranges)
        points.append((fp / n_new, min(tp / p_new, 1.0) * found))
    points.append((1.0, 1.0))
    return sum((x1 - x0) * (y0 + y1) / 2 for (x0, y0), (x1, y1) in pairwise(points))


def test_temporal_auroc_hand_worked():
    labels = np.array([0, 0, 0, 1, 1, 1], bool)
    scores = np.array([0.1, 0.2, 0.3, 0.9, 0.8, 0.7])
    # soft = [0, 0, √½, 1, 1, 1]; P' = (3 + 3.7071)/2, N' = 6 − P'. The curve climbs to
    # TPR 3/P' at FPR 0, reaches TPR 1 at FPR (4 − 3.7071)/N' and stays there.
    p_new = (3 + 3 + math.sqrt(0.5)) / 2
    n_new = 6 - p_new
    first_fpr = (4 - 3 - math.sqrt(0.5)) / n_new
    expected = first_fpr * (3 / p_new + 1) / 2 + (1 - first_fpr)
    assert temporal_auroc(scores, labels, buffer=2) == pytest.approx(expected, abs=1e-12)
    assert expected == pytest.approx(0.994166, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(scored_rows(max_rows=1, max_len=30), st.integers(0, 8))
def test_temporal_auroc_matches_the_reference_loop(rows, buffer):
    scores, labels = rows[0][0], rows[1][0]
    if not labels.any() or scores.min() == scores.max():
        assert temporal_auroc(scores, labels, buffer) == 0.5
        return
    soft = soft_labels(labels, buffer)
    if len(labels) - (labels.sum() + soft.sum()) / 2 <= 0:
        return
    expected = reference_range_auc(scores, labels, buffer)
    assert temporal_auroc(scores, labels, buffer) == pytest.approx(expected, abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(scored_rows(max_rows=3, max_len=25), st.data())
def test_temporal_auroc_without_buffer_and_one_range_is_the_auroc(rows, data):
    scores, _ = rows
    labels = np.zeros(scores.shape, bool)
    for row in labels:
        start = data.draw(st.integers(0, row.size - 1))
        row[start : data.draw(st.integers(start, row.size))] = True
    np.testing.assert_allclose(
        temporal_auroc_rows(scores, labels, buffer=0), auroc_rows(scores, labels), atol=1e-12
    )


def test_temporal_auroc_credits_an_early_rise():
    labels = np.zeros(100, bool)
    labels[50:] = True
    scores = labels.astype(float)
    scores[46:50] = 1.0  # the detector fires 4 steps before the onset
    assert temporal_auroc(scores, labels, buffer=10) > auroc(scores, labels)


def test_temporal_auroc_degenerate_cases():
    labels = np.array([0, 0, 1, 1], bool)
    assert temporal_auroc(np.ones(4), labels) == 0.5
    assert temporal_auroc(np.arange(4.0), np.zeros(4, bool)) == 0.5
    with pytest.raises(ContractError, match="buffer"):
        temporal_auroc(np.arange(4.0), labels, buffer=-1)
