"""`pedm`: probabilistic ensemble dynamics model (Haider et al. 2023; SPEC §5).

An ensemble of M Gaussian networks p(s_{t+1} | s_t, a_t) = N(s_t + μ_m, diag σ²_m), trained with
the Gaussian negative log-likelihood on the fit transitions (each member from its own random
initialisation and data order). The score is the smallest squared distance between the observed
next state and K samples of every member:

    z_t = min_{m, k} ‖s_{t+1} − ŝ^{(m,k)}_t‖²,   ŝ^{(m,k)}_t = s_t + μ_m + σ_m ∘ ε^{(m,k)}_t.

Units: the networks model the increment s_{t+1} − s_t standardised per coordinate by its fit-set
standard deviation, and the distance is measured there, so every coordinate counts in units of
its typical increment. Inputs are the standardised (s_t, one-hot a_t).

The sampling noise ε^{(m,k)}_t depends only on `seed` and the step index t: scores are
deterministic, a trajectory's scores do not depend on what it is batched with, and a perturbed
trajectory and its matched clean one see the same noise (common random numbers).

The alarm threshold defaults to the maximum held-out score (`threshold_rule="max"`).

Networks, and why they are the same bytes on every machine: `oodrl.detectors.neural`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import increments, split_scores, stacked
from oodrl.detectors.mlp import gaussian_mean_and_logvar
from oodrl.detectors.neural import TransitionEnsemble, chunked_scores
from oodrl.validation import Interval


@detector_parameters
class Pedm(TransitionEnsemble):
    """Minimum sampled transition error of a probabilistic dynamics ensemble.

    Parameters
    ----------
    n_members : int >= 1, default 5
        Ensemble size M.
    n_samples : int >= 1, default 10
        Samples K drawn from each member per step.
    hidden_sizes, epochs, batch_size, lr
        Training (`NeuralDetector`): defaults [64, 64], 30, 256, 1e-3.
    threshold_rule : default "max"
        The maximum held-out score (SPEC §5); "percentile" uses `threshold_percentile`.
    """

    name: ClassVar[str] = "pedm"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "n_members": [Interval(int, 1, None)],
        "n_samples": [Interval(int, 1, None)],
    }

    n_samples: int = 10
    threshold_rule: str = "max"

    @property
    def latency(self) -> int:
        # z_t compares the observed s_{t+1} with the predictions: known one step after t.
        return 1

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        # Two outputs per coordinate: the Gaussian mean and log-variance of each increment.
        self.target_standardizer_ = self._fit_ensemble(
            trajectories, "gaussian_nll", outputs_per_coordinate=2, bootstrap=False
        )

    def stream(self) -> DetectorStream:
        return PedmStream(self)

    def _noise(self, rng: np.random.Generator, steps: int) -> np.ndarray:
        """ε of the next `steps` steps from `rng`, (steps, M, d_s, K), samples innermost (so the
        sum over coordinates runs on whole rows). A generator drawn step by step gives the rows
        of one draw of them all: a stream draws as it goes."""
        shape = (steps, self.n_members, self.n_samples, self.state_dim_)
        return np.ascontiguousarray(rng.standard_normal(shape).swapaxes(2, 3))

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        steps = np.concatenate([np.arange(t.T) for t in trajectories])
        noise = self._noise(np.random.default_rng(self.seed), max(t.T for t in trajectories))
        return split_scores(self._min_sampled_errors(trajectories, noise, steps), trajectories)

    def _min_sampled_errors(
        self, trajectories: Sequence[Trajectory], noise: np.ndarray, steps: np.ndarray
    ) -> np.ndarray:
        """z of every step of `trajectories`, stacked; step i uses the noise `noise[steps[i]]`."""
        inputs = self._standardized_inputs(trajectories)
        targets = self.target_standardizer_.transform(stacked(trajectories, increments))

        def min_sampled_error(outputs: np.ndarray, rows: slice) -> np.ndarray:
            mean, logvar = gaussian_mean_and_logvar(outputs.transpose(1, 0, 2))  # (n, M, d_s)
            residual = targets[rows][:, None] - mean
            # s_{t+1} − ŝ^{(m,k)}_t = residual − σ_m ε^{(m,k)}_t at each row's own step index,
            # computed in place in one (n, M, d_s, K) buffer.
            errors = noise[steps[rows]]
            errors *= numerics.exp(0.5 * logvar)[..., None]
            np.subtract(residual[..., None], errors, out=errors)
            errors *= errors
            return errors.sum(axis=2).reshape(len(errors), -1).min(axis=1)

        return chunked_scores(self.weights_, inputs, min_sampled_error)


class PedmStream(DetectorStream):
    """Scores each step on its own, drawing its noise from a generator that follows the
    stream's step index, as `Pedm.score` indexes its noise by step."""

    def __init__(self, detector: Pedm) -> None:
        super().__init__(detector)
        self.noise_rng = np.random.default_rng(detector.seed)

    def _flush(self) -> StepScores:
        self.noise_rng = np.random.default_rng(self.detector.seed)
        return ()

    def _update(self, step: Trajectory, t: int) -> StepScores:
        noise = self.detector._noise(self.noise_rng, 1)
        return self.scored(t, self.detector._min_sampled_errors([step], noise, np.zeros(1, int)))
