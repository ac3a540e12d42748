"""Streaming scores: one step in, the scores that became known out (SPEC §13).

`detector.stream()` returns a `DetectorStream`. Feed it the steps of one deployment stream in
order with `update(state, action, reward, next_state, done)`; each call returns the `StepScore`
records (step index, score, alarm) whose scores it can now compute, and `flush()` at the end of
the stream returns the rest and starts a new stream at step 0. Fed a trajectory's steps, a stream
returns every step's score exactly once, in step order, equal bit for bit to `detector.score`.

When a step's score comes out (the convention; no None or NaN placeholders):

- An update happens once s_{t+1} is observed, so a detector whose z_t needs s_{t+1}
  (`latency` 1: transition features, residuals) returns z_t from the update of step t itself,
  like a `latency` 0 one.
- A look-ahead of H steps (`lyapunov_divergence`) returns z_t from the update of step t + H,
  and the pending scores of an episode at its `done` (they need nothing after it).
- `time_series_features` scores its first window's L − 1 early steps with the first full
  window (as `score` does), so its update of step L − 1 returns L records.
- An empty tuple means nothing new is known yet.

`done` inside a stream does not end it: a trajectory holds several episodes and every stream
treats the boundary exactly as its detector's batch scoring does. A stream ends with `flush()`.

`alarm` is `score >= threshold_` of the detector at the time `stream()` was called (False for
an uncalibrated detector). Streams keep constant memory and do constant work per step, except
`ReplayStream`, the default for detectors that only score whole trajectories.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from oodrl.core.trajectory import Trajectory

#: What `update` and `flush` return: the newly known scores, in step order.
StepScores = tuple["StepScore", ...]


@dataclass(frozen=True)
class StepScore:
    """The score of step `step` of the stream (counted from 0) and whether it raised an alarm."""

    step: int
    score: float
    alarm: bool


def one_step(state: Any, action: Any, reward: Any, next_state: Any, done: Any) -> Trajectory:
    """A validated one-step trajectory: the same dtypes and checks as a batch trajectory.

    A discrete action is a scalar; a continuous one a vector (shape (d_a,)).
    """
    return Trajectory(
        states=np.asarray(state, dtype=np.float32)[None],
        actions=np.asarray(action)[None],
        rewards=np.asarray([reward], dtype=np.float32),
        next_states=np.asarray(next_state, dtype=np.float32)[None],
        dones=np.asarray([bool(done)]),
    )


def concatenated(steps: list[Trajectory]) -> Trajectory:
    """One trajectory made of one-step trajectories, in order."""
    return Trajectory(
        states=np.concatenate([s.states for s in steps]),
        actions=np.concatenate([s.actions for s in steps]),
        rewards=np.concatenate([s.rewards for s in steps]),
        next_states=np.concatenate([s.next_states for s in steps]),
        dones=np.concatenate([s.dones for s in steps]),
    )


class StreamedDetector(Protocol):
    """What a stream needs of its detector (`oodrl.core.detector.BaseDetector` provides it).

    Stated here so that this contract imports nothing of the detector's: the detector module
    imports this one, never the other way round.
    """

    latency: int

    def _require_fitted(self) -> None: ...

    def _require_state_dim(self, trajectory: Trajectory) -> None: ...

    def _score_many(self, trajectories: list[Trajectory]) -> list[np.ndarray]: ...


class DetectorStream(ABC):
    """The streaming scorer of one fitted detector; see the module docstring."""

    def __init__(self, detector: StreamedDetector) -> None:
        detector._require_fitted()
        self.detector = detector
        self.threshold: float | None = getattr(detector, "threshold_", None)
        #: How many steps of the current stream have been fed.
        self.steps_fed = 0

    def update(
        self, state: Any, action: Any, reward: Any, next_state: Any, done: Any
    ) -> StepScores:
        """Feed the next step; returns the scores that became known."""
        step = one_step(state, action, reward, next_state, done)
        self.detector._require_state_dim(step)
        t = self.steps_fed
        self.steps_fed += 1
        return self._update(step, t)

    def flush(self) -> StepScores:
        """End the stream: the scores still pending; the next update starts a new stream."""
        pending = self._flush()
        self.steps_fed = 0
        return pending

    @abstractmethod
    def _update(self, step: Trajectory, t: int) -> StepScores:
        """Take step `t` (a one-step trajectory); return the newly known scores."""

    def _flush(self) -> StepScores:
        """Return the pending scores and forget the stream's state."""
        return ()

    def scored(self, first_step: int, scores: np.ndarray) -> StepScores:
        """Records for consecutive steps from `first_step`, with alarms against the threshold."""
        values = np.asarray(scores, dtype=np.float64).tolist()
        threshold = self.threshold
        return tuple(
            StepScore(first_step + i, value, threshold is not None and value >= threshold)
            for i, value in enumerate(values)
        )


class RowStream(DetectorStream):
    """For detectors whose z_t is a function of step t alone (its state, action and next
    state): each update scores its one step with the detector's own batch code.

    Exact because the batch arithmetic is row-independent (`numerics` products, row-wise
    reductions): one row scored alone gives the bits it gets in a batch.
    """

    def _update(self, step: Trajectory, t: int) -> StepScores:
        return self.scored(t, self.detector._score_many([step])[0])


class ReplayStream(DetectorStream):
    """The default for detectors that only score whole trajectories (plugins).

    It keeps the stream's steps and, at each update of step t, scores the steps so far and
    returns z_{t − latency}; `flush` scores the whole stream and returns the rest. This is exact
    when z_t does not read steps after t + latency (what `latency` promises; the streaming
    contract test checks it), but memory and work grow with the stream: a detector meant for
    deployment overrides `stream()`.
    """

    def __init__(self, detector: StreamedDetector) -> None:
        super().__init__(detector)
        self.steps: list[Trajectory] = []

    def _update(self, step: Trajectory, t: int) -> StepScores:
        self.steps.append(step)
        ready = t - self.detector.latency
        if ready < 0:
            return ()
        scores = self.detector._score_many([concatenated(self.steps)])[0]
        return self.scored(ready, scores[ready : ready + 1])

    def _flush(self) -> StepScores:
        if not self.steps:
            return ()
        scores = self.detector._score_many([concatenated(self.steps)])[0]
        first = max(len(self.steps) - self.detector.latency, 0)
        self.steps = []
        return self.scored(first, scores[first:])
