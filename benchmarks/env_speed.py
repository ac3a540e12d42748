"""Rollout throughput per registered environment: bare environment vs the batched collector.

    python benchmarks/env_speed.py [--steps 8000] [--env CartPole-v1 ...]

For each environment, steps/s of
- the bare environment stepping random actions from its action space (resets included);
- the batched collector (one job of 16 streams, one worker) driven by a fixed random linear
  policy made with oodrl's own policy classes (argmax or tanh actor, one layer), clean;
- the same with a `dynamics_scaling` fault (severity 0.1) from the first step, so every step
  also reads the simulator's state vector twice and writes it back once.
Not a test: numbers depend on the machine and its load; run it on an idle one.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import BLOCK_SIZE, collect
from oodrl.policies.act import ArgmaxPolicy, Layer, LayeredPolicy, TanhActorPolicy


def random_linear_policy(adapter: EnvironmentAdapter, seed: int = 0) -> LayeredPolicy:
    """One random affine layer: argmax over discrete actions, or a tanh actor in the bounds."""
    rng = np.random.default_rng(seed)
    shape = (adapter.action_size, adapter.state_dim)
    layer = Layer(
        (rng.standard_normal(shape) / np.sqrt(shape[1])).astype(np.float32),
        (0.1 * rng.standard_normal(shape[0])).astype(np.float32),
    )
    if adapter.action_kind == "discrete":
        return ArgmaxPolicy([layer], kind="mlp")
    return TanhActorPolicy(
        [layer], low=adapter.action_low, high=adapter.action_high, kind="tanh_actor"
    )


def bare_env(adapter: EnvironmentAdapter, steps: int) -> float:
    env = adapter.make()
    env.reset(seed=0)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(steps)]
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - start)
    env.close()
    return rate


def batched(adapter: EnvironmentAdapter, steps: int, fault: str | None) -> float:
    T = max(1, steps // BLOCK_SIZE)  # noqa: N806
    seeds = range(BLOCK_SIZE)
    policy = random_linear_policy(adapter)
    faults, labels = None, None
    if fault is not None:
        from oodrl.injectors import INJECTORS

        injector = INJECTORS.get(fault).from_params({})
        spec = injector.spec(0.1, onset=0)  # small: HalfCheetah diverges at 0.3+
        faults = [injector.fault(spec, np.random.default_rng(i)) for i in seeds]
        labels = spec.labels(T)
    start = time.perf_counter()
    collect(adapter, policy, seeds, T, labels=labels, faults=faults)
    return BLOCK_SIZE * T / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=8000)
    parser.add_argument("--env", nargs="*", default=None, help="environment ids (default: all)")
    args = parser.parse_args()
    env_ids = args.env or ENVIRONMENTS.names()
    header = f"{'environment':26s} {'bare env':>10s} {'collector':>10s} {'ratio':>6s}"
    print(f"{header} {'+ scaling fault':>16s}   (steps/s)")
    for env_id in env_ids:
        adapter = ENVIRONMENTS.get(env_id)()
        bare = bare_env(adapter, args.steps)
        clean = batched(adapter, args.steps, None)
        faulty = batched(adapter, args.steps, "dynamics_scaling")
        print(
            f"{env_id:26s} {bare:10.0f} {clean:10.0f} {clean / bare:6.2f} {faulty:16.0f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
