"""Watch a live fault with the runtime monitor (SPEC §13) on CartPole.

    python examples/live_monitor.py [--fault dynamics_scaling] [--severity 0.6] [--seed 3]

1. `oodrl.run_monitor`, one call: the environment's committed policy acts, a detector fitted
   here on clean streams watches every step, and the fault turns on live a third of the way
   in; each alarm is reported as it is raised (here the first three), then a one-line summary.
2. The same by hand, as you would deploy it: `oodrl.OodMonitor` is a Gymnasium wrapper that
   adds `ood_score` and `ood_alarm` to each step's info. Its detector here is fitted on 10
   clean streams and calibrated by the per-stream rule on 20 more (`episode_max`, α = 0.05: a
   clean episode raises any alarm with probability at most α).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import oodrl

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "CartPole-v1"
STEPS = 500  # CartPole's pipeline streams: T = 500, the fault live from step 166


def first_alarms(n: int):
    """An `echo` for run_monitor that prints its first n alarm lines and its summary."""
    seen = []

    def echo(line: str) -> None:
        alarm = line.startswith("step ")
        seen.append(alarm)
        if not alarm or seen.count(True) <= n:
            print(line)
        elif seen.count(True) == n + 1:
            print("...")

    return echo


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--detector", default="cusum", help="a registered detector")
    parser.add_argument("--fault", default="dynamics_scaling", help="a live fault")
    parser.add_argument("--severity", type=float, default=0.3, help="0.27: CartPole's mild "
                        "tier of dynamics_scaling (R̃ = 0.95)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()

    print(f"1. oodrl.run_monitor: {args.detector} watching {ENV_ID}, {args.fault} at "
          f"σ = {args.severity} from step {STEPS // 3}")  # fmt: skip
    oodrl.run_monitor(ENV_ID, args.detector, args.fault, args.severity,
                      steps=STEPS, seed=args.seed, root=ROOT, echo=first_alarms(3))  # fmt: skip

    from oodrl.detectors import DETECTORS
    from oodrl.envs import ENVIRONMENTS
    from oodrl.envs.collect import collect
    from oodrl.monitor import FaultInjection, live_fault
    from oodrl.policies.load import load_policy

    adapter = ENVIRONMENTS.get(ENV_ID)()
    policy = load_policy(ROOT / "pipeline" / "cartpole" / "models" / "policy.pt")
    clean = collect(adapter, policy, range(10_000, 10_030), STEPS).trajectories()
    detector = DETECTORS.get(args.detector)(threshold_rule="episode_max", alpha=0.05)
    detector.fit(clean[:10]).calibrate(clean[10:])

    onset = STEPS // 3
    env = adapter.make()
    fault = live_fault(adapter, args.fault, args.severity, onset, {}, args.seed)
    alarms = []
    env = oodrl.OodMonitor(FaultInjection(env, adapter.handle(env), fault, onset), detector,
                           on_alarm=alarms.append)  # fmt: skip
    print(f"\n2. oodrl.OodMonitor around gym's {ENV_ID}, threshold {detector.threshold_:.4g}")
    observation, _ = env.reset(seed=args.seed)
    for t in range(STEPS):
        action = policy.act(np.asarray(observation, dtype=np.float32)[None], None)[0]
        observation, _, terminated, truncated, info = env.step(action)
        if info["ood_alarm"] and len(alarms) == 1:
            when = "before" if alarms[0].step < onset else f"{alarms[0].step - onset} steps after"
            print(f"step {t}: first alarm, score {info['ood_score']:.4g}, {when} the onset")
        if terminated or truncated:
            break
    print(f"episode over after {t + 1} steps: {len(alarms)} alarmed steps, the first at step "
          f"{alarms[0].step if alarms else None} (fault from step {onset})")  # fmt: skip
    env.close()


if __name__ == "__main__":
    main()
