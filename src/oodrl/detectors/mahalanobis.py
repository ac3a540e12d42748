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

from oodrl.core.detector import detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import FeatureSetDetector, GaussianModel, split_scores
from oodrl.validation import Interval


@detector_parameters
class MahalanobisDistance(FeatureSetDetector):
    """Squared Mahalanobis distance of standardised step features from the fit distribution.

    Parameters
    ----------
    features : "state" | "state_action" | "transition", default "state"
        Which channels form x_t.
    ridge : float > 0, default 1e-3
        λ added to the diagonal of the covariance of the standardised features.
    """

    name: ClassVar[str] = "mahalanobis_distance"
    # z_t reads step t alone (s_t, a_t, s_{t+1}): a stream scores each step on its own.
    row_independent: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "ridge": [Interval(float, 0, None, closed="neither")],
    }

    ridge: float = 1e-3

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self.gaussian_ = GaussianModel.fit(self._fit_features(trajectories), self.ridge)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        x = self._standardized_features(trajectories)
        return split_scores(self.gaussian_.squared_distance(x), trajectories)
