"""`cusum`: one-sided CUSUM of a one-step transition residual (SPEC §5).

    g_t = max(0, g_{t−1} + e_t − ν − k),   g_{−1} = 0,   z_t = g_t.

e_t is the residual of a cheap linear dynamics model: ridge regression of the standardised
increment s'_t − s_t on the standardised (s_t, one-hot a_t), fitted on the fit set. With r_t the
residual vector and σ its per-coordinate standard deviation on the fit set,

    e_t = (1/d_s) Σ_i (r_{t,i} / σ_i)²,

so e_t ≈ 1 on in-distribution data. ν is the fit-set mean of e_t and the slack k is
`slack` × (fit-set standard deviation of e_t): in-distribution the statistic drifts down by k per
step and stays near 0; a sustained increase of the residual by more than k accumulates.

Episode resets: by default g is *not* reset at `dones`. The residual uses (s_t, a_t, s'_t), and
s'_t is the terminal observation at an episode end, so the reset jump never enters e_t; and a
trajectory is one deployment stream whose faults persist across resets, so evidence carries
over. `reset_on_done=True` restarts g at 0 on the first step of every new episode instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import BaseDetector
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    ActionEncoding,
    Standardizer,
    increments,
    split_scores,
    stacked,
    trajectory_features,
)
from oodrl.validation import Interval, IsType


@dataclass(frozen=True)
class LinearResidualModel:
    """Ridge regression y ≈ x W + b on standardised x; residuals scaled to unit variance."""

    coefficients: np.ndarray
    intercept: np.ndarray
    residual_scale: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, ridge: float) -> LinearResidualModel:
        # numerics, not @/np.linalg: BLAS and LAPACK kernels differ per CPU (SPEC §14).
        n, d = x.shape
        x_mean, y_mean = x.mean(axis=0), y.mean(axis=0)
        centred = x - x_mean
        gram = numerics.matmul(centred.T, centred) / n + ridge * np.eye(d)
        coefficients = numerics.spd_solve(gram, numerics.matmul(centred.T, y - y_mean) / n)
        intercept = y_mean - numerics.matmul(x_mean, coefficients)
        residuals = y - numerics.matmul(x, coefficients) - intercept
        scale = residuals.std(axis=0)
        return cls(coefficients, intercept, np.where(scale > 0, scale, 1.0))

    def residual(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """e = mean over coordinates of the squared scaled residual, one value per row."""
        predicted = numerics.matmul(x, self.coefficients) + self.intercept
        scaled = (y - predicted) / self.residual_scale
        return np.mean(scaled**2, axis=1)


def cusum(drift: np.ndarray, restarts: np.ndarray) -> np.ndarray:
    """g_t = max(0, g_{t−1} + drift_t), restarting from g = 0 where `restarts` is True.

    Computed in closed form per segment (Lindley): with S the cumulative sum of the drift,
    g_t = S_t − min(0, min_{s ≤ t} S_s).
    """
    starts = np.flatnonzero(restarts)
    segments = np.split(drift, starts[starts > 0])
    out = []
    for segment in segments:
        total = np.cumsum(segment)
        out.append(total - np.minimum(np.minimum.accumulate(total), 0.0))
    return np.concatenate(out)


class Cusum(BaseDetector):
    """One-sided CUSUM of a standardised one-step transition residual.

    Parameters
    ----------
    ridge : float > 0, default 1e-3
        λ of the ridge regression of the increment on (state, one-hot action), in units of the
        standardised inputs' variance.
    slack : float >= 0, default 0.5
        k in units of the fit-set standard deviation of the residual e_t.
    reset_on_done : bool, default False
        Restart g at 0 on the first step of each new episode.
    """

    name: ClassVar[str] = "cusum"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "ridge": [Interval(float, 0, None, closed="neither")],
        "slack": [Interval(float, 0, None)],
        "reset_on_done": [IsType(bool)],
    }

    def __init__(
        self,
        *,
        ridge: float = 1e-3,
        slack: float = 0.5,
        reset_on_done: bool = False,
        threshold_rule: str = "percentile",
        threshold_percentile: float = 99.0,
        seed: int = 0,
    ) -> None:
        super().__init__(
            threshold_rule=threshold_rule, threshold_percentile=threshold_percentile, seed=seed
        )
        self.ridge = ridge
        self.slack = slack
        self.reset_on_done = reset_on_done

    def _inputs(self, trajectory: Trajectory) -> np.ndarray:
        return trajectory_features(trajectory, "state_action", self.action_encoding_)

    def _residuals(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        x = self.input_standardizer_.transform(stacked(trajectories, self._inputs))
        y = self.target_standardizer_.transform(stacked(trajectories, increments))
        return self.model_.residual(x, y)

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self.action_encoding_ = ActionEncoding.fit(trajectories)
        inputs = stacked(trajectories, self._inputs)
        deltas = stacked(trajectories, increments)
        self.input_standardizer_ = Standardizer.fit(inputs)
        self.target_standardizer_ = Standardizer.fit(deltas)
        x = self.input_standardizer_.transform(inputs)
        y = self.target_standardizer_.transform(deltas)
        self.model_ = LinearResidualModel.fit(x, y, self.ridge)
        residuals = self.model_.residual(x, y)
        self.residual_mean_ = float(residuals.mean())
        self.slack_ = self.slack * float(residuals.std())

    def _restarts(self, trajectory: Trajectory) -> np.ndarray:
        restarts = np.zeros(trajectory.T, dtype=bool)
        restarts[0] = True
        if self.reset_on_done:
            restarts[1:] = trajectory.dones[:-1]
        return restarts

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        drift = self._residuals(trajectories) - self.residual_mean_ - self.slack_
        scores = cusum(drift, stacked(trajectories, self._restarts))
        return split_scores(scores, trajectories)
