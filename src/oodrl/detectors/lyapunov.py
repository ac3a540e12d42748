"""`lyapunov_divergence`: divergence from the nearest ID neighbour in a delay embedding (SPEC §5).

    y_t = (x_t, x_{t−τ}, …, x_{t−(m−1)τ}),   x the standardised state,
    j   = the fit-set embedding nearest to y_t (Euclidean, exact KD-tree search among at most
          `max_reference` seeded-subsampled fit embeddings),
    z_t = (1/H_t) Σ_{h=1..H_t} log((‖y_{t+h} − y_{j+h}‖ + ε) / (‖y_t − y_j‖ + ε)).

A large z_t means the trajectory moves away from where the closest in-distribution trajectory
went: its local dynamics differ. A step far from all ID data has a large denominator too, so
this score answers changed dynamics, not displaced states: a displaced stream that contracts
towards its neighbour can score *lower* than the clean one (tests/detectors/test_sanity.py).

Episodes and the end of the trajectory. Each episode is its own series: the observations
s_a..s_b of the episode followed by its last observation `next_states[b]` (the terminal one at a
reset, the one after the last step at the end of the trajectory). Nothing crosses a reset:

- embedding: components before the episode's first step repeat its first observation
  (edge padding), in the fit set and in scored trajectories alike;
- horizon: H_t = min(H, steps left in the episode's series), at least 1 since every step has
  its next observation; near an episode end or the end of the trajectory the average runs over
  the H_t steps that exist;
- neighbours: only fit embeddings with a full horizon H ahead in their own episode are
  candidates, so y_{j+h} always exists.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import Standardizer, seeded_subsample, split_scores
from oodrl.errors import ContractError
from oodrl.validation import Interval


@dataclass(frozen=True)
class EpisodeEmbedding:
    """Delay embeddings of a set of trajectories, each episode extended by its last observation.

    `vectors` (P, m·d) holds every position of every episode series; `steps` (ΣT,) the position
    of each original step in trajectory order; `steps_left` (P,) how many positions follow in
    the same episode series.
    """

    vectors: np.ndarray
    steps: np.ndarray
    steps_left: np.ndarray


def episode_embedding(
    trajectories: Sequence[Trajectory],
    standardizer: Standardizer,
    dimension: int,
    lag: int,
) -> EpisodeEmbedding:
    vectors, steps, steps_left = [], [], []
    offset = 0
    for trajectory in trajectories:
        states = standardizer.transform(trajectory.states.astype(np.float64))
        last_states = standardizer.transform(trajectory.next_states.astype(np.float64))
        ends = np.flatnonzero(trajectory.dones[:-1]).tolist() + [trajectory.T - 1]
        ends = np.asarray(ends)
        episode = np.concatenate([[0], np.cumsum(trajectory.dones[:-1])])
        # The series: each episode's states followed by its last next_state.
        series = np.insert(states, ends + 1, last_states[ends], axis=0)
        series_episode = np.insert(episode, ends + 1, episode[ends])
        position = np.arange(len(series))
        first = np.searchsorted(series_episode, series_episode, side="left")
        last = np.searchsorted(series_episode, series_episode, side="right") - 1
        back = position[:, None] - lag * np.arange(dimension)
        vectors.append(series[np.maximum(back, first[:, None])].reshape(len(series), -1))
        steps.append(offset + np.arange(trajectory.T) + episode)
        steps_left.append(last - position)
        offset += len(series)
    return EpisodeEmbedding(
        np.concatenate(vectors), np.concatenate(steps), np.concatenate(steps_left)
    )


@detector_parameters
class LyapunovDivergence(BaseDetector):
    """Mean log growth of the distance to the nearest ID neighbour over a short horizon.

    Parameters
    ----------
    embedding_dim : int >= 1, default 2
        Delay-embedding dimension m (the KD-tree slows quickly as m·d_s grows).
    lag : int >= 1, default 1
        Delay τ in steps.
    horizon : int >= 1, default 5
        H, the number of steps the divergence is followed.
    epsilon : float > 0, default 1e-3
        ε in standardised-state units; keeps the ratio finite when a distance is 0.
    max_reference : int >= 1, default 4096
        Largest number of candidate neighbours (a seeded subsample of the fit embeddings).
    """

    name: ClassVar[str] = "lyapunov_divergence"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "embedding_dim": [Interval(int, 1, None)],
        "lag": [Interval(int, 1, None)],
        "horizon": [Interval(int, 1, None)],
        "epsilon": [Interval(float, 0, None, closed="neither")],
        "max_reference": [Interval(int, 1, None)],
    }

    embedding_dim: int = 2
    lag: int = 1
    horizon: int = 5
    epsilon: float = 1e-3
    max_reference: int = 4096

    @property
    def latency(self) -> int:
        # z_t follows the embedding H steps ahead: it is known at t + H.
        return self.horizon

    def _embed(self, trajectories: Sequence[Trajectory]) -> EpisodeEmbedding:
        return episode_embedding(trajectories, self.standardizer_, self.embedding_dim, self.lag)

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self.standardizer_ = Standardizer.fit(
            np.concatenate([t.states for t in trajectories]).astype(np.float64)
        )
        embedding = self._embed(trajectories)
        candidates = np.flatnonzero(embedding.steps_left >= self.horizon)
        if candidates.size == 0:
            raise ContractError(
                f"{self.name} found no fit step with {self.horizon} steps left in its "
                "episode; lower 'horizon' or fit on longer episodes."
            )
        anchors = candidates[seeded_subsample(len(candidates), self.max_reference, self.seed)]
        self.vectors_ = embedding.vectors
        self.anchors_ = anchors

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        # Imported here: scipy.spatial costs every stage that only validates params ~0.3 s.
        # The tree is rebuilt per call (milliseconds for <= max_reference points) rather than
        # fitted state: a pickled cKDTree is not byte-reproducible.
        from scipy.spatial import cKDTree

        embedding = self._embed(trajectories)
        query = embedding.steps
        tree = cKDTree(self.vectors_[self.anchors_])
        initial, nearest = tree.query(embedding.vectors[query])
        neighbour = self.anchors_[nearest]
        horizon = np.minimum(embedding.steps_left[query], self.horizon)
        total = np.zeros(len(query))
        for h in range(1, self.horizon + 1):
            valid = h <= horizon
            ahead = embedding.vectors[np.where(valid, query + h, query)]
            distance = np.linalg.norm(ahead - self.vectors_[neighbour + h], axis=1)
            total += np.where(valid, numerics.log(distance + self.epsilon), 0.0)
        # numerics.log: numpy's log differs in the last bits between CPUs (SPEC §14).
        scores = total / horizon - numerics.log(initial + self.epsilon)
        return split_scores(scores, trajectories)

    def stream(self) -> DetectorStream:
        return LyapunovStream(self)


@dataclass
class _Pending:
    """A step whose horizon is still running: its series position, its ID neighbour, the
    initial distance and the sum of the log distances of the `terms` steps seen ahead."""

    step: int
    position: int
    neighbour: int
    initial: float
    total: float = 0.0
    terms: int = 0


class LyapunovStream(DetectorStream):
    """The episode series as it arrives: a ring of its last (m − 1)τ + 1 observations (and
    its first, the edge padding) gives each new embedding; the steps whose horizon is running
    (at most H) collect one log distance per new position, in the order `score` adds them.

    z_t comes out with the update of step t + H, which brings s_{t+H}; at a `done` (or
    `flush`), the episode's last observation ends the pending horizons early, as in `score`.
    The KD-tree over the fit embeddings is built once per stream object.
    """

    def __init__(self, detector: LyapunovDivergence) -> None:
        from scipy.spatial import cKDTree

        super().__init__(detector)
        self.tree = cKDTree(detector.vectors_[detector.anchors_])
        self.recent: deque[np.ndarray] = deque(
            maxlen=(detector.embedding_dim - 1) * detector.lag + 1
        )
        self.pending: deque[_Pending] = deque()
        # The episode's first observation (the edge padding), the position of the newest one,
        # and the newest step's next observation (the series' end if the stream ends there).
        self.first: np.ndarray | None = None
        self.position = -1
        self.last_observation: np.ndarray | None = None

    def _update(self, step: Trajectory, t: int) -> StepScores:
        standardize = self.detector.standardizer_.transform
        self.last_observation = standardize(step.next_states.astype(np.float64))[0]
        ready = self._extend(standardize(step.states.astype(np.float64))[0], step=t)
        if step.dones[0]:
            ready += self._end_episode()
        return ready

    def _flush(self) -> StepScores:
        return self._end_episode()

    def _end_episode(self) -> StepScores:
        """The series' last observation ends every pending horizon; a new episode begins."""
        if not self.recent:
            return ()
        ready = self._extend(self.last_observation, step=None)
        ready += self._finish(len(self.pending))
        self.recent.clear()
        return ready

    def _extend(self, observation: np.ndarray, step: int | None) -> StepScores:
        """Add the series' next position (a step's state, or with `step` None the episode's
        last observation): one more term for every pending step, and a new pending step."""
        detector = self.detector
        if not self.recent:
            self.first = observation
            self.position = -1
        self.position += 1
        self.recent.append(observation)
        vector = np.concatenate(
            [
                self.recent[-1 - k * detector.lag] if k * detector.lag <= self.position
                else self.first
                for k in range(detector.embedding_dim)
            ]
        )  # fmt: skip
        if self.pending:
            ahead = np.array([self.position - p.position for p in self.pending])
            neighbours = np.array([p.neighbour for p in self.pending])
            distance = np.linalg.norm(vector - detector.vectors_[neighbours + ahead], axis=1)
            for pending, term in zip(
                self.pending, numerics.log(distance + detector.epsilon).tolist(), strict=True
            ):
                pending.total += term
                pending.terms += 1
        ready = self._finish(sum(p.terms == detector.horizon for p in self.pending))
        if step is not None:
            initial, nearest = self.tree.query(vector[None])
            neighbour = int(detector.anchors_[nearest[0]])
            self.pending.append(_Pending(step, self.position, neighbour, float(initial[0])))
        return ready

    def _finish(self, count: int) -> StepScores:
        """Score and drop the `count` oldest pending steps (z = mean term − log initial)."""
        done = [self.pending.popleft() for _ in range(count)]
        if not done:
            return ()
        total = np.array([p.total for p in done])
        terms = np.array([p.terms for p in done])
        initial = np.array([p.initial for p in done])
        scores = total / terms - numerics.log(initial + self.detector.epsilon)
        return self.scored(done[0].step, scores)
