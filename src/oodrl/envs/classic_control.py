"""CartPole-v1, Acrobot-v1 and Pendulum-v1: simulators whose whole state is one float64 array.

Each keeps its state in `env.unwrapped.state` and recomputes the observation from it, so the
state vector is that array: written back, it reads back bit for bit.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from typing import TYPE_CHECKING

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.errors import ContractError

if TYPE_CHECKING:
    import gymnasium as gym


class StateArrayHandle(SimulatorHandle):
    """Reads and writes `env.unwrapped.state`; a subclass says how it becomes an observation."""

    def __init__(self, env: gym.Env) -> None:
        self._env = env.unwrapped

    def read_state(self) -> np.ndarray:
        return np.array(self._env.state, dtype=np.float64)

    def write_state(self, state: np.ndarray) -> np.ndarray:
        self._env.state = np.array(state, dtype=np.float64)
        return self._observation()

    @abstractmethod
    def _observation(self) -> np.ndarray:
        """The observation the environment computes from its current state."""


class CartPoleHandle(StateArrayHandle):
    """The observation is the state, rounded to float32."""

    state_names = ("x", "x_dot", "theta", "theta_dot")

    def _observation(self) -> np.ndarray:
        return np.array(self._env.state, dtype=np.float32)


class AcrobotHandle(StateArrayHandle):
    """The two joint angles and angular velocities; the observation holds the angles' cos and
    sin. Acrobot wraps both angles into [-π, π] and bounds both velocities after every step."""

    state_names = ("theta1", "theta2", "theta1_dot", "theta2_dot")
    wrapped_angles = (0, 1)

    def write_state(self, state: np.ndarray) -> np.ndarray:
        """A written state is held to what Acrobot's own step keeps: angles wrapped into
        [-π, π], velocities bounded by MAX_VEL_1 and MAX_VEL_2, with Gymnasium's own `wrap` and
        `bound`. A scaled increment (the dynamics faults) otherwise pushes a velocity past its
        bound every step; the state then grows to infinity within a few steps, and the next
        step's `wrap`, a loop adding 2π, never ends. A state inside the bounds is written
        unchanged."""
        from gymnasium.envs.classic_control.acrobot import bound, wrap

        state = np.array(state, dtype=np.float64)
        if not np.all(np.isfinite(state)):
            raise ContractError(f"Acrobot state must be finite, got {state.tolist()}")
        env = self._env
        state[0] = wrap(state[0], -math.pi, math.pi)
        state[1] = wrap(state[1], -math.pi, math.pi)
        state[2] = bound(state[2], -env.MAX_VEL_1, env.MAX_VEL_1)
        state[3] = bound(state[3], -env.MAX_VEL_2, env.MAX_VEL_2)
        return super().write_state(state)

    def _observation(self) -> np.ndarray:
        return self._env._get_ob()


class PendulumHandle(StateArrayHandle):
    """The angle (never wrapped by the simulator) and angular velocity; the observation holds
    the angle's cos and sin."""

    state_names = ("theta", "theta_dot")

    def _observation(self) -> np.ndarray:
        return self._env._get_obs()


class CartPoleAdapter(EnvironmentAdapter):
    env_id = "CartPole-v1"

    def handle(self, env: gym.Env) -> CartPoleHandle:
        return CartPoleHandle(env)


class AcrobotAdapter(EnvironmentAdapter):
    env_id = "Acrobot-v1"

    def handle(self, env: gym.Env) -> AcrobotHandle:
        return AcrobotHandle(env)


class PendulumAdapter(EnvironmentAdapter):
    env_id = "Pendulum-v1"

    def handle(self, env: gym.Env) -> PendulumHandle:
        return PendulumHandle(env)
