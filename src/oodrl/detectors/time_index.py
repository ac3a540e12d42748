"""`time_index`: the trivial baseline whose score is the time step alone (SPEC §15, §17).

z_t = t, the step's index in its stream, whatever the stream holds. It knows nothing of the
states, so a cell it detects well is detected by *when* the fault starts, not by what it does to
the agent: the leaderboard flags such cells (a step-level AUROC that compares steps after the
onset with earlier or clean ones rewards late steps). Fitting learns nothing; the threshold
rules apply as to any detector (on streams of one length, "episode_max" never alarms).

It does not use the fit set, by design, so of oodrl's detector contract it passes every check
but `check_scores_use_the_data` (which asks exactly that).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory


@detector_parameters
class TimeIndex(BaseDetector):
    """z_t = t. No parameters of its own; the threshold parameters of every detector."""

    name: ClassVar[str] = "time_index"

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        """Nothing to learn: the state dimension the base class records is all it keeps."""

    def _score(self, trajectory: Trajectory) -> np.ndarray:
        return np.arange(trajectory.T, dtype=np.float64)

    def stream(self) -> DetectorStream:
        return TimeIndexStream(self)


class TimeIndexStream(DetectorStream):
    """Each update returns its own step index as the score."""

    def _update(self, step: Trajectory, t: int) -> StepScores:
        return self.scored(t, [float(t)])
