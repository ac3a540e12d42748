"""Operating points (SPEC §15): what a deployed detector does at a clean false-alarm budget.

The alarm rule is per stream: the threshold is the conformal quantile of the maxima of n
held-out clean streams at level α (`threshold_rule: episode_max`,
`oodrl.core.detector.episode_max_threshold`, reused here), so a new clean stream of the same
length raises any alarm with probability ≤ α. It needs n ≥ ⌈1/α⌉ − 1 calibration streams;
with n streams the smallest α it supports is 1/(n + 1).

Per (detector, cell), from the scores of faulty streams with onset t* and of clean streams:

- `detection_rate@K`: the share of faulty streams whose FIRST alarm is raised in [t*, t* + K].
  An alarm on the score of step t is raised at t + latency (the detector's look-ahead, as
  `oodrl.metrics.alarms.detection_delay` counts it); a first raise before t* is a false alarm,
  not a detection, and a raise at or after T (beyond the stream) is no alarm;
- the delays (raise − t*) of the streams detected within the stream, their median and 90th
  percentile, and the detection-rate curve over K;
- the achieved clean-stream false-alarm rate (share of clean streams with any alarm) beside α,
  with its exact (Clopper-Pearson) binomial interval.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np

from oodrl.core.detector import episode_max_threshold
from oodrl.errors import ContractError

#: The suite's default false-alarm budget per clean stream (SPEC §15).
DEFAULT_ALPHA = 0.05


def min_calibration_streams(alpha: float) -> int:
    """⌈1/α⌉ − 1: the fewest clean calibration streams that give a finite conformal threshold."""
    return math.ceil(1 / Fraction(str(alpha))) - 1


def min_alpha(n_calibration: int) -> float:
    """1/(n + 1): the smallest α that n clean calibration streams support."""
    return 1.0 / (n_calibration + 1)


def conformal_threshold(calibration_maxima: Sequence[float], alpha: float) -> float:
    """The per-stream alarm threshold from the score maxima of held-out clean streams
    (`episode_max`; raises ConfigError below `min_calibration_streams(alpha)` streams)."""
    return episode_max_threshold(np.asarray(calibration_maxima, dtype=np.float64), alpha)


def first_raise(alarms: np.ndarray, latency: int = 0) -> np.ndarray:
    """Per stream (rows of `alarms`, (N, T) bool): the step at which its first alarm is raised
    (first alarm index + latency), or T when it raises none within the stream."""
    alarms = np.atleast_2d(np.asarray(alarms))
    if alarms.dtype != bool or alarms.ndim != 2:
        raise ContractError(f"alarms must be bool (N, T); got {alarms.dtype} {alarms.shape}.")
    if latency < 0:
        raise ContractError(f"latency must be >= 0 steps; got {latency}.")
    T = alarms.shape[1]  # noqa: N806 - the protocol's name for the horizon
    raised = np.argmax(alarms, axis=1) + latency
    return np.where(alarms.any(axis=1), np.minimum(raised, T), T).astype(np.int64)


def detection_rate(raised: np.ndarray, onset: int, k: int, T: int) -> float:  # noqa: N803
    """The share of streams whose first raise (`first_raise`) falls in [onset, onset + k]."""
    raised = np.asarray(raised)
    return float(np.mean((raised >= onset) & (raised <= onset + k) & (raised < T)))


def clopper_pearson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) interval of a binomial proportion; (0, 1) without trials."""
    if trials == 0:
        return 0.0, 1.0
    from scipy.stats import beta

    tail = (1 - confidence) / 2
    low = 0.0 if successes == 0 else float(beta.ppf(tail, successes, trials - successes + 1))
    high = (
        1.0 if successes == trials else float(beta.ppf(1 - tail, successes + 1, trials - successes))
    )
    return low, high


def _rounded(value: float) -> float:
    return round(float(value), 6) + 0.0


@dataclass(frozen=True)
class OperatingPoint:
    """One detector on one cell at the per-stream rule; `as_dict` is its YAML record."""

    alpha: float
    threshold: float
    k: int
    n_faulty: int
    detected: int
    early_false_alarms: int
    delays: tuple[int, ...]
    curve: dict[int, float]
    n_clean: int
    clean_false_alarms: int
    confidence: float

    @property
    def detection_rate(self) -> float:
        return self.detected / self.n_faulty

    def as_dict(self) -> dict[str, Any]:
        delays = np.asarray(self.delays, dtype=np.float64)
        fa_low, fa_high = clopper_pearson(self.clean_false_alarms, self.n_clean, self.confidence)
        dr_low, dr_high = clopper_pearson(self.detected, self.n_faulty, self.confidence)
        quantile = (lambda q: _rounded(np.quantile(delays, q))) if delays.size else (lambda q: None)
        return {
            "alpha": self.alpha,
            "threshold": self.threshold,
            "k": self.k,
            "detection_rate": _rounded(self.detection_rate),
            "detection_rate_ci": [_rounded(dr_low), _rounded(dr_high)],
            "n_faulty": self.n_faulty,
            "early_false_alarm_rate": _rounded(self.early_false_alarms / self.n_faulty),
            "delay": {
                "median": quantile(0.5),
                "p90": quantile(0.9),
                "n_detected": int(delays.size),
            },
            "detection_curve": {int(k): _rounded(v) for k, v in sorted(self.curve.items())},
            "clean_false_alarm_rate": _rounded(self.clean_false_alarms / max(self.n_clean, 1)),
            "clean_false_alarm_ci": [_rounded(fa_low), _rounded(fa_high)],
            "clean_false_alarm_interval": "clopper-pearson",
            "n_clean": self.n_clean,
            "confidence": self.confidence,
        }


def operating_point(
    faulty_scores: np.ndarray,
    clean_scores: np.ndarray,
    threshold: float,
    onset: int,
    *,
    alpha: float = DEFAULT_ALPHA,
    k: int = 100,
    latency: int = 0,
    curve_ks: Sequence[int] | None = None,
    confidence: float = 0.95,
) -> OperatingPoint:
    """The operating point of scores (N, T) of faulty streams with onset t* and (M, T) of clean
    streams, alarms = score ≥ threshold (the threshold from `conformal_threshold`).

    `curve_ks` are the K of the detection-rate curve (default: every 10 steps to T − t*).
    Delays are those of streams raising their first alarm in [t*, T), whatever K.
    """
    faulty = np.atleast_2d(np.asarray(faulty_scores, dtype=np.float64))
    clean = np.atleast_2d(np.asarray(clean_scores, dtype=np.float64))
    T = faulty.shape[1]  # noqa: N806
    if not 0 <= onset < T:
        raise ContractError(f"onset must be in [0, T={T}); got {onset}.")
    if k < 0:
        raise ContractError(f"K must be >= 0 steps; got {k}.")
    raised = first_raise(faulty >= threshold, latency)
    within = (raised >= onset) & (raised < T)
    if curve_ks is None:
        curve_ks = range(0, T - onset + 1, 10)
    curve = {int(kk): detection_rate(raised, onset, int(kk), T) for kk in curve_ks}
    return OperatingPoint(
        alpha=float(alpha),
        threshold=float(threshold),
        k=int(k),
        n_faulty=len(faulty),
        detected=int(np.sum(within & (raised <= onset + k))),
        early_false_alarms=int(np.sum(raised < onset)),
        delays=tuple(int(d) for d in raised[within] - onset),
        curve=curve,
        n_clean=len(clean),
        clean_false_alarms=int(np.sum((clean >= threshold).any(axis=1))),
        confidence=float(confidence),
    )


def calibration_maxima(detector: Any, trajectories: Sequence[Any]) -> np.ndarray:
    """The per-stream score maxima of a fitted detector on held-out clean trajectories (in the
    pipeline: the ID set's calibration split, as `oodrl.stages.fit` calibrates on it)."""
    return np.array([output.scores.max() for output in detector.score_many(trajectories)])
