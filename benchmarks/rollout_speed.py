"""Rollout throughput, in one run: bare environment, policy one env at a time, batched collector.

    python benchmarks/rollout_speed.py [--policy models/policy.pt] [--steps 20000]

Prints steps/s for each mode and the ratios against the bare environment measured here.
"""

from __future__ import annotations

import argparse
import time

from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.policy import Policy


def bare_env(adapter: EnvironmentAdapter, steps: int) -> float:
    env = adapter.make()
    env.reset(seed=0)
    env.action_space.seed(0)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def policy_one_env(adapter: EnvironmentAdapter, policy: Policy, steps: int) -> float:
    env = adapter.make()
    obs, _ = env.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        action = policy.act(obs[None, :], None)[0]
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            obs, _ = env.reset()
    return steps / (time.perf_counter() - start)


def batched(
    adapter: EnvironmentAdapter, policy: Policy, steps: int, streams: int, workers: int
) -> float:
    from oodrl.envs.collect import collect

    T = steps // streams  # noqa: N806
    start = time.perf_counter()
    collect(adapter, policy, range(streams), T, workers=workers)
    return streams * T / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="models/policy.pt")
    parser.add_argument("--steps", type=int, default=20_000)
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    from oodrl.envs.lunar_lander import LunarLanderAdapter
    from oodrl.policies.load import load_policy

    adapter, policy = LunarLanderAdapter(), load_policy(args.policy)
    results = {
        "bare env, random actions": bare_env(adapter, args.steps),
        "policy, one env at a time": policy_one_env(adapter, policy, args.steps),
        "batched collector, 16 streams, 1 worker": batched(adapter, policy, args.steps, 16, 1),
        "batched collector, 32 streams, 2 workers": batched(adapter, policy, args.steps, 32, 2),
    }
    base = results["bare env, random actions"]
    for name, rate in results.items():
        print(f"{name:45s} {rate:10.0f} steps/s   {rate / base:5.2f}x bare env")


if __name__ == "__main__":
    main()
