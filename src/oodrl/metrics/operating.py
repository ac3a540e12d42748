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
- the delays (raise − t*) of the streams detected within K, their count, and their median and
  90th percentile from `MIN_DELAY_COUNT` = 5 such streams on (SPEC §19), and the
  detection-rate curve over K;
- the achieved clean-stream false-alarm rate (share of clean streams with any alarm) beside α,
  with its exact (Clopper-Pearson) binomial interval (`achieved_false_alarm_rate`).

The training-conditional rule (SPEC §19, `threshold_rule: episode_max_conditional`): with the
threshold at the k-th smallest of n i.i.d. continuous maxima, one calibration draw's
false-alarm rate FAR = 1 − F(X_(k)) is Beta(n + 1 − k, k) distributed, and
P(FAR > α) = P(Binomial(n, α) ≤ n − k). The rule takes the smallest k with P(FAR > α) ≤ δ,
computed exactly in integers (`conditional_rank`); k = n needs (1 − α)^n ≤ δ, so n streams
support α ≥ 1 − δ^(1/n) (`min_alpha_conditional`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np

from oodrl.core.detector import episode_max_threshold
from oodrl.errors import ConfigError, ContractError

#: The suite's default false-alarm budget per clean stream (SPEC §15).
DEFAULT_ALPHA = 0.05
#: The default δ of the training-conditional rule: P(FAR > α) ≤ δ over calibration draws.
DEFAULT_DELTA = 0.1
#: The per-stream threshold rules: marginal (E[FAR] ≤ α) and training-conditional (SPEC §19).
PER_STREAM_RULES = ("episode_max", "episode_max_conditional")
#: The fewest detected streams whose delays are shown (SPEC §19 "Cells").
MIN_DELAY_COUNT = 5


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


def _ratio(value: float) -> tuple[int, int]:
    """A params value as the exact fraction its decimal text says (0.05 = 1/20)."""
    fraction = Fraction(str(value))
    return fraction.numerator, fraction.denominator


def conditional_rank(n: int, alpha: float, delta: float = DEFAULT_DELTA) -> int | None:
    """The smallest k in 1..n such that the k-th smallest of n calibration maxima has
    P(FAR > α) = P(Binomial(n, α) ≤ n − k) ≤ δ; None when even k = n does not.

    Exact: with α = p/q and δ = r/s, P(Binomial(n, α) ≤ j) ≤ δ ⇔
    s · Σ_{i ≤ j} C(n, i) p^i (q − p)^(n − i) ≤ r · q^n, all integers.
    """
    p, q = _ratio(alpha)
    r, s = _ratio(delta)
    bound, cumulative, largest = r * q**n, 0, None
    for j in range(n):  # j = n − k, the number of calibration maxima above the threshold
        cumulative += math.comb(n, j) * p**j * (q - p) ** (n - j)
        if s * cumulative > bound:
            break
        largest = j
    return None if largest is None else n - largest


def min_calibration_streams_conditional(alpha: float, delta: float = DEFAULT_DELTA) -> int:
    """The fewest streams the training-conditional rule needs: the least n with
    (1 − α)^n ≤ δ (then k = n qualifies), found exactly around log δ / log(1 − α)."""
    p, q = _ratio(alpha)
    r, s = _ratio(delta)

    def enough(n: int) -> bool:
        return s * (q - p) ** n <= r * q**n

    n = max(1, math.ceil(math.log(delta) / math.log1p(-alpha)))
    while not enough(n):
        n += 1
    while n > 1 and enough(n - 1):
        n -= 1
    return n


def min_alpha_conditional(n_calibration: int, delta: float = DEFAULT_DELTA) -> float:
    """1 − δ^(1/n): the smallest α that n calibration streams support under the
    training-conditional rule at δ (1 without streams)."""
    return -math.expm1(math.log(delta) / n_calibration) if n_calibration > 0 else 1.0


def conditional_shortfall(n: int, alpha: float, delta: float = DEFAULT_DELTA) -> str | None:
    """Why n calibration streams cannot give the training-conditional rule at (α, δ), in
    words naming the fewest streams and the smallest α allowed; None when they can."""
    needed = min_calibration_streams_conditional(alpha, delta)
    if n >= needed:
        return None
    smallest = math.ceil(min_alpha_conditional(n, delta) * 1e5) / 1e5  # rounded up: a bound
    return (
        f"threshold_rule episode_max_conditional at alpha={alpha}, delta={delta} needs at least "
        f"{needed} calibration streams ((1 - alpha)^n <= delta); got {n}, which allow "
        f"alpha >= {smallest:g}"
    )


def conditional_threshold(
    calibration_maxima: Sequence[float], alpha: float, delta: float = DEFAULT_DELTA
) -> float:
    """Just above the `conditional_rank`-th smallest of n calibration maxima: a new clean
    stream alarms with probability at most α in all but a share δ of calibration draws
    (`episode_max_conditional`). Ties are safe: alarms are `score >= threshold`, and the
    threshold is the next float above the order statistic."""
    maxima = np.sort(np.asarray(calibration_maxima, dtype=np.float64))
    shortfall = conditional_shortfall(len(maxima), alpha, delta)
    if shortfall:
        raise ConfigError(f"{shortfall}.")
    rank = conditional_rank(len(maxima), alpha, delta)
    return float(np.nextafter(maxima[rank - 1], np.inf))


def per_stream_threshold(
    calibration_maxima: Sequence[float],
    alpha: float,
    rule: str = "episode_max",
    delta: float = DEFAULT_DELTA,
) -> float:
    """The per-stream threshold by a rule of PER_STREAM_RULES (`delta` only for the
    training-conditional one)."""
    if rule == "episode_max_conditional":
        return conditional_threshold(calibration_maxima, alpha, delta)
    if rule != "episode_max":
        raise ConfigError(
            f"Per-stream threshold rule must be one of {PER_STREAM_RULES}; got {rule!r}."
        )
    return conformal_threshold(calibration_maxima, alpha)


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


@dataclass(frozen=True)
class FalseAlarmRate:
    """The achieved false-alarm rate on an audit set of clean streams: the share of streams
    with any alarm and its exact (Clopper-Pearson) interval."""

    rate: float
    ci_low: float
    ci_high: float
    n_alarmed: int
    n_streams: int


def achieved_false_alarm_rate(
    alarms: np.ndarray | Sequence[np.ndarray], confidence: float = 0.95
) -> FalseAlarmRate:
    """The share of clean audit streams that raise any alarm (one bool array per stream, or
    (N, T)), with its Clopper-Pearson interval at `confidence` (SPEC §19)."""
    n_alarmed = sum(bool(np.any(a)) for a in alarms)
    n_streams = len(alarms)
    low, high = clopper_pearson(n_alarmed, n_streams, confidence)
    rate = n_alarmed / n_streams if n_streams else 0.0
    return FalseAlarmRate(rate, low, high, n_alarmed, n_streams)


def _rounded(value: float) -> float:
    return round(float(value), 6) + 0.0


def delay_summary(delays: Sequence[int]) -> dict[str, float | int | None]:
    """The delays of the streams detected within K: their count always, their median and
    90th percentile only from `MIN_DELAY_COUNT` streams on (None below: not shown)."""
    values = np.asarray(delays, dtype=np.float64)
    shown = values.size >= MIN_DELAY_COUNT
    return {
        "median": _rounded(np.quantile(values, 0.5)) if shown else None,
        "p90": _rounded(np.quantile(values, 0.9)) if shown else None,
        "n_detected": int(values.size),
    }


def delay_text(summary: Mapping[str, Any]) -> str:
    """A delay cell: the median with its count, "12 (n = 40)", or "— (n = 3)" below
    `MIN_DELAY_COUNT` detected streams."""
    median = summary["median"]
    return f"{'—' if median is None else f'{median:g}'} (n = {summary['n_detected']})"


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
        fa_low, fa_high = clopper_pearson(self.clean_false_alarms, self.n_clean, self.confidence)
        dr_low, dr_high = clopper_pearson(self.detected, self.n_faulty, self.confidence)
        return {
            "alpha": self.alpha,
            "threshold": self.threshold,
            "k": self.k,
            "detection_rate": _rounded(self.detection_rate),
            "detection_rate_ci": [_rounded(dr_low), _rounded(dr_high)],
            "n_faulty": self.n_faulty,
            "early_false_alarm_rate": _rounded(self.early_false_alarms / self.n_faulty),
            "delay": delay_summary(self.delays),
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
    Delays are those of the streams detected within K (first raise in [t*, t* + K]).
    """
    faulty = np.atleast_2d(np.asarray(faulty_scores, dtype=np.float64))
    clean = np.atleast_2d(np.asarray(clean_scores, dtype=np.float64))
    T = faulty.shape[1]  # noqa: N806
    if not 0 <= onset < T:
        raise ContractError(f"onset must be in [0, T={T}); got {onset}.")
    if k < 0:
        raise ContractError(f"K must be >= 0 steps; got {k}.")
    raised = first_raise(faulty >= threshold, latency)
    detected = (raised >= onset) & (raised <= onset + k) & (raised < T)
    if curve_ks is None:
        curve_ks = range(0, T - onset + 1, 10)
    curve = {int(kk): detection_rate(raised, onset, int(kk), T) for kk in curve_ks}
    return OperatingPoint(
        alpha=float(alpha),
        threshold=float(threshold),
        k=int(k),
        n_faulty=len(faulty),
        detected=int(np.sum(detected)),
        early_false_alarms=int(np.sum(raised < onset)),
        delays=tuple(int(d) for d in raised[detected] - onset),
        curve=curve,
        n_clean=len(clean),
        clean_false_alarms=achieved_false_alarm_rate(clean >= threshold).n_alarmed,
        confidence=float(confidence),
    )


def calibration_maxima(detector: Any, trajectories: Sequence[Any]) -> np.ndarray:
    """The per-stream score maxima of a fitted detector on held-out clean trajectories (in the
    pipeline: the ID set's calibration split, as `oodrl.stages.fit` calibrates on it)."""
    return np.array([output.scores.max() for output in detector.score_many(trajectories)])


def per_stream_detections(
    faulty: np.ndarray, threshold: float, onset: int, k: int, latency: int
) -> np.ndarray:
    """1.0 per faulty stream whose first alarm is raised in [t*, t* + K] within the stream."""
    raised = first_raise(faulty >= threshold, latency)
    detected = (raised >= onset) & (raised <= onset + k) & (raised < faulty.shape[1])
    return detected.astype(np.float64)
