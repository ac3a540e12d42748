"""Environment adapters: the only environment-aware code in oodrl (SPEC §2, §11).

Registered lazily by Gymnasium id; `ENVIRONMENTS.get(id)()` is the adapter every collector,
injector check and stage is handed.
"""

from oodrl.registry import Registry

ENVIRONMENTS = Registry("environment")
ENVIRONMENTS.register("LunarLander-v3", "oodrl.envs.lunar_lander:LunarLanderAdapter")
