"""Under dynamics_scaling on LunarLander: how much of an episode's recorded return comes from the
writes' uncharged potential changes (SPEC §15 choices, issue 21 item 8).

    python benchmarks/shaping_under_scaling.py

reward_t = Φ(u_t) − Φ(w_{t−1}) (the adapter resets the shaping baseline to the written state), so
Σ rewards misses Σ_t Φ(w_t) − Φ(u_t). Committed policy, the impact seeds 500000.., 8 episodes.
"""

from pathlib import Path

import numpy as np

from oodrl.core.injector import Fault
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import collect
from oodrl.envs.lunar_lander import _shaping
from oodrl.impact import first_episode_returns
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import injector_rng
from oodrl.policies.load import load_policy


class Ledger(Fault):
    def __init__(self, inner):
        self.inner, self.missed, self.episode_missed = inner, [], 0.0

    def before_step(self, t, commanded, sim):
        return self.inner.before_step(t, commanded, sim)

    def after_step(self, t, observation, commanded, sim):
        written = self.inner.after_step(t, observation, commanded, sim)
        self.episode_missed += _shaping(np.asarray(written, np.float64)) - _shaping(
            np.asarray(observation, np.float64)
        )
        return written

    def after_reset(self, t, observation, sim):
        self.missed.append(self.episode_missed)
        self.episode_missed = 0.0
        return observation


a = ENVIRONMENTS.get("LunarLander-v3")()
p = load_policy(Path(__file__).resolve().parents[1] / "models" / "policy.pt", mode="greedy")
seeds = [500000 + j for j in range(8)]
for sev in (0.5, 1.0):
    inj = INJECTORS.get("dynamics_scaling")()
    spec = inj.spec(sev, 0)
    faults = [
        Ledger(inj.fault(spec, injector_rng(0, "dynamics_scaling", j))) for j in range(len(seeds))
    ]
    t = collect(a, p, seeds, 1000, labels=spec.labels(1000), faults=faults)
    returns = first_episode_returns(t)
    missed = np.array([f.missed[0] if f.missed else f.episode_missed for f in faults])
    print(
        f"σ={sev}: recorded return mean {returns.mean():.1f}; writes' uncharged potential change "
        f"mean {missed.mean():.1f}; corrected return mean {(returns + missed).mean():.1f}"
    )
clean = collect(a, p, seeds, 1000)
print(f"clean return mean {first_episode_returns(clean).mean():.1f}")
