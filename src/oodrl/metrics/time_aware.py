"""Thresholds that follow time (SPEC §24): a time-aware per-stream rule for every detector.

The constant rule (`oodrl.metrics.operating`) compares a stream's maximum score with one order
statistic of the calibration streams' maxima. When the clean score law changes along an episode
(a quiet start, a loud end), that maximum is set by the loud steps, and a fault in a quiet phase
must outshout them to be seen. The time-aware rule first standardises each step's score by the
clean law at that step, z_t = (s_t − loc_t) / scale_t, then applies the SAME per-stream rule to
z: a stream alarms at the first step with z_t ≥ the order statistic of the calibration streams'
maxima of z (`operating.per_stream_threshold`, training-conditional by default).

Why each choice of `fit_step_standardiser`:

- median and IQR / 1.349 (the IQR of a normal law in sd): detector scores have heavy tails, and
  a mean and sd would follow the few wild steps of the fit streams;
- each step pools the least window of steps centred on it that holds `MIN_WINDOW_VALUES` = 300
  values: a quantile's standard error from n values is about 1/√n of the scale (a few percent
  at 300), and late steps, which only a few long fit streams reach, borrow wider windows;
- a step's scale is the largest raw scale within its window: a window that happens to be quiet
  (or straddles a change from quiet to loud) would shrink the scale and make every later
  threshold anti-conservative there; the largest is the conservative side of that error;
- the scale is floored at `SCALE_FLOOR` = 0.1 × the scale of all fit values pooled, so a step
  where the detector is nearly constant does not divide by ~0 (1 in the scores' unit when even
  the pooled IQR is 0: standardising then only shifts);
- steps beyond the longest fit stream keep the last step's location and scale.

The standardiser is a function of the fit (ID training) streams only, never of the calibration or
audit streams. Given it, the calibration streams' maxima of z and a fresh clean stream's are
still i.i.d., so the order statistic keeps the constant rule's promise (marginal: FAR ≤ α;
training-conditional: FAR ≤ α in all but a share δ of calibration draws) and the audit on
untouched clean streams reads the same. Everything is numpy, without randomness: results are
byte-identical across runs.

Every function below takes `standardiser=None` for the constant rule, so a stage can compute
both rules side by side with one call shape; scores are (N, T) arrays as the score stores hold
them (calibration scores may also be a list of 1-D streams of different lengths).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from oodrl.errors import ConfigError, ContractError
from oodrl.metrics.operating import (
    DEFAULT_DELTA,
    PER_STREAM_RULES,
    OperatingPoint,
    _rounded,
    first_raise,
    operating_point,
    per_stream_detections,
    per_stream_threshold,
)

#: The fewest fit values each step's window pools.
MIN_WINDOW_VALUES = 300
#: A step's scale is at least this share of the scale of all fit values pooled.
SCALE_FLOOR = 0.1
#: The IQR of a normal law in units of its sd (2 Φ⁻¹(0.75)), so IQR / 1.349 estimates an sd.
IQR_PER_SD = 1.349
#: The per-stream rules and the α of the operating curve (SPEC §24).
RULES = ("constant", "time_aware")
ALPHAS = (0.01, 0.02, 0.05, 0.1, 0.2)


def _stretch(values: np.ndarray, steps: int) -> np.ndarray:
    """The first `steps` entries, the last repeated beyond the end."""
    if steps <= values.size:
        return values[:steps]
    return np.concatenate([values, np.full(steps - values.size, values[-1])])


@dataclass(frozen=True, eq=False)
class StepStandardiser:
    """Per-step location and scale of a detector's clean scores, fitted on ID streams only
    (`fit_step_standardiser`); arrays are read-only."""

    location: np.ndarray
    scale: np.ndarray
    #: Per step, the half-width h of its window [t − h, t + h] (cut at the ends).
    half_width: np.ndarray
    #: IQR / 1.349 of all fit values pooled (the floor is `scale_floor` × this).
    pooled_scale: float
    min_values: int = MIN_WINDOW_VALUES
    scale_floor: float = SCALE_FLOOR
    iqr_per_sd: float = IQR_PER_SD

    def standardise(self, scores: np.ndarray) -> np.ndarray:
        """(s_t − loc_t) / scale_t over the last axis of (T,) or (N, T) scores."""
        scores = np.asarray(scores, dtype=np.float64)
        steps = scores.shape[-1]
        return (scores - _stretch(self.location, steps)) / _stretch(self.scale, steps)


def fit_step_standardiser(id_scores: Sequence[np.ndarray]) -> StepStandardiser:
    """The per-step median and IQR / 1.349 of a detector's scores on the ID fit streams (1-D
    arrays of any lengths), each pooled over the least centred window of steps holding
    `MIN_WINDOW_VALUES` values; the scale is the largest within the window, floored at
    `SCALE_FLOOR` × the pooled scale (see the module doc for why)."""
    streams = [np.asarray(s, dtype=np.float64) for s in id_scores]
    if not streams or any(s.ndim != 1 or s.size == 0 for s in streams):
        raise ContractError("fit scores must be non-empty 1-D arrays, one per ID stream.")
    if not all(np.isfinite(s).all() for s in streams):
        raise ContractError("fit scores contain NaN or inf; per-step scores must be finite.")
    lengths = np.array([s.size for s in streams])
    T = int(lengths.max())  # noqa: N806 - the protocol's name for the horizon
    total = int(lengths.sum())
    if total < MIN_WINDOW_VALUES:
        raise ContractError(
            f"the time-aware rule needs at least {MIN_WINDOW_VALUES} fit scores; got {total}."
        )
    # All values ordered by step (then stream): a window of steps is one contiguous slice.
    padded = np.zeros((len(streams), T))
    held = np.arange(T) < lengths[:, None]
    for row, s in zip(padded, streams, strict=True):
        row[: s.size] = s
    by_step = padded.T[held.T]
    bounds = np.concatenate([[0], np.cumsum(held.sum(axis=0))])

    steps = np.arange(T)
    half = np.zeros(T, dtype=np.int64)

    def window(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.maximum(steps - h, 0), np.minimum(steps + h + 1, T)

    lo, hi = window(half)
    while (short := bounds[hi] - bounds[lo] < MIN_WINDOW_VALUES).any():
        half[short] += 1  # ends when the window spans every step: total ≥ MIN_WINDOW_VALUES
        lo, hi = window(half)

    # Quartiles per window, vectorised over the steps whose windows hold equally many values.
    start, size = bounds[lo], bounds[hi] - bounds[lo]
    quartiles = np.empty((3, T))
    for count in np.unique(size):
        at = np.flatnonzero(size == count)
        values = by_step[start[at, None] + np.arange(count)]
        quartiles[:, at] = np.quantile(values, [0.25, 0.5, 0.75], axis=1)
    raw_scale = (quartiles[2] - quartiles[0]) / IQR_PER_SD
    widest = np.array([raw_scale[a:b].max() for a, b in zip(lo, hi, strict=True)])
    q1, q3 = np.quantile(by_step, [0.25, 0.75])
    pooled = float((q3 - q1) / IQR_PER_SD)
    floor = SCALE_FLOOR * pooled if pooled > 0 else 1.0
    location, scale = quartiles[1], np.maximum(widest, floor)
    for array in (location, scale, half):
        array.setflags(write=False)
    return StepStandardiser(location, scale, half, pooled)


def rule_scores(scores: Any, standardiser: StepStandardiser | None = None) -> Any:
    """The scores a rule thresholds: as given (constant rule, `standardiser=None`) or
    standardised per step (time-aware); of an (N, T) array, or of a list of 1-D streams."""

    def rule(stream: Any) -> np.ndarray:
        stream = np.asarray(stream, dtype=np.float64)
        return stream if standardiser is None else standardiser.standardise(stream)

    if isinstance(scores, np.ndarray):
        if scores.ndim != 2:
            raise ContractError(f"scores must be (N, T) or a list of streams; got {scores.shape}.")
        return rule(scores)
    return [rule(stream) for stream in scores]


def stream_maxima(scores: Any, standardiser: StepStandardiser | None = None) -> np.ndarray:
    """Each stream's maximum of its rule scores (what the per-stream threshold compares)."""
    return np.array([np.max(s) for s in rule_scores(scores, standardiser)], dtype=np.float64)


def time_aware_threshold(
    standardiser: StepStandardiser,
    calibration_scores: Any,
    alpha: float,
    delta: float = DEFAULT_DELTA,
    threshold_rule: str = "episode_max_conditional",
) -> float:
    """The per-stream threshold on standardised scores: the constant rule's order statistic
    (`operating.per_stream_threshold`, training-conditional by default) of the calibration
    streams' maxima of z; ConfigError where the calibration count cannot support α."""
    maxima = stream_maxima(calibration_scores, standardiser)
    return per_stream_threshold(maxima, alpha, threshold_rule, delta)


def first_alarm_steps(
    scores: np.ndarray,
    threshold: float,
    latency: int = 0,
    standardiser: StepStandardiser | None = None,
) -> list[int | None]:
    """Per stream of (N, T) scores, the step at which its first alarm (rule score ≥ threshold)
    is raised (`operating.first_raise`), or None when none is raised within the stream."""
    z = rule_scores(np.atleast_2d(scores), standardiser)
    raised = first_raise(z >= threshold, latency)
    return [None if r >= z.shape[1] else int(r) for r in raised]


def stream_detections(
    faulty: np.ndarray,
    threshold: float,
    onset: int,
    k: int,
    latency: int = 0,
    standardiser: StepStandardiser | None = None,
) -> np.ndarray:
    """1.0 per faulty stream whose first alarm is raised in [t*, t* + K] within the stream: the
    tier results' per-stream `detection_rate@K`, under either rule."""
    z = rule_scores(np.atleast_2d(faulty), standardiser)
    return per_stream_detections(z, threshold, onset, k, latency)


def rule_operating_point(
    faulty_scores: np.ndarray,
    clean_scores: np.ndarray,
    threshold: float,
    onset: int,
    standardiser: StepStandardiser | None = None,
    **kwargs: Any,
) -> OperatingPoint:
    """`operating.operating_point` (detection rate@K, early alarms, delays, audited false-alarm
    rate; same keyword arguments) under either rule."""
    faulty = rule_scores(np.atleast_2d(faulty_scores), standardiser)
    clean = rule_scores(np.atleast_2d(clean_scores), standardiser)
    return operating_point(faulty, clean, threshold, onset, **kwargs)


def point_record(point: OperatingPoint) -> dict[str, Any]:
    """`OperatingPoint.as_dict` with the delay's mean beside its median and 90th percentile over
    the streams detected within K, all three shown from `MIN_DELAY_COUNT` (5) such streams on
    and None below (SPEC §19, §24); their count always."""
    record = point.as_dict()
    shown = record["delay"]["median"] is not None  # from MIN_DELAY_COUNT detected streams
    record["delay"]["mean"] = _rounded(np.mean(point.delays)) if shown else None
    return record


def alpha_curve(
    calibration_scores: Any,
    faulty_scores: np.ndarray,
    audit_scores: np.ndarray,
    onset: int,
    *,
    standardiser: StepStandardiser | None = None,
    alphas: Sequence[float] = ALPHAS,
    delta: float = DEFAULT_DELTA,
    threshold_rule: str = "episode_max_conditional",
    k: int = 100,
    latency: int = 0,
    confidence: float = 0.95,
) -> list[dict[str, Any]]:
    """The operating curve over α of one rule (constant with `standardiser=None`, else
    time-aware): per α its own threshold from the calibration streams, the detection rate
    within K with its Clopper-Pearson CI, early alarms (first raise before the onset), the
    delay (median, 90th percentile and mean from `MIN_DELAY_COUNT` detected streams) and the
    false-alarm rate achieved on the audit streams with its CI (`OperatingPoint.as_dict`).

    An α the calibration count cannot support under `threshold_rule` is a record with
    `supported: False` and the reason; it is never computed under another rule.
    """
    if threshold_rule not in PER_STREAM_RULES:
        raise ConfigError(
            f"threshold_rule must be one of {PER_STREAM_RULES}; got {threshold_rule!r}."
        )
    rule = RULES[standardiser is not None]
    maxima = stream_maxima(calibration_scores, standardiser)
    records = []
    for alpha in alphas:
        head = {"alpha": alpha, "rule": rule, "threshold_rule": threshold_rule, "delta": delta}
        try:
            threshold = per_stream_threshold(maxima, alpha, threshold_rule, delta)
        except ConfigError as error:
            records.append({**head, "supported": False, "reason": str(error)})
            continue
        point = rule_operating_point(
            faulty_scores, audit_scores, threshold, onset, standardiser,
            alpha=alpha, k=k, latency=latency, curve_ks=(), confidence=confidence,
        )  # fmt: skip
        record = point_record(point)
        del record["detection_curve"]
        records.append(
            {**head, "supported": True, **record, "early_false_alarms": point.early_false_alarms}
        )
    return records
