"""`random_scores`: seeded uniform scores, the leaderboard's floor (SPEC §20).

z_t ~ U[0, 1), drawn independently for every step, carrying no information about the stream:
every metric it gets is what chance gets under that metric's own conventions (matched AUROC
≈ 0.5, AP ≈ the positive fraction, a clean alarm rate ≈ the threshold rule's nominal rate).

Deterministic without any generator state: z_t is a hash of (`seed`, the step index t, the
bits of s_t and of a_t), SplitMix64's finaliser chained over those 64-bit words, its top 53
bits read as a float in [0, 1). So a stream gives the same scores as `score` bit for bit, and
the scores of a step depend only on what the detector may see of it (latency 0):

- a perturbed stream and its matched clean one share their scores until the first step whose
  observation or action differs (common random numbers, as the other detectors' scores do);
  from there on they are independent draws;
- two different streams (other seeds of the environment) get independent scores.

The trajectory's own seed is not used: a deployed stream (`stream()`) is never told it.
Fitting learns nothing (`learns_from_data = False`: the contract does not ask that refitting
moves the scores); the threshold rules apply as for any detector.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory

_GOLDEN_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_MIX_1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX_2 = np.uint64(0x94D049BB133111EB)


def _splitmix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser of x + γ (uint64 arithmetic wraps, as the algorithm needs)."""
    z = x + _GOLDEN_GAMMA
    z = (z ^ (z >> np.uint64(30))) * _MIX_1
    z = (z ^ (z >> np.uint64(27))) * _MIX_2
    return z ^ (z >> np.uint64(31))


def _step_words(trajectory: Trajectory) -> np.ndarray:
    """(T, k) uint64: the bit patterns of each step's state and action, one word per value."""
    states = np.ascontiguousarray(trajectory.states).view(np.uint32).astype(np.uint64)
    # Actions are int64 (discrete) or float32 vectors (continuous, 32 bits each).
    actions = np.ascontiguousarray(trajectory.actions.reshape(trajectory.T, -1))
    bits = actions.view(np.uint64) if actions.dtype == np.int64 else actions.view(np.uint32)
    return np.hstack([states, bits.astype(np.uint64)])


def uniform_hash(seed: int, steps: np.ndarray, words: np.ndarray) -> np.ndarray:
    """A uniform [0, 1) float per row, a deterministic hash of (seed, step index, row words)."""
    h = _splitmix(np.full(len(steps), seed, dtype=np.uint64))
    h = _splitmix(h ^ steps.astype(np.uint64))
    for column in words.T:
        h = _splitmix(h ^ column)
    return (h >> np.uint64(11)).astype(np.float64) * 2.0**-53


@detector_parameters
class RandomScores(BaseDetector):
    """Uniform scores that ignore the data: the floor every detector should beat.

    No parameters of its own; `seed` picks the draws.
    """

    name: ClassVar[str] = "random_scores"
    learns_from_data: ClassVar[bool] = False

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        """Nothing to learn: the state dimension the base class records is all it keeps."""

    def _score(self, trajectory: Trajectory) -> np.ndarray:
        return self._scores_from(trajectory, 0)

    def _scores_from(self, trajectory: Trajectory, first_step: int) -> np.ndarray:
        steps = np.arange(first_step, first_step + trajectory.T)
        return uniform_hash(self.seed, steps, _step_words(trajectory))

    def stream(self) -> DetectorStream:
        return RandomScoresStream(self)


class RandomScoresStream(DetectorStream):
    """Each update hashes its one step with the stream's step index."""

    def _update(self, step: Trajectory, t: int) -> StepScores:
        return self.scored(t, self.detector._scores_from(step, t))
