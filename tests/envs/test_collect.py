"""The batched collector: deployment streams, determinism, fault hooks, both action kinds."""

from __future__ import annotations

import numpy as np
import pytest
from rollout_policies import HeuristicPolicy, LinearPolicy

from oodrl.core.injector import Fault
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import BLOCK_SIZE, collect, episode_seed
from oodrl.envs.lunar_lander import LunarLanderAdapter
from oodrl.errors import PolicyError

FIELDS = ("states", "actions", "rewards", "next_states", "dones", "executed_actions")


def _equal(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in FIELDS)


def test_deployment_stream_semantics(heuristic_clean):
    tset = heuristic_clean
    assert tset.states.shape == (8, 300, 8)
    assert tset.dones.any(), "heuristic episodes end inside 300 steps for some seeds"
    for i, t in zip(*np.nonzero(tset.dones[:, :-1]), strict=True):
        # After an episode end the next state is a fresh reset, not the terminal observation.
        assert not np.array_equal(tset.states[i, t + 1], tset.next_states[i, t])
        assert tset.episode_index[i, t + 1] == tset.episode_index[i, t] + 1
    continuing = ~tset.dones[:, :-1]
    np.testing.assert_array_equal(
        tset.states[:, 1:][continuing], tset.next_states[:, :-1][continuing]
    )


def test_same_seed_same_trajectory_for_any_worker_count():
    seeds = range(300, 300 + BLOCK_SIZE + 3)
    adapter, policy = LunarLanderAdapter(), HeuristicPolicy()
    one = collect(adapter, policy, seeds, 60)
    two = collect(adapter, policy, seeds, 60, workers=2)
    again = collect(adapter, policy, seeds, 60)
    assert _equal(one, two) and _equal(one, again)


def test_episode_seeds_do_not_collide_with_other_streams():
    assert episode_seed(5, 0) == 5
    derived = {episode_seed(s, k) for s in range(50) for k in range(1, 5)}
    assert not derived & set(range(50))


class _RecordingFault(Fault):
    def __init__(self):
        self.steps = []

    def before_step(self, t, commanded, sim):
        self.steps.append(t)
        return np.int64(0)


def test_fault_hooks_run_on_labelled_steps_only():
    labels = np.zeros(40, bool)
    labels[25:] = True
    faults = [_RecordingFault() for _ in range(2)]
    adapter, policy = LunarLanderAdapter(), HeuristicPolicy()
    clean = collect(adapter, policy, [1, 2], 40)
    faulty = collect(adapter, policy, [1, 2], 40, labels=labels, faults=faults)
    assert faults[0].steps == list(range(25, 40))
    np.testing.assert_array_equal(faulty.states[:, :26], clean.states[:, :26])
    assert (faulty.executed_actions[:, 25:] == 0).all()
    np.testing.assert_array_equal(faulty.actions[:, 25], clean.actions[:, 25])


@pytest.mark.parametrize("env_id", ENVIRONMENTS.names())
def test_actions_are_stored_as_the_action_space_needs(env_id):
    adapter = ENVIRONMENTS.get(env_id)()
    policy = LinearPolicy(adapter, noise=0.0)
    tset = collect(adapter, policy, [0, 1], 30)
    shape, dtype = (2, 30, *adapter.action_shape), adapter.action_dtype
    assert tset.actions.shape == shape and tset.actions.dtype == dtype
    assert tset.executed_actions.shape == shape and tset.executed_actions.dtype == dtype
    assert tset.states.shape == (2, 30, adapter.state_dim)
    np.testing.assert_array_equal(tset.executed_actions, tset.actions)
    # The stored actions are the policy's own, not rounded: acting again gives them back.
    for j in range(2):
        np.testing.assert_array_equal(policy.act(tset.states[j]), tset.actions[j])
    if adapter.action_kind == "continuous":
        assert len(np.unique(tset.actions)) > 10, "continuous actions must not be truncated"
    assert tset.trajectory(0).actions.shape == (30, *adapter.action_shape)


def test_a_policy_for_another_environment_is_refused():
    lander = LunarLanderAdapter()
    cartpole = ENVIRONMENTS.get("CartPole-v1")()
    with pytest.raises(PolicyError, match=r"8-dim observations; CartPole-v1 gives 4"):
        collect(cartpole, LinearPolicy(lander), [0], 5)
    continuous = ENVIRONMENTS.get("LunarLanderContinuous-v3")()
    with pytest.raises(PolicyError, match=r"LunarLanderContinuous-v3 has 2-dim continuous"):
        collect(continuous, LinearPolicy(lander), [0], 5)


def test_continuous_sets_survive_a_store_round_trip(tmp_path):
    from oodrl.io.store import read_trajectories, write_trajectories

    adapter = ENVIRONMENTS.get("Pendulum-v1")()
    tset = collect(adapter, LinearPolicy(adapter), [0, 1, 2], 25, attrs={"env_id": "Pendulum-v1"})
    write_trajectories(tmp_path / "set.zarr", tset)
    again = read_trajectories(tmp_path / "set.zarr")
    for field in (*FIELDS, "episode_index", "seeds"):
        stored, original = getattr(again, field), getattr(tset, field)
        assert stored.dtype == original.dtype
        np.testing.assert_array_equal(stored, original)
    assert again.trajectory(1).actions.shape == (25, 1)


def test_first_episode_collection_stops_each_stream_at_its_first_end():
    """What impact calibration counts (the first episode's return) is the same with and without
    simulating the rest of the horizon; a stopped stream's later steps are zero."""
    from oodrl.protocol.impact import first_episode_returns

    adapter, policy = LunarLanderAdapter(), HeuristicPolicy()
    seeds = list(range(500000, 500006))
    full = collect(adapter, policy, seeds, 1000)
    short = collect(adapter, policy, seeds, 1000, first_episode=True)
    assert np.array_equal(first_episode_returns(full), first_episode_returns(short))
    ends = short.dones.argmax(axis=1)
    assert short.dones.sum(axis=1).tolist() == [1] * len(seeds)
    for row, end in enumerate(ends):
        before = slice(0, end + 1)
        for field in ("states", "actions", "rewards", "next_states"):
            assert np.array_equal(
                getattr(short, field)[row, before], getattr(full, field)[row, before]
            )
            assert not getattr(short, field)[row, end + 1 :].any()
