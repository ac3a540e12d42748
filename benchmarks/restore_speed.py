"""A task's restore of a built project from the local DVC cache, two ways, timed in one run.

    python benchmarks/restore_speed.py --root CHECKOUT --project pipeline/pendulum_policy2
        [--rounds 2]

CHECKOUT is a git checkout whose project is built at HEAD, its outputs in CHECKOUT's DVC cache
(after `oodrl suite run` there, say). Each round clones HEAD twice, as a task of `oodrl suite
run` or `oodrl suite try` does, points each clone at that cache and reproduces the project's
results stages (`metrics`, `tier_metrics`: what a try's run ends with):

- stage by stage: `dvc repro` alone, which restores each current stage's missing outputs in
  turn ("is cached - skipping run") and rewrites dvc.lock after each;
- one checkout: `oodrl.suite.run.restore_outputs` first (`dvc checkout --allow-missing` without
  a remote), then the same `dvc repro`.

The two alternate which goes first. Both must end with the same results files, byte for byte,
and run no stage but `check_params` (a project not built at HEAD is refused); the medians and
their ratio are printed. A try adds its detector's own stages to both.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from oodrl.suite.run import ran_stages, restore_outputs, task_environment
from oodrl.testing.pipeline import run

RESULTS_STAGES = ("dvc.yaml:metrics", "dvc.yaml:tier_metrics")
RESULTS_FILES = ("reports/results.yaml", "reports/sweep_results.yaml", "reports/tier_results.json")


def restored(root: Path, project: str, cache: str, folder: Path, one_checkout: bool):
    """Clone HEAD into `folder`, restore the project's results stages one way; the seconds from
    the clone's first DVC command on, the stages that ran and the results files' bytes."""
    clone = folder / "repo"
    run(folder, "git", "clone", "-q", str(root), str(clone))
    where = clone / project
    env = task_environment(clone)
    start = time.perf_counter()
    run(where, "dvc", "cache", "dir", "--local", cache)
    if one_checkout:
        restore_outputs(where, env, None)
    done = run(where, "dvc", "repro", *RESULTS_STAGES, env=env)
    seconds = time.perf_counter() - start
    return seconds, ran_stages(done.stdout), {f: (where / f).read_bytes() for f in RESULTS_FILES}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="a checkout, its project built")
    parser.add_argument("--project", required=True, help="e.g. pipeline/pendulum_policy2")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    root = args.root.resolve()
    cache = run(root, "dvc", "cache", "dir").stdout.strip()
    times: dict[bool, list[float]] = {False: [], True: []}
    reference = None  # the results files of the first clone: every other must match them
    for round_ in range(args.rounds):
        for one_checkout in (round_ % 2 == 1, round_ % 2 == 0):
            with tempfile.TemporaryDirectory(prefix="oodrl-restore-") as folder:
                seconds, ran, files = restored(root, args.project, cache, Path(folder),
                                               one_checkout)  # fmt: skip
            if set(ran) - {"check_params"}:
                sys.exit(f"error: {args.project} is not built at HEAD: `dvc repro` ran "
                         f"{', '.join(ran)}")  # fmt: skip
            reference = reference or files
            if files != reference:
                print("error: the two ways gave different results files", file=sys.stderr)
                return 1
            times[one_checkout].append(seconds)
            way = "one checkout" if one_checkout else "stage by stage"
            print(f"round {round_ + 1}, {way}: {seconds:.1f} s (ran: {', '.join(ran) or 'none'})")
    a, b = statistics.median(times[False]), statistics.median(times[True])
    print(f"{args.project}: stage by stage median {a:.1f} s, one checkout {b:.1f} s "
          f"({args.rounds} rounds): {b / a:.2f}×")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
