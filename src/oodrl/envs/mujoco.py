"""MuJoCo locomotion (HalfCheetah-v5, Hopper-v5): the state vector is `qpos` then `qvel`.

Written through gymnasium's `set_state`, which copies both and runs `mj_forward`, so the derived
quantities (contacts, sensor values, the observation) describe the written state. `qpos` and
`qvel` are the whole physical state of these models (motors without activation dynamics); only
the constraint solver's warm start is not, which changes later steps by rounding error alone.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle

if TYPE_CHECKING:
    import gymnasium as gym

# Coordinates of one joint in qpos and in qvel, by mjtJoint (free, ball, slide, hinge).
_JOINT_COORDINATES = {
    0: (("x", "y", "z", "qw", "qx", "qy", "qz"), ("vx", "vy", "vz", "wx", "wy", "wz")),
    1: (("qw", "qx", "qy", "qz"), ("wx", "wy", "wz")),
    2: (("",), ("",)),
    3: (("",), ("",)),
}


def coordinate_names(model) -> tuple[str, ...]:
    """'qpos.<joint>' and 'qvel.<joint>' names (with a suffix per coordinate of a free or ball
    joint) in qpos-then-qvel order, read from the compiled model."""
    positions, velocities = [], []
    for j in range(model.njnt):
        joint = model.joint(j).name or f"joint{j}"
        pos, vel = _JOINT_COORDINATES[int(model.jnt_type[j])]
        positions += [f"qpos.{joint}" + (f".{c}" if c else "") for c in pos]
        velocities += [f"qvel.{joint}" + (f".{c}" if c else "") for c in vel]
    return (*positions, *velocities)


class MujocoHandle(SimulatorHandle):
    def __init__(self, env: gym.Env) -> None:
        self._env = env.unwrapped
        self._nq = self._env.model.nq
        self.state_names = coordinate_names(self._env.model)

    def read_state(self) -> np.ndarray:
        return np.concatenate([self._env.data.qpos, self._env.data.qvel])

    def write_state(self, state: np.ndarray) -> np.ndarray:
        state = np.asarray(state, dtype=np.float64)
        self._env.set_state(state[: self._nq], state[self._nq :])
        return self._env._get_obs()


class MujocoAdapter(EnvironmentAdapter):
    """A gymnasium MuJoCo environment; subclasses name the id."""

    @classmethod
    def version(cls) -> str:
        # The physics engine's own version changes trajectories as much as gymnasium's does.
        import gymnasium
        import mujoco

        return f"gymnasium {gymnasium.__version__}, mujoco {mujoco.__version__}"

    def handle(self, env: gym.Env) -> MujocoHandle:
        return MujocoHandle(env)


class HalfCheetahAdapter(MujocoAdapter):
    env_id = "HalfCheetah-v5"


class HopperAdapter(MujocoAdapter):
    env_id = "Hopper-v5"
