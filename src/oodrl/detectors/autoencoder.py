"""`autoencoder`: reconstruction error of an undercomplete autoencoder (SPEC §5).

z_t = ‖x_t − g(f(x_t))‖², x_t the standardised features of step t (state by default), f an MLP
encoder to a `latent_dim` bottleneck and g its mirror-image decoder, trained with the mean squared
reconstruction error on the fit set. The error is measured in standardised units.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    FEATURE_SETS,
    ActionEncoding,
    Standardizer,
    split_scores,
    stacked,
    trajectory_features,
)
from oodrl.detectors.neural import TorchDetector, chunked_scores
from oodrl.validation import Interval, Options


class Autoencoder(TorchDetector):
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
    device : "auto" | "cpu" | "cuda", default "auto"
        Where the network trains ("auto" = CUDA when available); scoring runs in numpy.
    """

    name: ClassVar[str] = "autoencoder"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "features": [Options(FEATURE_SETS)],
        "latent_dim": [Interval(int, 1, None)],
    }

    def __init__(
        self,
        *,
        features: str = "state",
        hidden_sizes: Sequence[int] = (64, 64),
        latent_dim: int = 3,
        epochs: int = 40,
        batch_size: int = 256,
        lr: float = 3e-3,
        device: str = "auto",
        threshold_rule: str = "percentile",
        threshold_percentile: float = 99.0,
        seed: int = 0,
    ) -> None:
        super().__init__(
            threshold_rule=threshold_rule, threshold_percentile=threshold_percentile, seed=seed
        )
        self.features = features
        self.hidden_sizes = hidden_sizes
        self.latent_dim = latent_dim
        self.epochs = epochs
        self.batch_size = batch_size
        self.lr = lr
        self.device = device

    def _features(self, trajectory: Trajectory) -> np.ndarray:
        return trajectory_features(trajectory, self.features, self.action_encoding_)

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        from oodrl.detectors.torch_utils import (
            EnsembleMLP,
            member_indices,
            member_mse,
            seeded_generator,
            train_ensemble,
        )

        self.action_encoding_ = ActionEncoding.fit(trajectories)
        x = stacked(trajectories, self._features)
        self.standardizer_ = Standardizer.fit(x)
        generator = seeded_generator(self.seed)
        layers = [*self.hidden_sizes, self.latent_dim, *reversed(self.hidden_sizes)]
        model = EnsembleMLP(1, x.shape[1], x.shape[1], layers, generator)
        z = self.standardizer_.transform(x)
        self.weights_ = train_ensemble(
            model,
            z,
            z,
            member_mse,
            self._train_settings(),
            member_indices(1, len(z), False, generator),
            generator,
        )

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        z = self.standardizer_.transform(stacked(trajectories, self._features))

        def reconstruction_error(outputs: np.ndarray, rows: slice) -> np.ndarray:
            return ((outputs[0] - z[rows]) ** 2).sum(axis=-1)

        scores = chunked_scores(self.weights_, z, reconstruction_error)
        return split_scores(scores, trajectories)
