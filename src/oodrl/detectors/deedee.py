"""`deedee`: an episode's running mean against the training episodes' (Aljaafari et al. 2025,
"DEEDEE: fast and scalable out-of-distribution dynamics detection"; SPEC §20).

DEEDEE summarises a stream by low-order statistics: the mean of its step features, and an RBF
kernel similarity of that mean to the training set's summaries. oodrl's streaming form: with x_t
the standardised step features (`features`, as for every feature-set detector) and τ the steps
since the current episode began (0 at its first step),

    m_t = (1/(τ + 1)) Σ_{u = t−τ..t} x_u                      (the episode's running mean)
    k_j = exp(−‖m_t − c_{j,τ}‖² / (2 h_τ²))                   (RBF similarity to episode j)
    z_t = 1 − max_j k_j      (`similarity: max`; `mean`: 1 − mean_j k_j)

where c_{j,τ} is training episode j's running mean at its own step τ (at its last step if it
was shorter), so a running mean is compared with the training means *at the same point of an
episode*: early means, made of few steps, with early ones, and no step is anomalous merely for
being early. The bandwidth is the median heuristic per τ: h_τ = the median distance between
two training summaries c_{j,τ}, c_{k,τ} (`bandwidth: median`), or a fixed float in standardised
units. Scores lie in [0, 1]; a mean far from every training mean saturates at 1 (ties).

Training episodes are the fit trajectories cut at their `dones`; an episode cut short by the end
of its trajectory counts with the steps it has. Every arithmetic step is elementwise or summed
in a fixed order, and the exp is `numerics.exp`, so the scores are the same bytes on every
machine, and a stream (a running sum and a step counter) gives the batch scores bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import FeatureSetDetector, split_scores, stacked
from oodrl.validation import Interval, Options

SIMILARITIES = ("max", "mean")

#: Summaries scored per block: (rows × episodes × features) float64 temporaries stay small.
_ROWS_PER_BLOCK = 256
#: A median distance at or below this (identical training summaries) is treated as this.
_MIN_BANDWIDTH = 1e-12


def episode_steps(dones: np.ndarray) -> np.ndarray:
    """τ_t: the steps since the episode of step t began (0 on its first step)."""
    index = np.arange(len(dones))
    starts = np.zeros(len(dones), dtype=bool)
    starts[0] = True
    starts[1:] = dones[:-1]
    return index - np.maximum.accumulate(np.where(starts, index, 0))


def running_means(x: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Each row's mean of its episode's rows so far; `steps` = `episode_steps` of the rows.

    Sums run row after row in float64 (an accumulate, as a stream adds), one episode at a time.
    """
    starts = np.flatnonzero(steps == 0)
    sums = [np.cumsum(segment, axis=0) for segment in np.split(x, starts[1:])]
    return np.concatenate(sums) / (steps + 1.0)[:, None]


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """‖a − b‖² over the last axis (broadcast), summed coordinate by coordinate in index order."""
    diff = a - b
    total = diff[..., 0] * diff[..., 0]
    for j in range(1, diff.shape[-1]):
        total += diff[..., j] * diff[..., j]
    return total


@detector_parameters
class Deedee(FeatureSetDetector):
    """One minus the RBF similarity of the episode's running mean to the training episodes'.

    Parameters
    ----------
    features : "state" | "state_action" | "transition", default "state"
        The step features x_t (standardised on the fit set).
    similarity : "max" | "mean", default "max"
        Compare with the most similar training episode, or with all of them on average.
    bandwidth : "median" | float > 0, default "median"
        h: the median distance between the training summaries at the same episode step, or a
        fixed width in standardised units.
    """

    name: ClassVar[str] = "deedee"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "similarity": [Options(SIMILARITIES)],
        "bandwidth": [Options(("median",)), Interval(float, 0, None, closed="neither")],
    }

    similarity: str = "max"
    bandwidth: str | float = "median"

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        x = self._fit_features(trajectories)
        steps = stacked(trajectories, lambda t: episode_steps(t.dones))
        self.summaries_ = running_means(x, steps)
        starts = np.flatnonzero(steps == 0)
        self.episode_starts_ = starts
        self.episode_lengths_ = np.diff(np.r_[starts, len(steps)])
        longest = int(self.episode_lengths_.max())
        if self.bandwidth == "median":
            self.bandwidths_ = self._median_distances(longest)
        else:
            self.bandwidths_ = np.full(longest, float(self.bandwidth))

    def _references(self, steps: np.ndarray) -> np.ndarray:
        """(n, E, d): every training episode's summary at each row's episode step."""
        index = np.minimum(steps[:, None], self.episode_lengths_ - 1) + self.episode_starts_
        return self.summaries_[index]

    def _median_distances(self, longest: int) -> np.ndarray:
        """h_τ for τ < `longest`: the median distance between two training summaries at τ."""
        n_episodes = len(self.episode_starts_)
        if n_episodes < 2:
            return np.ones(longest)
        upper = np.triu_indices(n_episodes, 1)
        medians = []
        for first in range(0, longest, _ROWS_PER_BLOCK // n_episodes + 1):
            steps = np.arange(first, min(first + _ROWS_PER_BLOCK // n_episodes + 1, longest))
            references = self._references(steps)  # (τs, E, d)
            pairs = squared_distances(references[:, :, None], references[:, None, :])
            medians.append(np.median(np.sqrt(pairs[:, upper[0], upper[1]]), axis=1))
        return np.maximum(np.concatenate(medians), _MIN_BANDWIDTH)

    def _scores_of(self, means: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """z for running means (n, d) at episode steps (n,), block by block."""
        scores = []
        for first in range(0, len(steps), _ROWS_PER_BLOCK):
            rows = slice(first, first + _ROWS_PER_BLOCK)
            distances = squared_distances(means[rows, None], self._references(steps[rows]))
            width = self.bandwidths_[np.minimum(steps[rows], len(self.bandwidths_) - 1)]
            scale = 2.0 * width * width
            if self.similarity == "max":
                similarity = numerics.exp(-distances.min(axis=1) / scale)
            else:
                kernel = numerics.exp(-distances / scale[:, None])
                total = kernel[:, 0].copy()
                for j in range(1, kernel.shape[1]):
                    total += kernel[:, j]
                similarity = total / kernel.shape[1]
            scores.append(1.0 - similarity)
        return np.concatenate(scores)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        x = self._standardized_features(trajectories)
        steps = stacked(trajectories, lambda t: episode_steps(t.dones))
        return split_scores(self._scores_of(running_means(x, steps), steps), trajectories)

    def stream(self) -> DetectorStream:
        return DeedeeStream(self)


class DeedeeStream(DetectorStream):
    """The running sum of the episode's features and its step count, reset after a `done`."""

    def __init__(self, detector: Deedee) -> None:
        super().__init__(detector)
        self._flush()

    def _flush(self) -> StepScores:
        self.total: np.ndarray | None = None
        self.episode_step = 0
        return ()

    def _update(self, step: Trajectory, t: int) -> StepScores:
        x = self.detector._standardized_features([step])[0]
        if self.total is None:
            self.total, self.episode_step = x.copy(), 0
        else:
            self.total += x
            self.episode_step += 1
        steps = np.array([self.episode_step])
        mean = (self.total / (self.episode_step + 1.0))[None]
        score = self.detector._scores_of(mean, steps)
        if step.dones[0]:
            self.total = None
        return self.scored(t, score)
