"""Any Gymnasium environment with a flat Box observation (SPEC §18).

Observation faults act on recorded observations and action faults on the commanded action, so
both need nothing but the Gymnasium API. Dynamics faults scale the increment of a state vector
the adapter reads and writes back; generically that exists for MuJoCo environments only
(`qpos` then `qvel`, through `set_state`, as `oodrl.envs.mujoco`), and only where writing a
state back gives that state and a twin that moves as the original does (`probe_state`). Every
other environment gets a handle that refuses, naming why (`oodrl.suite.new.fault_support` lists each
fault left out with it).

`generic_adapter(env_id)` is the adapter class of one id; `oodrl.envs.ENVIRONMENTS` hands it
out for every Gymnasium id the suite does not register, and for `FlattenObservation(<id>)`, whose
observations gymnasium.wrappers.FlattenObservation flattens (`oodrl new --flatten`).
"""

from __future__ import annotations

from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.envs import gymnasium_id
from oodrl.errors import ContractError

if TYPE_CHECKING:
    import gymnasium as gym

#: How closely a twin made by copying the state follows the original (MuJoCo's solver warm
#: start is not state: rounding error), and over how many steps it is checked.
TWIN_TOLERANCE = 1e-9
TWIN_STEPS = 20


def is_mujoco(env_id: str) -> bool:
    """Whether gymnasium's entry point of `env_id` is a MuJoCo environment (without making it)."""
    import gymnasium

    entry = gymnasium.spec(gymnasium_id(env_id)).entry_point
    return isinstance(entry, str) and entry.startswith("gymnasium.envs.mujoco")


class NoStateHandle(SimulatorHandle):
    """The handle of an environment without a state vector: dynamics faults are refused."""

    state_names = ()

    def __init__(self, env_id: str) -> None:
        self.env_id = env_id

    def read_state(self) -> np.ndarray:
        raise ContractError(no_state_reason(self.env_id))

    def write_state(self, state: np.ndarray) -> np.ndarray:
        raise ContractError(no_state_reason(self.env_id))


def no_state_reason(env_id: str) -> str:
    return (
        f"{env_id} has no state vector oodrl can read and write: generically only MuJoCo "
        "environments have one (qpos, qvel); an adapter of its own "
        "(oodrl.core.adapter.EnvironmentAdapter) would add it."
    )


class GenericAdapter(EnvironmentAdapter):
    """A Gymnasium environment outside the suite; `generic_adapter(env_id)` names the id."""

    env_id = ""

    def make(self) -> gym.Env:
        from oodrl.envs import make

        # Never a render mode, as EnvironmentAdapter.make; FlattenObservation where named.
        env = make(self.env_id, disable_env_checker=True, **self.env_kwargs)
        space = env.observation_space
        if not _is_flat_box(space):
            env.close()
            raise ContractError(unsupported_observation(self.env_id, space))
        return env

    @classmethod
    def version(cls) -> str:
        import gymnasium

        if not is_mujoco(cls.env_id):
            return gymnasium.__version__
        import mujoco

        return f"gymnasium {gymnasium.__version__}, mujoco {mujoco.__version__}"

    def handle(self, env: gym.Env) -> SimulatorHandle:
        if is_mujoco(self.env_id):
            from oodrl.envs.mujoco import MujocoHandle

            return MujocoHandle(env)
        return NoStateHandle(self.env_id)

    def __reduce__(self) -> tuple[Any, ...]:
        # The class is made at run time, so collection's worker processes rebuild it by id.
        return (_rebuilt, (self.env_id, self.env_kwargs))


@cache
def generic_adapter(env_id: str) -> type[GenericAdapter]:
    """The adapter class of a Gymnasium id outside the suite."""
    return type(f"GenericAdapter[{env_id}]", (GenericAdapter,), {"env_id": env_id})


def _rebuilt(env_id: str, env_kwargs: dict[str, Any]) -> GenericAdapter:
    return generic_adapter(env_id)(**env_kwargs)


def _is_flat_box(space: gym.Space) -> bool:
    from gymnasium import spaces

    return isinstance(space, spaces.Box) and len(space.shape) == 1


def unsupported_observation(env_id: str, space: gym.Space) -> str:
    what = "an image" if len(getattr(space, "shape", None) or ()) == 3 else type(space).__name__
    return (
        f"{env_id} observes {what} ({space}); oodrl needs a flat Box observation (one vector "
        "per step): `oodrl new --flatten` wraps it in gymnasium.wrappers.FlattenObservation."
    )


def probe_state(adapter: EnvironmentAdapter, seed: int = 0) -> str | None:
    """None when the adapter's state vector reads back as written and a copied state makes a
    twin; else why not (the tests every suite adapter passes, run on this environment)."""
    env_a, env_b = adapter.make(), adapter.make()
    try:
        handle_a, handle_b = adapter.handle(env_a), adapter.handle(env_b)
        env_a.reset(seed=seed)
        env_b.reset(seed=seed + 1)
        env_a.action_space.seed(seed)
        for _ in range(5):
            env_a.step(env_a.action_space.sample())
        try:
            state = handle_a.read_state()
        except ContractError as error:
            return str(error)
        # Velocities only: a perturbed quaternion (free joints) would not be a valid position.
        target = state.copy()
        n_pos = sum(name.startswith("qpos.") for name in handle_a.state_names)
        target[n_pos:] += 0.05 * np.random.default_rng(seed).standard_normal(len(state) - n_pos)
        handle_a.write_state(target)
        if not np.array_equal(handle_a.read_state(), target):
            return f"{adapter.env_id}: a written state does not read back as written."
        handle_b.write_state(target)
        for _ in range(TWIN_STEPS):
            action = env_a.action_space.sample()
            obs_a = env_a.step(action)[0]
            obs_b = env_b.step(action)[0]
            if not np.allclose(obs_a, obs_b, rtol=0, atol=TWIN_TOLERANCE):
                return (
                    f"{adapter.env_id}: a copy of its qpos/qvel does not move as the original "
                    "(the simulator keeps state beyond them)."
                )
        return None
    finally:
        env_a.close()
        env_b.close()
