"""The collector before and after, side by side in one run: cost per simulated step (SPEC §12).

    python benchmarks/collect_speed.py [--envs LunarLander-v3 ...] [--streams 64] [--steps 300]
        [--repeats 3] [--baseline REV] [--workers 1]

For each environment of the suite, its committed policy collects ``--streams`` clean streams of
``--steps`` steps with the collector of commit ``--baseline`` (``old``: by default the last one
that stepped fixed blocks of 16 streams, read with ``git show`` into a module of its own) and
with this checkout's (``new``), alternating per repeat so that machine load hits both alike.

Prints, per environment:
- ``old``/``new``: milliseconds per stream-step of the whole collection (the best repeat; CPU
  time of this process with one worker, wall time with more), and new/old;
- the shares of a step of the new collector: the policy's calls, ``env.step`` (the simulator
  behind gymnasium's wrappers), and the rest (resets, making environments, the collector's own
  Python), measured in a separate timed run (the timers cost a little themselves);
- whether old and new collected the same bytes (every field, and its dtype).

Run it with ``OPENBLAS_NUM_THREADS=1`` as the stages do (`oodrl.parallel`).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

from policy_step import _Clock, _timed_adapter, _TimedPolicy  # noqa: E402

from oodrl.envs import ENVIRONMENTS  # noqa: E402
from oodrl.envs import collect as new_collector  # noqa: E402
from oodrl.policies.load import load_policy  # noqa: E402
from oodrl.suite.environments import PIPELINE_DIRS, policy_path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The last commit whose collector stepped fixed blocks of 16 streams.
BASELINE = "e7c7466"
FIELDS = ("states", "actions", "executed_actions", "rewards", "next_states", "dones")
FIELDS += ("episode_index", "seeds")


def collector_at(rev: str, directory: Path):
    """The module `oodrl.envs.collect` as commit `rev` had it, imported as `collect_<rev>`."""
    source = subprocess.run(
        ["git", "show", f"{rev}:src/oodrl/envs/collect.py"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    name = f"collect_{rev}".replace("-", "_").replace("~", "_").replace("^", "_")
    path = directory / f"{name}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses and forked workers look it up by name
    spec.loader.exec_module(module)
    return module


def timed_collection(collector, env_id: str, policy, streams: int, steps: int, workers: int):
    """Seconds (CPU of this process with one worker, else wall) and the set collected."""
    adapter = ENVIRONMENTS.get(env_id)()
    clock = time.process_time if workers == 1 else time.perf_counter
    start = clock()
    tset = collector.collect(adapter, policy, range(streams), steps, workers=workers)
    return clock() - start, tset


def shares(env_id: str, policy, streams: int, steps: int) -> tuple[float, float, float]:
    """Seconds per stream-step of the new collector: policy calls, env.step, and all of it."""
    clock = _Clock()
    start = time.thread_time()
    adapter, timed = _timed_adapter(env_id, clock), _TimedPolicy(policy, policy.act, clock)
    new_collector.collect(adapter, timed, range(streams), steps)
    total = time.thread_time() - start
    n = streams * steps
    return clock.policy / n, clock.env / n, total / n


def same_bytes(a, b) -> bool:
    for field in FIELDS:
        x, y = getattr(a, field), getattr(b, field)
        if x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
            return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=list(PIPELINE_DIRS))
    parser.add_argument("--streams", type=int, default=64)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--baseline", default=BASELINE, metavar="REV")
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args()

    unit = "CPU" if args.workers == 1 else f"wall, {args.workers} workers"
    print(
        f"{args.streams} streams x {args.steps} steps, best of {args.repeats}; ms per "
        f"stream-step ({unit}); old = collector at {args.baseline}, new = this checkout"
    )
    print(
        f"{'environment':26s} {'old':>7s} {'new':>7s} {'new/old':>7s}   {'policy':>7s} "
        f"{'env.step':>8s} {'rest':>7s}  same bytes"
    )
    with tempfile.TemporaryDirectory() as tmp:
        old_collector = collector_at(args.baseline, Path(tmp))
        collectors = {"old": old_collector, "new": new_collector}
        for env_id in args.envs:
            policy = load_policy(policy_path(env_id, ROOT))
            best = dict.fromkeys(collectors, float("inf"))
            sets = {}
            for _ in range(args.repeats):
                for name, collector in collectors.items():
                    seconds, sets[name] = timed_collection(
                        collector, env_id, policy, args.streams, args.steps, args.workers
                    )
                    best[name] = min(best[name], seconds)
            policy_s, env_s, total_s = shares(env_id, policy, args.streams, args.steps)
            per_step = {k: 1e3 * v / (args.streams * args.steps) for k, v in best.items()}
            rest_s = total_s - policy_s - env_s
            print(
                f"{env_id:26s} {per_step['old']:7.4f} {per_step['new']:7.4f} "
                f"{per_step['new'] / per_step['old']:7.2f}   {policy_s / total_s:7.0%} "
                f"{env_s / total_s:8.0%} {rest_s / total_s:7.0%}  "
                f"{same_bytes(sets['old'], sets['new'])}",
                flush=True,
            )


if __name__ == "__main__":
    main()
