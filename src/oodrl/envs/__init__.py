"""Environment adapters: the only environment-aware code in oodrl (SPEC §2, §11).

Registered lazily by Gymnasium id; `ENVIRONMENTS.get(id)()` is the adapter every collector,
injector check and stage is handed.
"""

from oodrl.registry import Registry

ENVIRONMENTS = Registry("environment")
ENVIRONMENTS.register("LunarLander-v3", "oodrl.envs.lunar_lander:LunarLanderAdapter")
ENVIRONMENTS.register("CartPole-v1", "oodrl.envs.classic_control:CartPoleAdapter")
ENVIRONMENTS.register("Acrobot-v1", "oodrl.envs.classic_control:AcrobotAdapter")
ENVIRONMENTS.register("Pendulum-v1", "oodrl.envs.classic_control:PendulumAdapter")
ENVIRONMENTS.register(
    "LunarLanderContinuous-v3", "oodrl.envs.lunar_lander:LunarLanderContinuousAdapter"
)
ENVIRONMENTS.register("HalfCheetah-v5", "oodrl.envs.mujoco:HalfCheetahAdapter")
ENVIRONMENTS.register("Hopper-v5", "oodrl.envs.mujoco:HopperAdapter")
