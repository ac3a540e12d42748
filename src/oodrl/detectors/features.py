"""Feature extraction and feature-space statistics shared by the detectors (numpy only).

Feature sets (the `features` parameter of the detectors that take one):

- ``"state"`` — the observation ``s_t``;
- ``"state_action"`` — ``(s_t, a_t)`` with a discrete action one-hot encoded;
- ``"transition"`` — ``(s_t, a_t, s'_t - s_t)``: the increment rather than ``s'_t`` itself, so the
  dynamics are not hidden behind the strong ``s' ≈ s`` correlation.

Transitions use ``next_states``, never ``states[t + 1]``: at an episode end ``next_states[t]`` is
the terminal observation, so no feature ever spans the reset jump. Detectors see the *commanded*
actions (``Trajectory.actions``), as a deployed monitor would; the executed actions are not
theirs to know.

Everything learned here is learned on the fit set only and stored in frozen dataclasses, so a
fitted detector's state is plain numpy arrays.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.errors import ContractError
from oodrl.validation import Options

FEATURE_SETS = ("state", "state_action", "transition")

#: A standard deviation at or below this is treated as a constant coordinate (scale 1).
_MIN_SCALE = 1e-12


@dataclass(frozen=True)
class ActionEncoding:
    """How actions become features: one-hot for `n_actions` discrete actions, else as given.

    A discrete action outside the fitted range (never seen while fitting) is encoded as an
    all-zero row: it matches no known action, so it cannot be mistaken for one.
    """

    n_actions: int | None
    dim: int

    @classmethod
    def fit(cls, trajectories: Sequence[Trajectory]) -> ActionEncoding:
        actions = [t.actions for t in trajectories]
        if any(a.ndim != actions[0].ndim for a in actions):
            raise ContractError("Fit trajectories mix discrete and continuous actions.")
        if actions[0].ndim == 2:
            dims = {a.shape[1] for a in actions}
            if len(dims) != 1:
                raise ContractError(f"Fit trajectories have mixed action dimensions {dims}.")
            return cls(None, dims.pop())
        n_actions = int(max(a.max() for a in actions)) + 1
        return cls(n_actions, n_actions)

    def encode(self, actions: np.ndarray) -> np.ndarray:
        if self.n_actions is None:
            if actions.ndim != 2 or actions.shape[1] != self.dim:
                raise ContractError(
                    f"Expected continuous actions of dimension {self.dim}; "
                    f"got an action array of shape {actions.shape}."
                )
            return actions.astype(np.float64)
        if actions.ndim != 1:
            raise ContractError(
                f"Expected discrete actions (shape (T,)); got shape {actions.shape}."
            )
        return (actions[:, None] == np.arange(self.n_actions)).astype(np.float64)


def increments(trajectory: Trajectory) -> np.ndarray:
    """The (T, d_s) float64 state increments s'_t − s_t (never across a reset: see above)."""
    return trajectory.next_states.astype(np.float64) - trajectory.states


def trajectory_features(
    trajectory: Trajectory, feature_set: str, encoding: ActionEncoding
) -> np.ndarray:
    """The (T, d) float64 features of one trajectory for a feature set of FEATURE_SETS."""
    states = trajectory.states.astype(np.float64)
    if feature_set == "state":
        return states
    actions = encoding.encode(trajectory.actions)
    if feature_set == "state_action":
        return np.hstack([states, actions])
    return np.hstack([states, actions, increments(trajectory)])


def stacked(
    trajectories: Sequence[Trajectory], per_trajectory: Callable[[Trajectory], np.ndarray]
) -> np.ndarray:
    """Per-trajectory arrays of shape (T_i, ...) concatenated along the first axis."""
    return np.concatenate([per_trajectory(t) for t in trajectories], axis=0)


def stacked_features(
    trajectories: Sequence[Trajectory], feature_set: str, encoding: ActionEncoding
) -> np.ndarray:
    """The (ΣT_i, d) float64 features of a feature set, trajectory after trajectory."""
    return stacked(trajectories, lambda t: trajectory_features(t, feature_set, encoding))


def split_scores(scores: np.ndarray, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
    """Undo `stacked` for a (sum T_i,) score vector: one array per trajectory."""
    return np.split(scores, np.cumsum([t.T for t in trajectories])[:-1])


def seeded_subsample(n: int, limit: int, seed: int) -> np.ndarray:
    """Sorted indices of at most `limit` of n rows, drawn without replacement from `seed`."""
    if n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, limit, replace=False))


@dataclass(frozen=True)
class Standardizer:
    """Per-coordinate centring and scaling learned on the fit set (a constant coordinate: 1)."""

    mean: np.ndarray
    scale: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray) -> Standardizer:
        std = x.std(axis=0)
        return cls(x.mean(axis=0), np.where(std > _MIN_SCALE, std, 1.0))

    def transform(self, x: np.ndarray) -> np.ndarray:
        return (x - self.mean) / self.scale


@dataclass(frozen=True)
class GaussianModel:
    """Mean and ridge-regularised precision (Σ + λI)⁻¹ of a feature distribution.

    Fit it on standardised features, so that λ is in units of the features' variance.
    """

    mean: np.ndarray
    precision: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray, ridge: float) -> GaussianModel:
        # numerics, not np.cov/np.linalg: BLAS and LAPACK kernels differ per CPU (SPEC §14).
        mean = x.mean(axis=0)
        centred = x - mean
        covariance = numerics.matmul(centred.T, centred) / len(x)
        regularised = covariance + ridge * np.eye(covariance.shape[0])
        return cls(mean, numerics.spd_inverse(regularised))

    def squared_distance(self, x: np.ndarray) -> np.ndarray:
        """(x − μ)ᵀ P (x − μ) for every row of x."""
        centred = x - self.mean
        return (numerics.matmul(centred, self.precision) * centred).sum(axis=1)


@detector_parameters
class FeatureSetDetector(BaseDetector):
    """A detector of the standardised step features of one feature set (its `features`).

    `_fit_features` learns the action encoding and the standardisation on the fit set;
    `_standardized_features` applies them to the trajectories being scored.
    """

    _parameter_constraints: ClassVar[dict[str, list]] = {"features": [Options(FEATURE_SETS)]}

    features: str = "state"

    @property
    def latency(self) -> int:
        # "transition" features hold the increment s_{t+1} − s_t: known one step after t.
        return int(self.features == "transition")

    def _fit_features(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        """The fit set's standardised features; sets `action_encoding_` and `standardizer_`."""
        self.action_encoding_ = ActionEncoding.fit(trajectories)
        x = stacked_features(trajectories, self.features, self.action_encoding_)
        self.standardizer_ = Standardizer.fit(x)
        return self.standardizer_.transform(x)

    def _standardized_features(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        x = stacked_features(trajectories, self.features, self.action_encoding_)
        return self.standardizer_.transform(x)
