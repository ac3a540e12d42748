"""Ranking metrics of SPEC §6: AUROC, average precision (the step-wise area under the
precision-recall curve, reported as "AUPRC"), FPR at a TPR target on the interpolated ROC curve,
and the range-based temporal AUROC and VUS-PR. Ties between scores are handled explicitly by
each: they count ½ in the AUROC, as one threshold in the average precision (and VUS-PR) and as a
fraction at the FPR-at-TPR operating point. Score direction: larger = more anomalous.

Every function works on rows: `scores` (N, n) float64, one row per episode, and boolean masks
`positive` / `negative` (N, n) that say which entries are positives and which negatives; an entry
in neither mask is ignored. That one shape covers both comparisons of SPEC §6:

* whole-trajectory metrics (raw, null): `scores = z̃`, `positive = y`, `negative = ~y`;
* matched metrics: `scores = [z̃ | z]`, `positive = [y | 0]`, `negative = [0 | y]`, i.e. the
  perturbed scores on the anomaly steps P against the clean scores on the same steps.

Scores must be finite (the stage-facing API in `oodrl.metrics.aggregate` checks that and names
the detector). Degenerate rows get a defined value instead of an error: see each function.
"""

from __future__ import annotations

import numpy as np

from oodrl.errors import ContractError


def _rows(
    scores: np.ndarray, positive: np.ndarray, negative: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, n) float64 scores and bool masks (1-D = one row); negative defaults to ~positive."""
    scores = np.atleast_2d(np.asarray(scores, dtype=np.float64))
    positive = np.atleast_2d(np.asarray(positive, dtype=bool))
    negative = ~positive if negative is None else np.atleast_2d(np.asarray(negative, dtype=bool))
    if scores.ndim != 2 or positive.shape != scores.shape or negative.shape != scores.shape:
        raise ContractError(
            f"scores and masks must have one shape (N, n); got scores {scores.shape}, "
            f"positive {positive.shape}, negative {negative.shape}."
        )
    if (positive & negative).any():
        raise ContractError("An entry cannot be both a positive and a negative.")
    return scores, positive, negative


def _tie_bounds(sorted_scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last index of the group of equal values each entry of a row-sorted array is in."""
    n = sorted_scores.shape[1]
    index = np.broadcast_to(np.arange(n), sorted_scores.shape)
    starts = np.ones(sorted_scores.shape, dtype=bool)
    starts[:, 1:] = sorted_scores[:, 1:] != sorted_scores[:, :-1]
    ends = np.ones(sorted_scores.shape, dtype=bool)
    ends[:, :-1] = starts[:, 1:]
    first = np.maximum.accumulate(np.where(starts, index, 0), axis=1)
    # The last index of a group is the first index of the same group read backwards.
    last = n - 1 - np.maximum.accumulate(np.where(ends[:, ::-1], index, 0), axis=1)[:, ::-1]
    return first, last


def _sorted_rows(
    scores: np.ndarray, positive: np.ndarray, negative: np.ndarray, *, descending: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    order = np.argsort(-scores if descending else scores, axis=1, kind="stable")
    return (
        np.take_along_axis(scores, order, axis=1),
        np.take_along_axis(positive, order, axis=1),
        np.take_along_axis(negative, order, axis=1),
    )


def auroc_rows(
    scores: np.ndarray, positive: np.ndarray, negative: np.ndarray | None = None
) -> np.ndarray:
    """AUROC per row by the rank (Mann-Whitney) formulation, ties counting ½.

    AUROC = Σ_{i∈pos} (#{j∈neg : s_j < s_i} + ½ #{j∈neg : s_j = s_i}) / (n_pos · n_neg),
    equal to scikit-learn's `roc_auc_score`. Rows without positives or without negatives
    (single-class labels) get 0.5, the value of an uninformative detector; constant scores
    give 0.5 by the tie rule.
    """
    scores, positive, negative = _rows(scores, positive, negative)
    s, pos, neg = _sorted_rows(scores, positive, negative, descending=False)
    first, last = _tie_bounds(s)
    negatives_through = np.cumsum(neg, axis=1)
    negatives_below = np.where(
        first > 0, np.take_along_axis(negatives_through, np.maximum(first - 1, 0), axis=1), 0
    )
    negatives_tied = np.take_along_axis(negatives_through, last, axis=1) - negatives_below
    wins = np.where(pos, negatives_below + 0.5 * negatives_tied, 0.0).sum(axis=1)
    pairs = pos.sum(axis=1) * neg.sum(axis=1)
    return np.where(pairs > 0, wins / np.maximum(pairs, 1), 0.5)


def average_precision_rows(
    scores: np.ndarray, positive: np.ndarray, negative: np.ndarray | None = None
) -> np.ndarray:
    """Area under the precision-recall curve as average precision, per row.

    AP = Σ_k (R_k − R_{k−1}) · P_k over the distinct scores taken as thresholds from high to low
    (P_k, R_k the precision and recall of `score ≥ threshold_k`), exactly scikit-learn's
    `average_precision_score`. Rows without positives get 0.0 (as scikit-learn); constant
    scores give the positive fraction.
    """
    scores, positive, negative = _rows(scores, positive, negative)
    s, pos, neg = _sorted_rows(scores, positive, negative, descending=True)
    _, last = _tie_bounds(s)
    true_through = np.take_along_axis(np.cumsum(pos, axis=1), last, axis=1)
    false_through = np.take_along_axis(np.cumsum(neg, axis=1), last, axis=1)
    flagged = true_through + false_through
    precision = np.where(flagged > 0, true_through / np.maximum(flagged, 1), 0.0)
    n_pos = pos.sum(axis=1)
    # Each positive adds 1/n_pos of recall at the threshold of its tie group.
    return np.where(pos, precision, 0.0).sum(axis=1) / np.maximum(n_pos, 1)


def fpr_at_tpr_rows(
    scores: np.ndarray, positive: np.ndarray, negative: np.ndarray, tpr_target: float = 0.95
) -> np.ndarray:
    """False-positive rate at true-positive rate `tpr_target` on the interpolated ROC curve.

    τ = the k-th largest positive score, k = ⌈tpr_target · n_pos⌉: the largest threshold that
    can reach the target. Scores above τ always alarm; a score *equal* to τ alarms with the
    probability q that makes the expected TPR exactly `tpr_target` (a randomised threshold),

        q = (tpr_target · n_pos − #{pos > τ}) / #{pos = τ},
        FPR = (#{neg > τ} + q · #{neg = τ}) / n_neg,

    which is the linear interpolation of scikit-learn's `roc_curve` between the points of the
    thresholds just above τ and at τ. Without ties at τ, q = 1 and FPR = #{neg ≥ τ} / n_neg.
    With ties, a deterministic "≥ τ" would count every tied negative as a false positive: when
    a detector has a floor (CUSUM's 0) holding ≥ 5% of the positives and most negatives,
    τ = the floor and FPR ≈ 1, "worse than chance" for a detector with a high AUROC. The
    randomised threshold counts a tie as a fraction instead, so constant scores give
    `tpr_target` (chance) and no tie can do worse than that. Perfect separation gives 0.
    Rows without positives or without negatives get `tpr_target`, the uninformative value.
    """
    if not 0.0 < tpr_target <= 1.0:
        raise ContractError(f"tpr_target must be in (0, 1]; got {tpr_target}.")
    scores, positive, negative = _rows(scores, positive, negative)
    n_pos = positive.sum(axis=1)
    n_neg = negative.sum(axis=1)
    wanted = _exact_count(tpr_target * n_pos)
    positives_descending = -np.sort(-np.where(positive, scores, -np.inf), axis=1)
    k = np.maximum(np.ceil(wanted).astype(np.int64), 1)
    tau = np.take_along_axis(positives_descending, (k - 1)[:, None], axis=1)
    above, tied = scores > tau, scores == tau
    positives_tied = (positive & tied).sum(axis=1)
    fraction = (wanted - (positive & above).sum(axis=1)) / np.maximum(positives_tied, 1)
    fraction = np.clip(fraction, 0.0, 1.0)
    false_alarms = (negative & above).sum(axis=1) + fraction * (negative & tied).sum(axis=1)
    fpr = false_alarms / np.maximum(n_neg, 1)
    return np.where((n_pos > 0) & (n_neg > 0), fpr, tpr_target)


def _exact_count(count: np.ndarray) -> np.ndarray:
    """A fractional count with float noise (0.95 · 100 = 95.00000000000001) snapped to integers."""
    nearest = np.round(count)
    return np.where(np.abs(count - nearest) < 1e-9, nearest, count)


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """AUROC of one score series against boolean labels (see `auroc_rows`)."""
    return float(auroc_rows(scores, labels)[0])


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Average precision of one score series against boolean labels."""
    return float(average_precision_rows(scores, labels)[0])


def label_ranges(labels: np.ndarray) -> list[tuple[int, int]]:
    """Runs of True in a 1-D boolean array as half-open (start, end) pairs."""
    padded = np.concatenate(([False], np.asarray(labels, dtype=bool), [False]))
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _range_inputs(scores, labels, buffer: int) -> tuple[np.ndarray, np.ndarray]:
    """The scores and labels of one stream as the range-based metrics take them, checked."""
    scores = np.asarray(scores, dtype=np.float64)
    labels = np.asarray(labels, dtype=bool)
    if scores.ndim != 1 or labels.shape != scores.shape:
        raise ContractError(
            f"scores and labels must be 1-D of one length; got {scores.shape}, {labels.shape}."
        )
    if buffer < 0:
        raise ContractError(f"buffer must be >= 0; got {buffer}.")
    return scores, labels


def soft_labels(labels: np.ndarray, buffer: int) -> np.ndarray:
    """Range labels of Paparrizos et al. (2022) with a buffer of `buffer` steps.

    1 inside every anomaly range; a step d = 1 … ⌊buffer/2⌋ steps before a range's first step
    or after its last step gets √(1 − d/buffer); contributions of neighbouring ranges add and
    are capped at 1. (The reference code softens one step fewer after a range than before it;
    here both sides get ⌊buffer/2⌋ steps.)
    """
    labels = np.asarray(labels, dtype=bool)
    soft = labels.astype(np.float64)
    half = buffer // 2
    if half == 0:
        return soft
    T = labels.size  # noqa: N806 - the protocol's name for the horizon
    ramp = np.sqrt(1.0 - np.arange(1, half + 1) / buffer)
    for start, end in label_ranges(labels):
        before = np.arange(start - 1, start - half - 1, -1)
        after = np.arange(end, end + half)
        soft[before[before >= 0]] += ramp[before >= 0]
        soft[after[after < T]] += ramp[after < T]
    return np.minimum(soft, 1.0)


def temporal_auroc(scores: np.ndarray, labels: np.ndarray, buffer: int = 10) -> float:
    """Range-based AUROC (R-AUC) of Paparrizos et al. (2022, "Volume under the surface").

    With ℓ = `soft_labels(labels, buffer)`, P = Σ y, P' = (P + Σ ℓ)/2, N' = T − P', and for each
    threshold θ (every distinct score, high to low) the prediction p = [s ≥ θ]:

        TP = Σ ℓ·p,   FP = Σ p − TP,
        TPR(θ) = min(TP / P', 1) · (fraction of the ranges of ℓ > 0 containing a predicted step),
        FPR(θ) = FP / N'.

    R-AUC is the trapezoidal area under (0, 0), (FPR(θ), TPR(θ)) …, (1, 1). With `buffer = 0`
    and one anomaly range (the protocol's [t*, offset)) it equals the AUROC. The reference code
    evaluates 250 sub-sampled thresholds; this one uses every distinct score, so it is exact.
    Single-class labels and constant scores give 0.5 (the existence factor would otherwise
    credit a constant detector slightly above chance).
    """
    scores, labels = _range_inputs(scores, labels, buffer)
    soft = soft_labels(labels, buffer)
    n_positive = labels.sum()
    positive_mass = (n_positive + soft.sum()) / 2
    negative_mass = labels.size - positive_mass
    if n_positive == 0 or negative_mass <= 0 or scores.min() == scores.max():
        return 0.5
    order = np.argsort(-scores, kind="stable")
    s = scores[order]
    _, last = _tie_bounds(s[None, :])
    group_end = np.flatnonzero(last[0] == np.arange(s.size))
    thresholds = s[group_end]
    true_mass = np.cumsum(soft[order])[group_end]
    flagged = group_end + 1
    ranges = label_ranges(soft > 0)
    range_peaks = np.sort([scores[a:b].max() for a, b in ranges])
    ranges_found = len(ranges) - np.searchsorted(range_peaks, thresholds, side="left")
    tpr = np.minimum(true_mass / positive_mass, 1.0) * ranges_found / len(ranges)
    fpr = (flagged - true_mass) / negative_mass
    tpr = np.concatenate(([0.0], tpr, [1.0]))
    fpr = np.concatenate(([0.0], fpr, [1.0]))
    return float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))


def temporal_auroc_rows(scores: np.ndarray, labels: np.ndarray, buffer: int = 10) -> np.ndarray:
    """`temporal_auroc` of every row of (N, T) scores against (N, T) labels."""
    scores, labels, _ = _rows(scores, labels, None)
    return np.array([temporal_auroc(s, y, buffer) for s, y in zip(scores, labels, strict=True)])


def buffered_ranges(labels: np.ndarray, half: int) -> list[tuple[int, int]]:
    """The anomaly ranges of 1-D boolean labels widened by `half` steps on each side (clipped
    to the series), half-open; widened ranges that share a step merge (TSB-AD's
    `new_sequence`: ranges that only touch stay apart)."""
    T = len(labels)  # noqa: N806 - the protocol's name for the horizon
    merged: list[list[int]] = []
    for start, end in label_ranges(labels):
        a, b = max(start - half, 0), min(end + half, T)
        if merged and a < merged[-1][1]:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    return [(a, b) for a, b in merged]


def range_average_precision(scores: np.ndarray, labels: np.ndarray, buffer: int) -> float:
    """Range-based average precision at one label buffer (Paparrizos et al. 2022, as TSB-AD's
    `RangeAUC_volume_opt` computes it for one window).

    With ℓ = `soft_labels(labels, buffer)`, P = Σ y, and for each threshold θ (every distinct
    score, high to low) the prediction p = [s ≥ θ]:

        TP = Σ ℓ·p                    (anomaly steps count 1, buffer steps their ℓ)
        P' = P + ½ Σ_{y = 0} ℓ·p       (the buffer mass that was predicted counts half)
        TPR(θ) = min(TP / P', 1) · (fraction of the ranges, widened by ⌊buffer/2⌋ steps,
                                    containing a predicted step)
        Precision(θ) = TP / Σ p

    and AP = Σ_θ (TPR(θ) − TPR(θ⁺)) · Precision(θ), θ⁺ the threshold before θ (TPR 0 before
    the first). With `buffer` 0 or 1 and one anomaly range it is the average precision
    (`average_precision_rows`); with several ranges the existence factor also counts how many
    ranges were found. TSB-AD evaluates 250 sub-sampled thresholds; this uses every distinct
    score, so it is exact. No positive step gives 0.0 (as the average precision).
    """
    scores, labels = _range_inputs(scores, labels, buffer)
    return _range_average_precisions(scores, labels, _label_surfaces(labels, [buffer]))[0]


def _label_surfaces(
    labels: np.ndarray, buffers: list[int]
) -> tuple[np.ndarray, list[list[tuple[int, int]]]]:
    """What the range-based AP takes from the labels at each buffer: the soft label mass outside
    the anomaly ranges (len(buffers), T) and the ranges widened by ⌊buffer/2⌋ steps."""
    outside = np.stack([np.where(labels, 0.0, soft_labels(labels, b)) for b in buffers])
    return outside, [buffered_ranges(labels, b // 2) for b in buffers]


def _range_average_precisions(
    scores: np.ndarray, labels: np.ndarray,
    surfaces: tuple[np.ndarray, list[list[tuple[int, int]]]],
) -> list[float]:  # fmt: skip
    """`range_average_precision` of one checked stream at each buffer of `surfaces`
    (`_label_surfaces` of its labels). The order of the scores, their ties and the counts
    inside the ranges do not depend on the buffer, so they are computed once and the buffers
    together, one row each; a row's arithmetic is the one-buffer formula's, step for step
    (cumulative sums along the row, one sum per row), so each value is the same bits as
    computing its buffer alone."""
    outside, ranges = surfaces
    n_positive = int(labels.sum())
    if n_positive == 0:
        return [0.0] * len(ranges)
    order = np.argsort(-scores, kind="stable")
    s = scores[order]
    _, last = _tie_bounds(s[None, :])
    group_end = np.flatnonzero(last[0] == np.arange(s.size))
    thresholds = s[group_end]
    inside = np.cumsum(labels[order])[group_end]
    buffer_mass = np.cumsum(outside[:, order], axis=1)[:, group_end]
    true_mass = inside + buffer_mass
    recall = np.minimum(true_mass / (n_positive + buffer_mass / 2), 1.0)
    ranges_found = np.stack([
        len(r) - np.searchsorted(np.sort([scores[a:b].max() for a, b in r]), thresholds, "left")
        for r in ranges
    ])  # fmt: skip
    tpr = recall * ranges_found / np.array([[len(r)] for r in ranges])
    precision = true_mass / (group_end + 1)
    return [float(np.sum(row)) for row in np.diff(tpr, axis=1, prepend=0.0) * precision]


def vus_pr(scores: np.ndarray, labels: np.ndarray, buffer: int = 10) -> float:
    """VUS-PR: the volume under the range-based precision-recall surface, the mean of
    `range_average_precision` over the buffers 0, 1, …, `buffer` (TSB-AD's VUS-PR with its
    window 2L = `buffer`: the last surface's labels are softened ⌊buffer/2⌋ steps on each side
    of a range, as `temporal_auroc`'s are)."""
    scores, labels = _range_inputs(scores, labels, buffer)
    surfaces = _label_surfaces(labels, list(range(buffer + 1)))
    return float(np.mean(_range_average_precisions(scores, labels, surfaces)))


def vus_pr_rows(scores: np.ndarray, labels: np.ndarray, buffer: int = 10) -> np.ndarray:
    """`vus_pr` of every row of (N, T) scores against (N, T) labels. Rows of equal labels (a
    set's streams share their fault's onset and offset) share their label surfaces."""
    scores, labels, _ = _rows(scores, labels, None)
    if buffer < 0:
        raise ContractError(f"buffer must be >= 0; got {buffer}.")
    buffers = list(range(buffer + 1))
    surfaces: dict[bytes, tuple[np.ndarray, list[list[tuple[int, int]]]]] = {}
    values = []
    for s, y in zip(scores, labels, strict=True):
        surface = surfaces.get(y.tobytes())
        if surface is None:
            surface = surfaces[y.tobytes()] = _label_surfaces(y, buffers)
        values.append(np.mean(_range_average_precisions(s, y, surface)))
    return np.array(values, dtype=np.float64)
