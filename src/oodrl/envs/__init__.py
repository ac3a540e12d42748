"""Environment adapters: the only environment-aware code in oodrl (SPEC §2)."""

from oodrl.registry import Registry

ENVIRONMENTS = Registry("environment")
ENVIRONMENTS.register("LunarLander-v3", "oodrl.envs.lunar_lander:LunarLanderAdapter")
