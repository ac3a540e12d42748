"""Under dynamics_scaling on LunarLander: the recorded return, and the share of it that the
fault's writes move through LunarLander's shaping potential Φ (SPEC §15 choices, issue 21 item 8).

    python benchmarks/shaping_under_scaling.py

The adapter keeps the simulator's shaping baseline when it writes a state, so each write's
potential change Φ(w_t) − Φ(u_t) is charged to the next step's reward and the recorded return
is the episode's true one. (Before the fix the baseline was reset to Φ(w_t): the writes were
charged to no step and the recorded return at σ = 1 was 490 against −53 true.) Committed
policy, the impact seeds 500000.., 8 episodes.
"""

from pathlib import Path

import numpy as np

from oodrl.core.injector import Fault
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import collect
from oodrl.envs.lunar_lander import _shaping
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import injector_rng
from oodrl.policies.load import load_policy
from oodrl.protocol.impact import first_episode_returns


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
        f"σ={sev}: recorded return mean {returns.mean():.1f}, of which the writes' potential "
        f"changes {missed.mean():.1f}"
    )
clean = collect(a, p, seeds, 1000)
print(f"clean return mean {first_episode_returns(clean).mean():.1f}")
