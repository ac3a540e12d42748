"""`mahalanobis_distance`: squared Mahalanobis distance of a step's features (SPEC §5).

z_t = (x_t − μ)ᵀ(Σ + λI)⁻¹(x_t − μ), with x_t the standardised features of step t (state,
state-action or transition; see `oodrl.detectors.features`) and μ, Σ their mean and covariance on
the fit set. Standardising first makes the ridge λ unit-free: it is added to a correlation
matrix. The one-hot action columns are linearly dependent (they sum to one), which is one reason
the ridge is needed.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.detector import BaseDetector
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    FEATURE_SETS,
    ActionEncoding,
    GaussianModel,
    Standardizer,
    split_scores,
    stacked,
    trajectory_features,
)
from oodrl.validation import Interval, Options


class MahalanobisDistance(BaseDetector):
    """Squared Mahalanobis distance of standardised step features from the fit distribution.

    Parameters
    ----------
    features : "state" | "state_action" | "transition", default "state"
        Which channels form x_t.
    ridge : float > 0, default 1e-3
        λ added to the diagonal of the covariance of the standardised features.
    """

    name: ClassVar[str] = "mahalanobis_distance"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "features": [Options(FEATURE_SETS)],
        "ridge": [Interval(float, 0, None, closed="neither")],
    }

    def __init__(
        self,
        *,
        features: str = "state",
        ridge: float = 1e-3,
        threshold_rule: str = "percentile",
        threshold_percentile: float = 99.0,
        seed: int = 0,
    ) -> None:
        super().__init__(
            threshold_rule=threshold_rule, threshold_percentile=threshold_percentile, seed=seed
        )
        self.features = features
        self.ridge = ridge

    @property
    def latency(self) -> int:
        # "transition" features hold the increment s_{t+1} − s_t: known one step after t.
        return int(self.features == "transition")

    def _features(self, trajectory: Trajectory) -> np.ndarray:
        return trajectory_features(trajectory, self.features, self.action_encoding_)

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self.action_encoding_ = ActionEncoding.fit(trajectories)
        x = stacked(trajectories, self._features)
        self.standardizer_ = Standardizer.fit(x)
        self.gaussian_ = GaussianModel.fit(self.standardizer_.transform(x), self.ridge)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        x = self.standardizer_.transform(stacked(trajectories, self._features))
        return split_scores(self.gaussian_.squared_distance(x), trajectories)
