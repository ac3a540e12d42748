"""What the neural detectors (`pedm`, `autoencoder`, `ensemble_disagreement`) share.

They train and score numpy ReLU MLP ensembles with Adam (`oodrl.detectors.mlp`) whose every
operation is machine-independent (SPEC §14): ReLU, unlike SiLU or tanh, is exact, and every
product is correctly rounded, so a fitted detector's pickle and its scores are the same bytes on
every x86-64 machine, and no stage needs torch.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors import mlp
from oodrl.detectors.features import (
    ActionEncoding,
    Standardizer,
    increments,
    stacked,
    stacked_features,
)
from oodrl.validation import Interval, SequenceOf

#: Rows per forward pass when scoring: bounds memory on long score batches, and keeps a chunk's
#: temporaries small enough for the CPU caches.
PREDICT_CHUNK = 2048

#: The training losses by name.
LOSSES: dict[str, mlp.Loss] = {"mse": mlp.mse, "gaussian_nll": mlp.gaussian_nll}


def chunked_scores(
    weights: mlp.EnsembleWeights,
    inputs: np.ndarray,
    reduce: Callable[[np.ndarray, slice], np.ndarray],
) -> np.ndarray:
    """Per-row scores (N,) float64 from every member's outputs, computed chunk by chunk.

    `reduce(outputs, rows)` gets the (M, n, out) float64 outputs of all members on the inputs
    `inputs[rows]` and returns their (n,) scores; chunking bounds memory on long score batches.
    """
    scores = []
    for start in range(0, inputs.shape[0], PREDICT_CHUNK):
        rows = slice(start, start + PREDICT_CHUNK)
        outputs = weights.predict(inputs[rows]).astype(np.float64)
        scores.append(reduce(outputs, rows))
    return np.concatenate(scores)


@detector_parameters
class NeuralDetector(BaseDetector):
    """Parameters every neural detector shares, with their defaults (a subclass may re-declare
    one with its own default).

    `hidden_sizes` (list of ints), `epochs`, `batch_size` and `lr` (Adam) are validated here once
    for all of them. Training and scoring run in numpy on the CPU.
    """

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "hidden_sizes": [SequenceOf(Interval(int, 1, None))],
        "epochs": [Interval(int, 1, None)],
        "batch_size": [Interval(int, 1, None)],
        "lr": [Interval(float, 0, None, closed="neither")],
    }

    hidden_sizes: Sequence[int] = (64, 64)
    epochs: int = 30
    batch_size: int = 256
    lr: float = 1e-3

    def _train(
        self,
        n_members: int,
        inputs: np.ndarray,
        targets: np.ndarray,
        n_outputs: int,
        loss: str,
        bootstrap: bool,
        hidden_sizes: Sequence[int],
        linear_layers: Sequence[int] = (),
    ) -> None:
        """Fit `n_members` MLPs (inputs → `n_outputs`, `hidden_sizes` between) on `targets` with
        `loss`, each on a bootstrap resample or on all rows (no ReLU after the hidden layers in
        `linear_layers`); sets `weights_` and `training_losses_` (mean minibatch loss per epoch)."""
        rng = np.random.default_rng(self.seed)
        sizes = (inputs.shape[1], *hidden_sizes, n_outputs)
        initial = mlp.init_weights(n_members, sizes, rng, linear_layers)
        self.weights_, self.training_losses_ = mlp.train(
            initial,
            inputs,
            targets,
            LOSSES[loss],
            mlp.OptimiserSettings(self.epochs, self.batch_size, self.lr),
            mlp.member_indices(n_members, len(inputs), bootstrap, rng),
            rng,
        )


@detector_parameters
class TransitionEnsemble(NeuralDetector):
    """An ensemble of M networks from the standardised (s_t, one-hot a_t) to the standardised
    increment s_{t+1} − s_t: the dynamics model `pedm` and `ensemble_disagreement` share."""

    n_members: int = 5

    def _standardized_inputs(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        inputs = stacked_features(trajectories, "state_action", self.action_encoding_)
        return self.input_standardizer_.transform(inputs)

    def _fit_ensemble(
        self, trajectories: Sequence[Trajectory], loss: str, outputs_per_coordinate: int,
        bootstrap: bool,
    ) -> Standardizer:  # fmt: skip
        """Train the members with `loss` ("mse" or "gaussian_nll"), each on a bootstrap
        resample or on all transitions; returns the increments' standardizer."""
        self.action_encoding_ = ActionEncoding.fit(trajectories)
        inputs = stacked_features(trajectories, "state_action", self.action_encoding_)
        deltas = stacked(trajectories, increments)
        self.input_standardizer_ = Standardizer.fit(inputs)
        target_standardizer = Standardizer.fit(deltas)
        self._train(
            self.n_members,
            self.input_standardizer_.transform(inputs),
            target_standardizer.transform(deltas),
            outputs_per_coordinate * deltas.shape[1],
            loss,
            bootstrap,
            self.hidden_sizes,
        )
        return target_standardizer
