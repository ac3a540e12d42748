"""`time_series_features`: rolling-window descriptors against their ID distribution (SPEC §5).

For each step t the window of the last L standardised states s_{t−L+1..t} is summarised per
state coordinate by seven descriptors:

- mean, standard deviation, least-squares slope, lag-1 autocorrelation,
- range (max − min), mean absolute first difference,
- spectral centroid: the power-weighted mean frequency (cycles per step, in (0, 0.5]) of the
  periodogram of the mean-removed window, DC excluded,

and the 7·d_s descriptor vector's distance from the descriptors of every window of the fit
trajectories is the score: the squared Mahalanobis distance of the standardised descriptors with
ridge λ (default), or the mean squared robust z-score (median / 1.4826·MAD per descriptor). A
constant window has no defined autocorrelation or spectrum; both are set to 0 there.

Early steps: z_t for t < L − 1 (no full window yet) is the score of the first full window, the
one ending at L − 1, so every step has a score from a descriptor vector of the same kind as the fit
ones. In the protocol the onset lies far beyond L, so this never borrows anomalous steps.

Episode resets: windows may span a reset. Clean fit data contains the same reset jumps, so
reset-spanning windows are part of the ID descriptor distribution rather than special-cased.
"""

from __future__ import annotations

import decimal
import functools
from collections import deque
from collections.abc import Sequence
from typing import ClassVar

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from oodrl import numerics
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import GaussianModel, Standardizer, stacked
from oodrl.errors import ContractError
from oodrl.validation import Interval, Options

DISTANCES = ("mahalanobis", "robust_z")
DESCRIPTORS = (
    "mean",
    "std",
    "slope",
    "autocorrelation",
    "range",
    "mean_abs_diff",
    "spectral_centroid",
)

#: 1.4826 · MAD estimates the standard deviation of a normal distribution.
_MAD_TO_SD = 1.4826


def _ratio_or_zero(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    positive = denominator > 0
    return np.divide(numerator, denominator, out=np.zeros_like(numerator), where=positive)


@functools.cache
def dft_basis(window: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of 2π·k·n/L, (L, L//2) for n < L and frequencies k = 1..L//2 (no DC term).

    Evaluated with ``decimal`` (Taylor series at 40 digits), so the table is the same float64
    on every machine whatever its libm; the power spectrum is then |Σ_n x_n e^{−2πikn/L}|².
    """
    with decimal.localcontext() as context:
        context.prec = 40
        two_pi = 2 * _decimal_pi()
        # k·n mod L: the same angle in [0, 2π), where the Taylor series converges fast.
        frequencies = range(1, window // 2 + 1)
        angles = [[two_pi * (k * n % window) / window for k in frequencies] for n in range(window)]
        cosines = [[float(_decimal_cos(a)) for a in row] for row in angles]
        sines = [[float(_decimal_cos(a - two_pi / 4)) for a in row] for row in angles]
    return np.array(cosines), np.array(sines)


def _decimal_pi() -> decimal.Decimal:
    """π to the context's precision (Machin's formula)."""
    return 4 * (4 * _decimal_arctan_inverse(5) - _decimal_arctan_inverse(239))


def _decimal_arctan_inverse(x: int) -> decimal.Decimal:
    total, power, n, sign = decimal.Decimal(0), decimal.Decimal(1) / x, 1, 1
    while power:
        total += sign * power / n
        power /= x * x
        n, sign = n + 2, -sign
        if power < decimal.Decimal(10) ** -(decimal.getcontext().prec + 5):
            break
    return total


def _decimal_cos(angle: decimal.Decimal) -> decimal.Decimal:
    total, term, n = decimal.Decimal(0), decimal.Decimal(1), 0
    while True:
        total += term
        n += 2
        term = -term * angle * angle / (n * (n - 1))
        if abs(term) < decimal.Decimal(10) ** -(decimal.getcontext().prec + 5):
            return total


def window_descriptors(series: np.ndarray, window: int) -> np.ndarray:
    """(T − L + 1, 7·d) descriptors of every length-L window of a (T, d) series.

    Row i describes series[i : i + L]; columns are grouped by descriptor (DESCRIPTORS order),
    each group holding one column per coordinate.
    """
    windows = sliding_window_view(series, window, axis=0)  # (n, d, L)
    mean = windows.mean(axis=-1)
    centred = windows - mean[..., None]
    sum_squares = (centred * centred).sum(axis=-1)
    time = np.arange(window) - (window - 1) / 2.0
    # numerics.matmul and a DFT, not @ and np.fft: BLAS and numpy's FFT differ per CPU (SPEC §14).
    slope = numerics.matmul(centred, time / (time * time).sum())
    lag_products = (centred[..., :-1] * centred[..., 1:]).sum(axis=-1)
    cosines, sines = dft_basis(window)
    power = numerics.matmul(centred, cosines) ** 2 + numerics.matmul(centred, sines) ** 2
    frequencies = np.arange(1, power.shape[-1] + 1) / window
    return np.concatenate(
        [
            mean,
            np.sqrt(sum_squares / window),
            slope,
            _ratio_or_zero(lag_products, sum_squares),
            np.ptp(windows, axis=-1),
            np.abs(np.diff(windows, axis=-1)).mean(axis=-1),
            _ratio_or_zero(numerics.matmul(power, frequencies), power.sum(axis=-1)),
        ],
        axis=1,
    )


@detector_parameters
class TimeSeriesFeatures(BaseDetector):
    """Distance of rolling-window descriptors of the state from their fit distribution.

    Parameters
    ----------
    window : int >= 3, default 32
        Window length L (steps); every trajectory needs T >= L.
    distance : "mahalanobis" | "robust_z", default "mahalanobis"
    ridge : float > 0, default 1e-3
        λ of the Mahalanobis distance (on standardised descriptors).
    """

    name: ClassVar[str] = "time_series_features"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "window": [Interval(int, 3, None)],
        "distance": [Options(DISTANCES)],
        "ridge": [Interval(float, 0, None, closed="neither")],
    }

    window: int = 32
    distance: str = "mahalanobis"
    ridge: float = 1e-3

    def _descriptors(self, trajectory: Trajectory) -> np.ndarray:
        if self.window > trajectory.T:
            raise ContractError(
                f"{self.name} needs trajectories of at least window={self.window} "
                f"steps; got T={trajectory.T}. Lower 'window' or use longer trajectories."
            )
        series = self.state_standardizer_.transform(trajectory.states.astype(np.float64))
        return window_descriptors(series, self.window)

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self.state_standardizer_ = Standardizer.fit(
            stacked(trajectories, lambda t: t.states.astype(np.float64))
        )
        descriptors = stacked(trajectories, self._descriptors)
        if self.distance == "mahalanobis":
            self.descriptor_standardizer_ = Standardizer.fit(descriptors)
            self.gaussian_ = GaussianModel.fit(
                self.descriptor_standardizer_.transform(descriptors), self.ridge
            )
        else:
            median = np.median(descriptors, axis=0)
            spread = _MAD_TO_SD * np.median(np.abs(descriptors - median), axis=0)
            fallback = Standardizer.fit(descriptors).scale
            self.descriptor_standardizer_ = Standardizer(
                median, np.where(spread > 0, spread, fallback)
            )

    def _window_scores(self, descriptors: np.ndarray) -> np.ndarray:
        z = self.descriptor_standardizer_.transform(descriptors)
        if self.distance == "mahalanobis":
            return self.gaussian_.squared_distance(z)
        return np.mean(z**2, axis=1)

    def _score(self, trajectory: Trajectory) -> np.ndarray:
        scores = self._window_scores(self._descriptors(trajectory))
        return np.concatenate([np.full(self.window - 1, scores[0]), scores])

    def stream(self) -> DetectorStream:
        return WindowStream(self)


class WindowStream(DetectorStream):
    """The last L standardised states in a ring; each full window is described and scored
    by the batch code. The update of step L − 1 also returns the L − 1 early steps (scored with
    the first window, as `score` does); a stream shorter than the window has no scores
    (`score` refuses such a trajectory)."""

    def __init__(self, detector: TimeSeriesFeatures) -> None:
        super().__init__(detector)
        self.recent: deque[np.ndarray] = deque(maxlen=detector.window)

    def _update(self, step: Trajectory, t: int) -> StepScores:
        detector = self.detector
        self.recent.extend(detector.state_standardizer_.transform(step.states.astype(np.float64)))
        if len(self.recent) < detector.window:
            return ()
        descriptors = window_descriptors(np.array(self.recent), detector.window)
        score = detector._window_scores(descriptors)
        if t + 1 == detector.window:
            return self.scored(0, np.repeat(score, detector.window))
        return self.scored(t, score)

    def _flush(self) -> StepScores:
        self.recent.clear()
        return ()
