"""The environment adapter contract: the only environment-aware code in oodrl (SPEC §2, §11).

An adapter makes the environments of one Gymnasium id and takes every fact about them (the
observation size, the action kind, the number of actions or the action vector's dimension and
bounds) from their spaces, never from constants. For online faults it hands out a
`SimulatorHandle` on one live environment, which reads the simulator's *state vector* and writes
a modified one back so that the next observation reflects it.

The state vector is the observation where the observation is the state (CartPole; LunarLander's
body coordinates); otherwise it is the physical coordinates the handle names in `state_names`
(Acrobot and Pendulum: angles and angular velocities, not their sines and cosines; MuJoCo:
`qpos` then `qvel`). Nothing here imports gymnasium: `oodrl.core` stays light.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from functools import cached_property
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from oodrl.core.policy import ActionKind, Policy
from oodrl.errors import ContractError, PolicyError

if TYPE_CHECKING:
    import gymnasium as gym


class SimulatorHandle(ABC):
    """Reads and writes the state vector of one live environment (float64, `state_names` order).

    `write_state` followed by `read_state`, with no step between, gives the written state back;
    where the simulator stores a coarser type (Box2D: float32) the handle says so.
    """

    #: One name per state coordinate, in state-vector order.
    state_names: tuple[str, ...]
    #: Indices of the coordinates the simulator wraps into [-π, π] after every step.
    wrapped_angles: tuple[int, ...] = ()

    @abstractmethod
    def read_state(self) -> np.ndarray:
        """The simulator's current state vector, (len(state_names),) float64."""

    @abstractmethod
    def write_state(self, state: np.ndarray) -> np.ndarray:
        """Write `state` into the simulator; returns the observation the environment now yields,
        the one its next `step` starts from."""

    def increment(self, before: np.ndarray, after: np.ndarray) -> np.ndarray:
        """`after − before`; a wrapped angle's increment is the short way round the circle, so a
        step across ±π is a small increment, not a jump of almost 2π."""
        delta = np.asarray(after, dtype=np.float64) - np.asarray(before, dtype=np.float64)
        if self.wrapped_angles:
            angles = list(self.wrapped_angles)
            delta[angles] = (delta[angles] + math.pi) % (2 * math.pi) - math.pi
        return delta


class EnvironmentAdapter(ABC):
    """Makes the environments of `env_id` and describes them from their spaces.

    Keyword arguments are passed to `gymnasium.make` (for variants such as another gravity), so
    the facts are read from an environment made with them, once per adapter instance.
    """

    env_id: ClassVar[str]

    def __init__(self, **env_kwargs: Any) -> None:
        self.env_kwargs = env_kwargs

    def make(self) -> gym.Env:
        import gymnasium as gym

        # Never a render mode: rendering slows every step (LunarLander keeps flame particles).
        return gym.make(self.env_id, disable_env_checker=True, **self.env_kwargs)

    @classmethod
    def version(cls) -> str:
        """The version of the simulation code, recorded with every trajectory store."""
        import gymnasium

        return gymnasium.__version__

    @abstractmethod
    def handle(self, env: gym.Env) -> SimulatorHandle:
        """The state read/write handle of one live environment made by `make`."""

    @cached_property
    def _spaces(self) -> tuple[gym.Space, gym.Space]:
        env = self.make()
        try:
            return env.observation_space, env.action_space
        finally:
            env.close()

    @property
    def observation_space(self) -> gym.Space:
        return self._spaces[0]

    @property
    def action_space(self) -> gym.Space:
        return self._spaces[1]

    @property
    def state_dim(self) -> int:
        """The size of an observation (the `states` rows of a trajectory)."""
        return math.prod(self.observation_space.shape)

    @property
    def action_kind(self) -> ActionKind:
        from gymnasium import spaces

        space = self.action_space
        if isinstance(space, spaces.Discrete) and space.start == 0:
            return "discrete"
        if isinstance(space, spaces.Box) and len(space.shape) == 1:
            return "continuous"
        raise ContractError(
            f"{self.env_id} has action space {space}; oodrl supports Discrete spaces starting "
            "at 0 and 1-dim Box spaces."
        )

    @property
    def action_size(self) -> int:
        """The number of discrete actions, or the continuous action vector's dimension."""
        if self.action_kind == "discrete":
            return int(self.action_space.n)
        return int(self.action_space.shape[0])

    @property
    def action_shape(self) -> tuple[int, ...]:
        """The shape of one action in a trajectory: () for an index, (d_a,) for a vector."""
        return () if self.action_kind == "discrete" else (self.action_size,)

    @property
    def action_dtype(self) -> np.dtype:
        """How trajectories store actions (SPEC §1): int64 indices or float32 vectors."""
        return np.dtype(np.int64 if self.action_kind == "discrete" else np.float32)

    @property
    def action_low(self) -> np.ndarray:
        """The lower bound of each continuous action coordinate."""
        return self._bounds()[0]

    @property
    def action_high(self) -> np.ndarray:
        """The upper bound of each continuous action coordinate."""
        return self._bounds()[1]

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self.action_kind != "continuous":
            raise ContractError(f"{self.env_id} has discrete actions; they have no bounds.")
        space = self.action_space
        return np.asarray(space.low, np.float32), np.asarray(space.high, np.float32)

    def describe_actions(self) -> str:
        """'4 discrete actions' or '2-dim continuous actions', for messages."""
        if self.action_kind == "discrete":
            return f"{self.action_size} discrete actions"
        return f"{self.action_size}-dim continuous actions"

    def check_policy(self, policy: Policy) -> None:
        """Refuse a policy made for another observation size or action space."""
        if policy.state_dim != self.state_dim:
            raise PolicyError(
                f"The policy takes {policy.state_dim}-dim observations; {self.env_id} gives "
                f"{self.state_dim}. Use a policy trained on {self.env_id}."
            )
        if (policy.action_kind, policy.action_size) != (self.action_kind, self.action_size):
            raise PolicyError(
                f"The policy commands {policy.action_size} {policy.action_kind} actions; "
                f"{self.env_id} has {self.describe_actions()}. Use a policy trained on "
                f"{self.env_id}."
            )
