"""Every registered adapter: facts from the spaces, and a state write-back that is exact."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rollout_policies import LinearPolicy

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.envs import ENVIRONMENTS

ENV_IDS = ENVIRONMENTS.names()

#: SPEC §11's table: action kind and size; observation size as gymnasium documents it.
SUITE = {
    "LunarLander-v3": ("discrete", 4, 8),
    "CartPole-v1": ("discrete", 2, 4),
    "Acrobot-v1": ("discrete", 3, 6),
    "Pendulum-v1": ("continuous", 1, 3),
    "LunarLanderContinuous-v3": ("continuous", 2, 8),
    "HalfCheetah-v5": ("continuous", 6, 17),
    "Hopper-v5": ("continuous", 3, 11),
}
#: Box2D keeps float32 bodies: a written state reads back to within float32 rounding. Every
#: other simulator keeps float64 state and gives it back bit for bit.
FLOAT32_STORAGE = {"LunarLander-v3", "LunarLanderContinuous-v3"}
#: How closely a twin follows after the state is copied, step by step with the same actions:
#: MuJoCo's solver warm start is not state (rounding error). A copied lander keeps its own leg
#: joint angles, and its legs are moved rigidly without the ω × r part of their velocity, so
#: on the first step the leg joints pull its angular velocity by up to ~0.1 (observation units).
TWIN_TOLERANCE = {
    "HalfCheetah-v5": 1e-9,
    "Hopper-v5": 1e-9,
    "LunarLander-v3": 0.15,
    "LunarLanderContinuous-v3": 0.15,
}


def adapter_of(env_id: str) -> EnvironmentAdapter:
    return ENVIRONMENTS.get(env_id)()


def live(adapter: EnvironmentAdapter, seed: int, steps: int):
    """An environment after `steps` steps of the random linear policy: (env, handle, obs)."""
    env, policy = adapter.make(), LinearPolicy(adapter, noise=0.0)
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        obs, *_ = env.step(policy.act(np.asarray(obs, np.float32)[None])[0])
    return env, adapter.handle(env), obs


def test_the_suite_is_registered():
    assert set(SUITE) <= set(ENV_IDS)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_facts_come_from_the_spaces(env_id):
    adapter = adapter_of(env_id)
    assert adapter.env_id == env_id
    assert (adapter.action_kind, adapter.action_size, adapter.state_dim) == SUITE[env_id]
    env = adapter.make()
    assert adapter.state_dim == math.prod(env.observation_space.shape)
    if adapter.action_kind == "continuous":
        np.testing.assert_array_equal(adapter.action_low, env.action_space.low)
        np.testing.assert_array_equal(adapter.action_high, env.action_space.high)
    assert isinstance(adapter.version(), str) and adapter.version()
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_written_state_reads_back_equal(env_id):
    adapter = adapter_of(env_id)
    env, handle, _ = live(adapter, seed=7, steps=15)
    assert isinstance(handle, SimulatorHandle)
    state = handle.read_state()
    assert state.dtype == np.float64 and state.shape == (len(handle.state_names),)
    assert len(set(handle.state_names)) == len(handle.state_names)
    target = state + 0.05 * np.random.default_rng(0).standard_normal(state.shape)
    observation = handle.write_state(target)
    if env_id in FLOAT32_STORAGE:
        np.testing.assert_allclose(handle.read_state(), target, rtol=0, atol=1e-6)
    else:
        np.testing.assert_array_equal(handle.read_state(), target)
    assert np.shape(observation) == (adapter.state_dim,)
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_a_copied_state_makes_a_twin(env_id):
    """Writing A's state into B gives A's observation, and B then moves as A does."""
    adapter = adapter_of(env_id)
    env_a, handle_a, obs_a = live(adapter, seed=1, steps=20)
    env_b, handle_b, _ = live(adapter, seed=2, steps=35)
    obs_b = handle_b.write_state(handle_a.read_state())
    # The simulator's own randomness (LunarLander's engine dispersion) is not state; share it.
    env_b.unwrapped.np_random.bit_generator.state = env_a.unwrapped.np_random.bit_generator.state
    tolerance = TWIN_TOLERANCE.get(env_id, 0.0)
    np.testing.assert_allclose(obs_b, obs_a, rtol=0, atol=min(tolerance, 1e-6))
    policy, rng = LinearPolicy(adapter, seed=1, noise=0.0), np.random.default_rng(3)
    for _ in range(10):
        observation = np.asarray(obs_a, np.float32)[None]
        action = policy.act(observation + 0.1 * rng.standard_normal(observation.shape))[0]
        obs_a, reward_a, *_ = env_a.step(action)
        obs_b, reward_b, *_ = env_b.step(action)
        np.testing.assert_allclose(obs_b, obs_a, rtol=0, atol=tolerance)
        if env_id not in TWIN_TOLERANCE:
            assert reward_b == reward_a
    env_a.close()
    env_b.close()


def test_acrobot_angle_increments_go_the_short_way_round():
    env, handle, _ = live(adapter_of("Acrobot-v1"), seed=0, steps=1)
    before = np.array([math.pi - 0.01, -0.5, 1.0, 2.0])
    after = np.array([-math.pi + 0.02, -0.4, 1.5, 2.5])
    np.testing.assert_allclose(handle.increment(before, after), [0.03, 0.1, 0.5, 0.5])
    env.close()


def test_acrobot_keeps_its_bounds_under_a_scaled_increment():
    """The dynamics faults write `before + factor · increment`; Acrobot holds the result to its
    own step's bounds, so a long episode at the largest factor stays finite (it used to grow to
    infinity and hang in Gymnasium's angle wrapping)."""
    from oodrl.injectors.online import ScalingFault, _Constant

    adapter = adapter_of("Acrobot-v1")
    env, handle, _ = live(adapter, seed=0, steps=1)
    fault, unwrapped = ScalingFault(_Constant(2.5)), env.unwrapped
    bounds = np.array([math.pi, math.pi, unwrapped.MAX_VEL_1, unwrapped.MAX_VEL_2])
    for t, action in enumerate(np.random.default_rng(0).integers(0, 3, size=500)):
        fault.before_step(t, np.asarray(action), handle)
        observation, _, terminated, truncated, _ = env.step(int(action))
        fault.after_step(t, observation, np.asarray(action), handle)
        assert np.all(np.abs(handle.read_state()) <= bounds)
        if terminated or truncated:
            env.reset(seed=t)
    written = handle.write_state(np.array([7.0, -4.0, 100.0, -100.0]))
    np.testing.assert_allclose(
        handle.read_state(), [7 - 2 * math.pi, 2 * math.pi - 4, *bounds[2:] * [1, -1]]
    )
    np.testing.assert_array_equal(written, unwrapped._get_ob())
    env.close()


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Hopper-v5"])
def test_mujoco_state_names_are_the_joints(env_id):
    env, handle, _ = live(adapter_of(env_id), seed=0, steps=1)
    model = env.unwrapped.model
    assert len(handle.state_names) == model.nq + model.nv
    assert handle.state_names[:3] == ("qpos.rootx", "qpos.rootz", "qpos.rooty")
    assert handle.state_names[model.nq] == "qvel.rootx"
    env.close()
