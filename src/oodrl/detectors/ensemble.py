"""`ensemble_disagreement`: epistemic uncertainty of a bootstrapped dynamics ensemble (SPEC §5).

M deterministic networks predict the standardised increment s_{t+1} − s_t from the standardised
(s_t, one-hot a_t), each trained with the mean squared error on its own bootstrap resample of the
fit transitions. The score is their spread about the ensemble mean:

    z_t = (1/M) Σ_m ‖ŝ^{(m)}_t − s̄_t‖²,   s̄_t = (1/M) Σ_m ŝ^{(m)}_t,

in standardised increment units. It uses (s_t, a_t) only, never the observed s_{t+1}: it flags
inputs the ensemble has not learned, not transitions that contradict what it has learned.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    ActionEncoding,
    Standardizer,
    increments,
    split_scores,
    stacked,
    trajectory_features,
)
from oodrl.detectors.neural import TorchDetector, chunked_scores
from oodrl.validation import Interval


class EnsembleDisagreement(TorchDetector):
    """Mean squared deviation of M bootstrapped transition predictors from their mean.

    Parameters
    ----------
    n_members : int >= 2, default 5
        Ensemble size M.
    hidden_sizes : list of int, default [64, 64]
    epochs : int >= 1, default 30
    batch_size : int >= 1, default 256
    lr : float > 0, default 1e-3
    device : "auto" | "cpu" | "cuda", default "auto"
        Where the networks train ("auto" = CUDA when available); scoring runs in numpy.
    """

    name: ClassVar[str] = "ensemble_disagreement"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "n_members": [Interval(int, 2, None)],
    }

    def __init__(
        self,
        *,
        n_members: int = 5,
        hidden_sizes: Sequence[int] = (64, 64),
        epochs: int = 30,
        batch_size: int = 256,
        lr: float = 1e-3,
        device: str = "auto",
        threshold_rule: str = "percentile",
        threshold_percentile: float = 99.0,
        seed: int = 0,
    ) -> None:
        super().__init__(
            threshold_rule=threshold_rule, threshold_percentile=threshold_percentile, seed=seed
        )
        self.n_members = n_members
        self.hidden_sizes = hidden_sizes
        self.epochs = epochs
        self.batch_size = batch_size
        self.lr = lr
        self.device = device

    def _inputs(self, trajectory: Trajectory) -> np.ndarray:
        return trajectory_features(trajectory, "state_action", self.action_encoding_)

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        from oodrl.detectors.torch_utils import (
            EnsembleMLP,
            member_indices,
            member_mse,
            seeded_generator,
            train_ensemble,
        )

        self.action_encoding_ = ActionEncoding.fit(trajectories)
        inputs = stacked(trajectories, self._inputs)
        deltas = stacked(trajectories, increments)
        self.input_standardizer_ = Standardizer.fit(inputs)
        targets = Standardizer.fit(deltas).transform(deltas)
        generator = seeded_generator(self.seed)
        model = EnsembleMLP(
            self.n_members, inputs.shape[1], targets.shape[1], self.hidden_sizes, generator
        )
        self.weights_ = train_ensemble(
            model,
            self.input_standardizer_.transform(inputs),
            targets,
            member_mse,
            self._train_settings(),
            member_indices(self.n_members, len(inputs), True, generator),
            generator,
        )

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        inputs = self.input_standardizer_.transform(stacked(trajectories, self._inputs))

        def disagreement(outputs: np.ndarray, rows: slice) -> np.ndarray:
            spread = outputs - outputs.mean(axis=0, keepdims=True)
            return (spread**2).sum(axis=-1).mean(axis=0)

        scores = chunked_scores(self.weights_, inputs, disagreement)
        return split_scores(scores, trajectories)
