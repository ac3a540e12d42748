"""`cusum_tv`: `cusum` against a time-varying threshold curve (after Huang and Veeravalli 2025).

oodrl's CUSUM statistic W_t (`oodrl.detectors.cusum`) is not stationary on clean streams: it
starts at 0 and, when the residual's spread changes along an episode, keeps rising (on clean
Acrobot streams its per-step 0.9 quantile grows 18.8 → 127 → 167 over the episode's thirds). A
constant threshold is then set by the late steps and is blind early on. `cusum_tv` divides W_t by
a per-step curve of clean W,

    z_t = W_t / b(a_t),

a_t the age of the statistic at step t: the steps since its last restart (the step index t
itself by default; the step within the episode with ``reset_on_done=True``). On clean streams z_t
has about the same distribution at every age, its per-age `quantile` near 1, so one threshold
(calibrated by the usual rule) holds the same false-alarm rate early and late.

**The curve b** is estimated at `fit`, on clean streams the residual model did not see:

1. *Split.* The fit trajectories are split by index parity: the even-indexed ones (0, 2, …)
   fit the residual model, ν and the slack exactly as `cusum` does (its own `_fit`); the
   odd-indexed ones (1, 3, …) are scored by that model and give the values of W from which b is
   estimated. In-sample residuals are smaller than those of new streams (the model fitted
   them), so a curve from the model's own streams would be biased low and raise false alarms.
   Interleaving, rather than first half / second half, keeps both halves spread over the order
   in which the streams were collected. At least 2 fit trajectories are needed.
2. *Pooled quantile per age.* At each age a the held-out streams give one value of W per
   stream that reaches a (and per episode, with resets): too few for a high quantile. The values
   are pooled over the narrowest window of ages [a − h, a + h] (clipped to the ages there are)
   that holds at least `min_pool` of them, and b̂(a) is their `quantile` as an order statistic
   (the ⌈q·m⌉-th smallest of m, no interpolation). Late ages, which fewer streams reach, get wider
   windows by themselves. A high quantile rather than the maximum: the maximum of m values moves
   with m and with one outlier; the 0.9 quantile of 50 pooled values still has 5 above it.
3. *Non-decreasing.* b̂ is replaced by its isotonic (non-decreasing) least-squares fit, by the
   pool-adjacent-violators algorithm with equal weights (scikit-learn's). For i.i.d.
   residuals, the CUSUM started at 0 is stochastically increasing in time (the Lindley
   recursion from its minimum), so its quantiles are non-decreasing and the isotonic fit removes
   only estimation noise; unlike a running maximum it is not biased upward by that noise. Where
   clean W truly dips (a calm phase of every episode) the fit averages over the dip, a
   conservative b there.
4. *Floor.* b ≥ `floor` × the standard deviation of the residual e_t on the held-out steps:
   W's increments are of that size, and early ages, where W is mostly 0, would otherwise divide
   by a quantile near 0 and turn one ordinary residual into a huge score.

Ages beyond the oldest held-out age use the last value of b.

Streaming equals batch bit for bit: W_t is `cusum`'s stream (`CusumStream`, the same additions
in the same order as its closed form) and b is fixed after `fit`, so z_t reads steps ≤ t (and
s_{t+1}, for the transition residual: latency 1) only. Everything is deterministic (parity
split, order statistics, left-to-right merges): no randomness, the same bits on every machine
as `cusum`'s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction
from typing import ClassVar

import numpy as np

from oodrl.core.detector import detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.cusum import Cusum, CusumStream
from oodrl.detectors.features import split_scores, stacked
from oodrl.errors import ContractError
from oodrl.validation import Interval


def model_and_curve_halves(n: int) -> tuple[list[int], list[int]]:
    """The indices of n fit trajectories that fit the residual model (even) and b (odd)."""
    return list(range(0, n, 2)), list(range(1, n, 2))


def ages(restarts: np.ndarray) -> np.ndarray:
    """The steps since the last restart at or before each step (restarts[0] must be True)."""
    steps = np.arange(len(restarts))
    return steps - np.maximum.accumulate(np.where(restarts, steps, 0))


def nondecreasing(values: np.ndarray) -> np.ndarray:
    """The isotonic (non-decreasing) least-squares fit of a sequence, equal weights:
    scikit-learn's pool-adjacent-violators, as the impact curves use it (`monotone_curve`)."""
    from sklearn.isotonic import isotonic_regression

    return np.asarray(isotonic_regression(np.asarray(values, dtype=np.float64)), dtype=np.float64)


def pooled_quantiles(
    values: np.ndarray, value_ages: np.ndarray, quantile: float, min_pool: int
) -> np.ndarray:
    """b̂(a) for a = 0..max age: the `quantile` (an order statistic) of the values whose age lies
    in the narrowest window [a − h, a + h] (clipped to the ages there are) that holds at least
    `min_pool` values (all of them, if there are fewer). Every age up to the oldest must hold
    values (it does for ages counted from restarts)."""
    order = np.argsort(value_ages, kind="stable")
    by_age = np.asarray(values, dtype=np.float64)[order]
    length = int(value_ages.max()) + 1
    # below[a]: how many values have an age < a.
    below = np.concatenate([[0], np.cumsum(np.bincount(value_ages, minlength=length))])
    need = min(min_pool, len(by_age))
    q = Fraction(str(quantile))
    out = np.empty(length)
    for age in range(length):

        def pooled(h: int, age: int = age) -> int:
            return int(below[min(length, age + h + 1)] - below[max(0, age - h)])

        low, high = 0, length  # a half-width of `length` holds every value
        while low < high:
            middle = (low + high) // 2
            if pooled(middle) >= need:
                high = middle
            else:
                low = middle + 1
        window = np.sort(by_age[below[max(0, age - low)] : below[min(length, age + low + 1)]])
        rank = max(math.ceil(q * len(window)), 1)
        out[age] = window[rank - 1]
    return out


class CusumTVStream(CusumStream):
    """`cusum`'s stream, each W_t divided by b at its age (the age tracked like its restarts)."""

    def __init__(self, detector: CusumTV) -> None:
        super().__init__(detector)
        self.age = 0

    def _update(self, step: Trajectory, t: int) -> StepScores:
        self.age = 0 if self.restart_next else self.age + 1
        return super()._update(step, t)

    def scored(self, first_step: int, scores: np.ndarray) -> StepScores:
        # CusumStream._update hands W_t of its one step here.
        return super().scored(first_step, self.detector._normalized(scores, np.array([self.age])))


@detector_parameters
class CusumTV(Cusum):
    """`cusum`'s W_t divided by a clean per-age curve b estimated on held-out fit streams.

    Parameters
    ----------
    residual, ridge, slack, reset_on_done
        `cusum`'s (defaults "transition", 1e-3, 0.5, False), for the statistic W_t.
    quantile : float in (0, 1), default 0.9
        The clean quantile b estimates at each age: the scores' per-age clean quantile is ≈ 1.
        High, to be a threshold-like scale, but not so high that 50 pooled values hold almost
        nothing above it (0.9 leaves 5; 0.99 would be the maximum).
    min_pool : int >= 1, default 50
        The fewest held-out values of W pooled (over neighbouring ages) for each age's quantile.
    floor : float > 0, default 1.0
        b ≥ floor × the standard deviation of the residual e_t on the held-out steps: one
        ordinary step's increment of W.
    """

    name: ClassVar[str] = "cusum_tv"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "quantile": [Interval(float, 0, 1, closed="neither")],
        "min_pool": [Interval(int, 1, None)],
        "floor": [Interval(float, 0, None, closed="neither")],
    }

    quantile: float = 0.9
    min_pool: int = 50
    floor: float = 1.0

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        n = len(trajectories)
        if n < 2:
            raise ContractError(
                f"{self.name}.fit needs at least 2 trajectories (the residual model is fitted on "
                f"half of them, the threshold curve on the other half); got {n}."
            )
        model_half, curve_half = model_and_curve_halves(n)
        super()._fit([trajectories[i] for i in model_half])
        held_out = [trajectories[i] for i in curve_half]
        statistic = np.concatenate(super()._score_many(held_out))
        curve = nondecreasing(
            pooled_quantiles(statistic, self._ages(held_out), self.quantile, self.min_pool)
        )
        self.floor_ = self.floor * float(self._residuals(held_out).std())
        self.curve_ = np.maximum(curve, self.floor_)
        if not self.curve_.min() > 0:
            # Only when every held-out residual is equal and W is 0 throughout.
            self.curve_ = np.ones_like(self.curve_)

    def _ages(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        return stacked(trajectories, lambda t: ages(self._restarts(t)))

    def _normalized(self, statistic: np.ndarray, step_ages: np.ndarray) -> np.ndarray:
        """W / b at each step's age; ages past the curve's end take its last value."""
        return statistic / self.curve_[np.minimum(step_ages, len(self.curve_) - 1)]

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        statistic = np.concatenate(super()._score_many(trajectories))
        return split_scores(self._normalized(statistic, self._ages(trajectories)), trajectories)

    def stream(self) -> DetectorStream:
        return CusumTVStream(self)
