"""Environment adapters: the only environment-aware code in oodrl (SPEC §2, §11).

Registered lazily by Gymnasium id; `ENVIRONMENTS.get(id)()` is the adapter every collector,
injector check and stage is handed. Any other id in gymnasium's registry gets the generic
adapter (`oodrl.envs.generic`, SPEC §18), and so does `FlattenObservation(<id>)`: that
environment with gymnasium.wrappers.FlattenObservation around it (`oodrl new --flatten`), so
params name the wrapped environment and every stage makes the same one.
"""

import re
from typing import Any

from oodrl.errors import RegistryError
from oodrl.registry import Registry, import_path

GENERIC_ADAPTER = "oodrl.envs.generic:GenericAdapter"
GENERIC_FACTORY = "oodrl.envs.generic:generic_adapter"
_FLATTENED = re.compile(r"FlattenObservation\((?P<id>.+)\)")


def flattened(env_id: str) -> str:
    """The name of `env_id`'s environment with flattened observations."""
    return f"FlattenObservation({env_id})"


def gymnasium_id(name: str) -> str:
    """The Gymnasium id an environment name makes: <id> of `FlattenObservation(<id>)`."""
    match = _FLATTENED.fullmatch(name)
    return match.group("id") if match else name


def make(name: str, **kwargs: Any):
    """`gymnasium.make` of an environment name, FlattenObservation around a flattened one's."""
    import gymnasium

    env = gymnasium.make(gymnasium_id(name), **kwargs)
    return env if gymnasium_id(name) == name else gymnasium.wrappers.FlattenObservation(env)


class EnvironmentRegistry(Registry):
    """The suite's adapters by id; every other Gymnasium id maps to the generic adapter."""

    def path(self, name: str) -> str:
        if name in self:
            return super().path(name)
        import gymnasium

        if gymnasium_id(name) not in gymnasium.registry:
            try:
                super().path(name)
            except RegistryError as error:
                raise RegistryError(f"{error} Or any id in gymnasium's registry.") from None
        return GENERIC_ADAPTER

    def get(self, name: str) -> Any:
        if ":" in name or name in self or self.path(name) != GENERIC_ADAPTER:
            return super().get(name)
        # By import path, as every adapter here: a stage's code stamp lists the generic module
        # only where its environment uses it (oodrl.suite.pipeline.component_modules).
        return import_path(GENERIC_FACTORY)(name)


ENVIRONMENTS = EnvironmentRegistry("environment")
ENVIRONMENTS.register("LunarLander-v3", "oodrl.envs.lunar_lander:LunarLanderAdapter")
ENVIRONMENTS.register("CartPole-v1", "oodrl.envs.classic_control:CartPoleAdapter")
ENVIRONMENTS.register("Acrobot-v1", "oodrl.envs.classic_control:AcrobotAdapter")
ENVIRONMENTS.register("Pendulum-v1", "oodrl.envs.classic_control:PendulumAdapter")
ENVIRONMENTS.register(
    "LunarLanderContinuous-v3", "oodrl.envs.lunar_lander:LunarLanderContinuousAdapter"
)
ENVIRONMENTS.register("HalfCheetah-v5", "oodrl.envs.mujoco:HalfCheetahAdapter")
ENVIRONMENTS.register("Hopper-v5", "oodrl.envs.mujoco:HopperAdapter")
