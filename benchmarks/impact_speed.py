"""Impact episodes with and without the rest of the horizon, side by side in one run.

    python benchmarks/impact_speed.py [--envs LunarLander-v3 ...] [--episodes 64] [--repeats 3]
        [--workers 1]

Impact calibration (SPEC §15, §19) counts each stream's first whole episode. Before protocol
version 3 a stream ran to the environment's time limit whatever happened; now it stops where its
first episode ends (the collector's `first_episode`). For each environment of the suite, its
committed policy plays ``--episodes`` clean impact episodes both ways, alternating per repeat
so that machine load hits both alike. Prints the stream-steps simulated, the seconds (best
repeat; CPU time of this process with one worker, wall time with more), their ratio, and
whether the first-episode returns are the same bits (they must be).

Run it with ``OPENBLAS_NUM_THREADS=1`` as the stages do (`oodrl.parallel`).
"""

from __future__ import annotations

import argparse
import os
import time

for _variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import numpy as np  # noqa: E402

from oodrl.config import POLICY_SEED_OFFSET  # noqa: E402
from oodrl.envs import ENVIRONMENTS  # noqa: E402
from oodrl.envs.collect import collect  # noqa: E402
from oodrl.policies.load import load_policy  # noqa: E402
from oodrl.protocol.impact import episode_limit, first_episode_returns  # noqa: E402
from oodrl.suite.environments import PIPELINE_DIRS, policy_path  # noqa: E402


def _timed(workers: int, *args, **kwargs) -> tuple[float, object]:
    """(seconds, set) of one `collect` call."""
    clock = time.perf_counter if workers > 1 else time.process_time
    start = clock()
    result = collect(*args, workers=workers, **kwargs)
    return clock() - start, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="*", default=sorted(PIPELINE_DIRS))
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args()
    seeds = [POLICY_SEED_OFFSET + j for j in range(args.episodes)]
    print(f"{args.episodes} clean impact episodes per environment, best of {args.repeats}, "
          f"{args.workers} worker(s)")  # fmt: skip
    print("| environment | horizon | steps, whole horizon | steps, first episode | "
          "s, whole horizon | s, first episode | ratio | same returns |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for env_id in args.envs:
        adapter = ENVIRONMENTS.get(env_id)()
        policy = load_policy(policy_path(env_id), mode="greedy")
        horizon = episode_limit(adapter)
        best = {False: np.inf, True: np.inf}
        returns = {}
        for _ in range(args.repeats):
            for first in (False, True):
                seconds, tset = _timed(
                    args.workers, adapter, policy, seeds, horizon, first_episode=first
                )
                best[first] = min(best[first], seconds)
                returns[first] = first_episode_returns(tset)
                if first:
                    stopped = int((np.cumsum(tset.dones, axis=1) - tset.dones == 0).sum())
        same = np.array_equal(returns[False], returns[True])
        whole = len(seeds) * horizon
        print(f"| {env_id} | {horizon} | {whole} | {stopped} | {best[False]:.2f} | "
              f"{best[True]:.2f} | {best[True] / best[False]:.2f} | {same} |")  # fmt: skip


if __name__ == "__main__":
    main()
