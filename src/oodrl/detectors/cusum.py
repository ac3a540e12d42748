"""`cusum`: one-sided CUSUM of a scalar residual (SPEC §5).

    g_t = max(0, g_{t−1} + e_t − ν − k),   g_{−1} = 0,   z_t = g_t.

The residual e_t (`residual`):

- ``"transition"`` (default): the residual of a cheap linear dynamics model, ridge regression of
  the standardised increment s'_t − s_t on the standardised (s_t, one-hot a_t), fitted on the
  fit set. With r_t the residual vector and σ its per-coordinate standard deviation on the fit
  set, e_t = (1/d_s) Σ_i (r_{t,i} / σ_i)². It uses s'_t = s_{t+1}: latency 1.
- ``"state"``: the standardised distance of s_t from the fit-set mean, e_t = (1/d_s) Σ_i
  ((s_{t,i} − μ_i) / σ_i)², μ and σ the fit-set mean and standard deviation per coordinate
  (the CUSUM of a state-outlier score, as in the reference paper). Latency 0.

Both are ≈ 1 on average on in-distribution data. ν is the fit-set mean of e_t and the slack k is
`slack` × (fit-set standard deviation of e_t): in-distribution the statistic drifts down by k per
step and stays near 0; a sustained increase of the residual by more than k accumulates. Which
residual is accumulated decides what the detector sees: docs/cusum.md compares the two.

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
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    ActionEncoding,
    Standardizer,
    increments,
    split_scores,
    stacked,
    stacked_features,
)
from oodrl.validation import Interval, IsType, Options

RESIDUALS = ("transition", "state")


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


@dataclass(frozen=True)
class TransitionResidual:
    """e_t of the linear dynamics model on the standardised (s_t, a_t) → s'_t − s_t."""

    action_encoding: ActionEncoding
    inputs: Standardizer
    targets: Standardizer
    model: LinearResidualModel

    @classmethod
    def fit(cls, trajectories: Sequence[Trajectory], ridge: float) -> TransitionResidual:
        encoding = ActionEncoding.fit(trajectories)
        inputs = stacked_features(trajectories, "state_action", encoding)
        deltas = stacked(trajectories, increments)
        input_standardizer, target_standardizer = Standardizer.fit(inputs), Standardizer.fit(deltas)
        model = LinearResidualModel.fit(
            input_standardizer.transform(inputs), target_standardizer.transform(deltas), ridge
        )
        return cls(encoding, input_standardizer, target_standardizer, model)

    def __call__(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        x = self.inputs.transform(
            stacked_features(trajectories, "state_action", self.action_encoding)
        )
        y = self.targets.transform(stacked(trajectories, increments))
        return self.model.residual(x, y)


@dataclass(frozen=True)
class StateResidual:
    """e_t = mean over coordinates of the squared standardised state (s_t − μ) / σ."""

    states: Standardizer

    @classmethod
    def fit(cls, trajectories: Sequence[Trajectory]) -> StateResidual:
        return cls(Standardizer.fit(stacked(trajectories, _states)))

    def __call__(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        z = self.states.transform(stacked(trajectories, _states))
        return np.mean(z**2, axis=1)


def _states(trajectory: Trajectory) -> np.ndarray:
    return trajectory.states.astype(np.float64)


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


class CusumStream(DetectorStream):
    """g_t by the closed form of `cusum`, step by step: the running sum S of the drift since
    the last restart and its running minimum (the same additions in the same order)."""

    def __init__(self, detector: Cusum) -> None:
        super().__init__(detector)
        self.total = self.lowest = 0.0
        self.restart_next = True

    def _update(self, step: Trajectory, t: int) -> StepScores:
        drift = float(self.detector._drift([step])[0])
        if self.restart_next:
            self.total = self.lowest = drift
        else:
            self.total += drift
            self.lowest = min(self.lowest, self.total)
        self.restart_next = self.detector.reset_on_done and bool(step.dones[0])
        return self.scored(t, np.array([self.total - min(self.lowest, 0.0)]))

    def _flush(self) -> StepScores:
        self.restart_next = True
        return ()


@detector_parameters
class Cusum(BaseDetector):
    """One-sided CUSUM of a standardised residual: a transition residual or a state distance.

    Parameters
    ----------
    residual : "transition" | "state", default "transition"
        What is accumulated: the one-step transition residual of a linear dynamics model, or
        the standardised distance of the state from its fit-set mean.
    ridge : float > 0, default 1e-3
        λ of the ridge regression of the increment on (state, one-hot action), in units of the
        standardised inputs' variance (``residual="transition"`` only).
    slack : float >= 0, default 0.5
        k in units of the fit-set standard deviation of the residual e_t.
    reset_on_done : bool, default False
        Restart g at 0 on the first step of each new episode.
    """

    name: ClassVar[str] = "cusum"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "residual": [Options(RESIDUALS)],
        "ridge": [Interval(float, 0, None, closed="neither")],
        "slack": [Interval(float, 0, None)],
        "reset_on_done": [IsType(bool)],
    }

    residual: str = "transition"
    ridge: float = 1e-3
    slack: float = 0.5
    reset_on_done: bool = False

    @property
    def latency(self) -> int:
        # The transition residual uses s'_t = s_{t+1}: known one step after t.
        return int(self.residual == "transition")

    def _residuals(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        return self.residual_model_(trajectories)

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        if self.residual == "transition":
            self.residual_model_ = TransitionResidual.fit(trajectories, self.ridge)
        else:
            self.residual_model_ = StateResidual.fit(trajectories)
        residuals = self._residuals(trajectories)
        self.residual_mean_ = float(residuals.mean())
        self.slack_ = self.slack * float(residuals.std())

    def _restarts(self, trajectory: Trajectory) -> np.ndarray:
        restarts = np.zeros(trajectory.T, dtype=bool)
        restarts[0] = True
        if self.reset_on_done:
            restarts[1:] = trajectory.dones[:-1]
        return restarts

    def _drift(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        """e_t − ν − k of every step, stacked."""
        return self._residuals(trajectories) - self.residual_mean_ - self.slack_

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        scores = cusum(self._drift(trajectories), stacked(trajectories, self._restarts))
        return split_scores(scores, trajectories)

    def stream(self) -> DetectorStream:
        return CusumStream(self)
