"""Cost beside accuracy: per detector, fit time, pickled size and streaming latency per step
(median and p99 of `stream().update`, one thread), on clean streams of a committed policy.

    python benchmarks/detector_cost.py [--env LunarLander-v3] [--steps 200] [--fit 4] [names...]
    python benchmarks/detector_cost.py --blocks src/oodrl/library_detectors.yaml [names...]

Detector parameters are the class defaults, or with `--blocks` the params blocks of a YAML file
(a block's `class:` may name a library's outlier class, SPEC §17); fit time is `fit` plus
`calibrate` (on `--calibration` streams, default as many as `--fit`). Latency is
measured by `oodrl.metrics.cost` (as the pipeline's render stage measures it into run_meta.yaml)
over every step of `--score` streams fed one update at a time (flushes included).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy, as in every oodrl stage

import pickle  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def clean_streams(env_id: str, n: int, steps: int, first_seed: int = 20_000) -> list:
    """`n` clean streams of `steps` steps of the environment's committed policy."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.envs.collect import collect
    from oodrl.policies.load import load_policy
    from oodrl.suite.environments import policy_path

    adapter = ENVIRONMENTS.get(env_id)()
    policy = load_policy(policy_path(env_id, ROOT), "greedy", None, adapter.state_dim)
    seeds = range(first_seed, first_seed + n)
    return collect(adapter, policy, seeds, steps).trajectories()


def build(name: str, blocks: dict):
    """The detector `name`: its block of `blocks` (class and parameters) or the class defaults."""
    from oodrl.detectors import DETECTORS

    block = dict(blocks.get(name, {}))
    return DETECTORS.get(block.pop("class", name)).from_params(block)


def detector_cost(detector, fit, calibration, scored) -> dict[str, float]:
    from oodrl.metrics.cost import step_latency_us

    start = time.perf_counter()
    detector.fit(fit)
    detector.calibrate(calibration)
    fit_s = time.perf_counter() - start
    return {
        "fit_s": fit_s,
        "size_kib": len(pickle.dumps(detector, protocol=5)) / 1024,
        **step_latency_us(detector, scored),
    }


def main() -> None:
    from oodrl.detectors import DETECTORS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*")
    parser.add_argument("--blocks", type=Path, help="YAML file of detector params blocks")
    parser.add_argument("--env", default="LunarLander-v3")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--fit", type=int, default=4)
    parser.add_argument("--calibration", type=int)
    parser.add_argument("--score", type=int, default=2)
    args = parser.parse_args()
    blocks = yaml.safe_load(args.blocks.read_text()) if args.blocks else {}
    names = args.names or list(blocks) or DETECTORS.names()
    n_calibration = args.fit if args.calibration is None else args.calibration
    data = clean_streams(args.env, args.fit + n_calibration + args.score, args.steps)
    fit, calibration = data[: args.fit], data[args.fit : args.fit + n_calibration]
    scored = data[args.fit + n_calibration :]
    print(f"{args.env}: fit on {args.fit} x {args.steps} steps, calibrate on {n_calibration}; "
          f"latency over {args.score * args.steps} streamed steps, one thread")  # fmt: skip
    print(f"{'detector':24} {'fit s':>8} {'size KiB':>9} {'median µs':>10} {'p99 µs':>9}")
    with threadpool_limits(limits=1):
        for name in names:
            cost = detector_cost(build(name, blocks), fit, calibration, scored)
            print(
                f"{name:24} {cost['fit_s']:8.2f} {cost['size_kib']:9.1f} "
                f"{cost['step_us_median']:10.0f} {cost['step_us_p99']:9.0f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
