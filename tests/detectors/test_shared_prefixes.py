"""A stage's sets share their equal pre-onset scores (`oodrl.protocol.scoring.SharedPrefixes`): the
same bits as scoring every stream in full, for every registered detector and for library detectors,
and fewer steps scored where the detector is row-independent."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest
from test_contract import NAMES, SPLITS, fitted

from oodrl.core.detector import BaseDetector
from oodrl.core.trajectory import Trajectory, TrajectorySet
from oodrl.detectors import DETECTORS
from oodrl.protocol.scoring import SharedPrefixes, first_difference, score_set

ONSET = 40


def as_set(trajectories: list[Trajectory]) -> TrajectorySet:
    return TrajectorySet(
        **{
            name: np.stack([getattr(t, name) for t in trajectories])
            for name in ("states", "actions", "rewards", "next_states", "dones")
        },
        executed_actions=np.stack([t.executed_actions for t in trajectories]),
        episode_index=np.stack([t.info["episode_index"] for t in trajectories]),
        seeds=np.array([t.info["seed"] for t in trajectories]),
    )


def faulted(clean: TrajectorySet, severity: float, onset: int = ONSET) -> TrajectorySet:
    """The clean streams with state noise of scale `severity` from `onset` on."""
    rng = np.random.default_rng(7)
    noise = rng.standard_normal((2, *clean.states.shape)).astype(np.float32)
    noise[:, :, :onset] = 0
    states, next_states = (
        clean.states + severity * noise[0],
        clean.next_states + severity * noise[1],
    )
    return TrajectorySet(
        states=states, actions=clean.actions, rewards=clean.rewards, next_states=next_states,
        dones=clean.dones, executed_actions=clean.executed_actions,
        episode_index=clean.episode_index, seeds=clean.seeds,
    )  # fmt: skip


def stage_sets(actions: str) -> list[TrajectorySet]:
    """What one scoring stage scores: a headline set, a sweep (with a severity that changes
    nothing and a fault from step 0), then one of the headline streams again (a tier set)."""
    clean = as_set(SPLITS[actions][2])
    return [
        faulted(clean, 0.5),
        faulted(clean, 0.0),
        faulted(clean, 1.0),
        faulted(clean, 0.3, onset=0),
        faulted(clean, 0.5).subset([1]),
    ]


def scored_in_a_stage(detector: BaseDetector, sets, shared: SharedPrefixes | None) -> list:
    return [score_set(detector, "d", tset, "a set", shared) for tset in sets]


def assert_same_bits(detector: BaseDetector, actions: str) -> None:
    sets = stage_sets(actions)
    full = scored_in_a_stage(detector, sets, None)
    shared = scored_in_a_stage(detector, sets, SharedPrefixes())
    for index, (a, b) in enumerate(zip(full, shared, strict=True)):
        assert a.tobytes() == b.tobytes(), f"{detector.name}: set {index} differs"


@pytest.mark.parametrize("actions", list(SPLITS))
@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_shared_prefixes_give_the_full_scores(name, actions):
    assert_same_bits(fitted(name, actions), actions)


LIBRARY = {
    "hbos_state": ("pyod.models.hbos:HBOS", {}),
    "knn_window": ("pyod.models.knn:KNN", {"features": "window", "window": 3}),
    "iforest_transition": ("pyod.models.iforest:IForest", {"features": "transition"}),
}


@pytest.mark.parametrize("case", LIBRARY, ids=list(LIBRARY))
def test_library_detectors_share_prefixes_of_their_row_views_only(case):
    path, params = LIBRARY[case]
    detector = DETECTORS.get(path).from_params(params).fit(SPLITS["continuous"][0])
    assert detector.row_independent == (params.get("features") != "window")
    assert_same_bits(detector, "continuous")


class CountingDetector(BaseDetector):
    """|s_t| summed, counting the steps it is asked to score."""

    name = "counting"
    row_independent: ClassVar[bool] = True
    steps_scored: ClassVar[int] = 0

    def _fit(self, trajectories) -> None:
        pass

    def _score(self, trajectory: Trajectory) -> np.ndarray:
        type(self).steps_scored += trajectory.T
        return np.abs(trajectory.states.astype(np.float64)).sum(axis=1)


@pytest.mark.parametrize("row_independent", [True, False])
def test_only_steps_after_the_first_difference_are_scored(row_independent, monkeypatch):
    monkeypatch.setattr(CountingDetector, "row_independent", row_independent)
    monkeypatch.setattr(CountingDetector, "steps_scored", 0)
    sets = stage_sets("discrete")
    scored_in_a_stage(CountingDetector().fit(SPLITS["discrete"][0]), sets, SharedPrefixes())
    n, T = len(sets[0]), sets[0].T
    # The first set (the headline) in full; the sweep after the onset where it differs from the
    # headline (severity 0 too), in full where the fault starts at step 0; nothing of a stream
    # equal to the headline's.
    expected = n * T + n * (T - ONSET) + n * (T - ONSET) + n * T + 0
    assert CountingDetector.steps_scored == (expected if row_independent else 4 * n * T + T)


def test_first_difference_compares_every_per_step_array():
    trajectory = as_set(SPLITS["discrete"][2]).trajectory(0)
    assert first_difference(trajectory, trajectory) == trajectory.T
    moved = trajectory.states.copy()
    moved[17, 2] += 1e-6
    assert first_difference(trajectory, trajectory.replace(states=moved)) == 17
    executed = trajectory.executed_actions.copy()
    executed[5] = (executed[5] + 1) % 3
    changed = trajectory.replace(info={**trajectory.info, "executed_actions": executed})
    assert first_difference(trajectory, changed) == 5
    first_30 = {k: v[:30] if isinstance(v, np.ndarray) else v for k, v in trajectory.info.items()}
    cut = Trajectory(
        trajectory.states[:30], trajectory.actions[:30], trajectory.rewards[:30],
        trajectory.next_states[:30], trajectory.dones[:30], first_30,
    )  # fmt: skip
    assert first_difference(trajectory, cut) == 30
    # Streams whose per-step arrays are not the same kind are not compared: nothing is shared.
    assert first_difference(trajectory, trajectory.replace(info={"seed": 1})) == 0


def test_negative_zero_counts_as_a_difference():
    trajectory = SPLITS["continuous"][2][0]
    states = trajectory.states.copy()
    states[3, 0] = 0.0
    signed = states.copy()
    signed[3, 0] = -0.0
    assert (
        first_difference(trajectory.replace(states=states), trajectory.replace(states=signed)) == 3
    )
