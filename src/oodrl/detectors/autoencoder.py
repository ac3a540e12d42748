"""`autoencoder`: reconstruction error of an undercomplete autoencoder (SPEC §5).

z_t = ‖x_t − g(f(x_t))‖², x_t the standardised features of step t (state by default), f an MLP
encoder to a linear `latent_dim` bottleneck and g its mirror-image decoder, trained with the mean
squared reconstruction error on the fit set. The error is measured in standardised units.

Networks, and why they are the same bytes on every machine: `oodrl.detectors.neural`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.detector import detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import FeatureSetDetector, split_scores
from oodrl.detectors.neural import NeuralDetector, chunked_scores
from oodrl.validation import Interval


@detector_parameters
class Autoencoder(NeuralDetector, FeatureSetDetector):
    """Squared reconstruction error of standardised step features.

    Parameters
    ----------
    features : "state" | "state_action" | "transition", default "state"
    hidden_sizes : list of int, default [64, 64]
        Encoder widths; the decoder mirrors them.
    latent_dim : int >= 1, default 3
        Bottleneck width (keep it below the feature dimension).
    epochs : int >= 1, default 40
    batch_size : int >= 1, default 256
    lr : float > 0, default 3e-3
    """

    name: ClassVar[str] = "autoencoder"
    # z_t reads step t alone (s_t, a_t, s_{t+1}): a stream scores each step on its own.
    row_independent: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "latent_dim": [Interval(int, 1, None)],
    }

    latent_dim: int = 3
    # The autoencoder's own defaults of two NeuralDetector parameters.
    epochs: int = 40
    lr: float = 3e-3

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        z = self._fit_features(trajectories)
        layers = [*self.hidden_sizes, self.latent_dim, *reversed(self.hidden_sizes)]
        # A linear code: a ReLU on a narrow bottleneck lets whole latent units die (measured: one
        # of three on pipeline-size data, +45% reconstruction error).
        bottleneck = len(self.hidden_sizes)
        self._train(1, z, z, z.shape[1], "mse", False, layers, linear_layers=(bottleneck,))

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        z = self._standardized_features(trajectories)

        def reconstruction_error(outputs: np.ndarray, rows: slice) -> np.ndarray:
            return ((outputs[0] - z[rows]) ** 2).sum(axis=-1)

        scores = chunked_scores(self.weights_, z, reconstruction_error)
        return split_scores(scores, trajectories)
