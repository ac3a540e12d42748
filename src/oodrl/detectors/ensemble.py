"""`ensemble_disagreement`: epistemic uncertainty of a bootstrapped dynamics ensemble (SPEC §5).

M deterministic networks predict the standardised increment s_{t+1} − s_t from the standardised
(s_t, one-hot a_t), each trained with the mean squared error on its own bootstrap resample of the
fit transitions. The score is their spread about the ensemble mean:

    z_t = (1/M) Σ_m ‖ŝ^{(m)}_t − s̄_t‖²,   s̄_t = (1/M) Σ_m ŝ^{(m)}_t,

in standardised increment units. It uses (s_t, a_t) only, never the observed s_{t+1}: it flags
inputs the ensemble has not learned, not transitions that contradict what it has learned.

Networks, and why they are the same bytes on every machine: `oodrl.detectors.neural`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.detector import detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import split_scores
from oodrl.detectors.neural import TransitionEnsemble, chunked_scores
from oodrl.validation import Interval


@detector_parameters
class EnsembleDisagreement(TransitionEnsemble):
    """Mean squared deviation of M bootstrapped transition predictors from their mean.

    Parameters
    ----------
    n_members : int >= 2, default 5
        Ensemble size M.
    hidden_sizes, epochs, batch_size, lr
        Training (`NeuralDetector`): defaults [64, 64], 30, 256, 1e-3.
    """

    name: ClassVar[str] = "ensemble_disagreement"
    # z_t reads step t alone (s_t, a_t, s_{t+1}): a stream scores each step on its own.
    row_independent: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "n_members": [Interval(int, 2, None)],
    }

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self._fit_ensemble(trajectories, "mse", outputs_per_coordinate=1, bootstrap=True)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        inputs = self._standardized_inputs(trajectories)

        def disagreement(outputs: np.ndarray, rows: slice) -> np.ndarray:
            spread = outputs - outputs.mean(axis=0, keepdims=True)
            return (spread**2).sum(axis=-1).mean(axis=0)

        scores = chunked_scores(self.weights_, inputs, disagreement)
        return split_scores(scores, trajectories)
