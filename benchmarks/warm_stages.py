"""Warm stage processes against cold ones: a built pipeline's forced `dvc repro`, both ways.

    python benchmarks/warm_stages.py pipeline/pendulum [--stages STAGE ...] [--rounds 1]

Runs `dvc repro -f` (every stage, or the ones named) in the project with OODRL_WARM=0 (each
stage imports its libraries anew) and with warm stages (`oodrl.warm`), alternating, and prints
each wall time, their ratio and whether every output came out the same bytes: after each run
every output hash its locks record must be as before (DVC records each output's md5 anew after
its stage runs). The project's data must be in the DVC cache (a built pipeline). The warm runs start
with no server, so they pay its start-up. Runs in place: stop other work on the machine first.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from pathlib import Path

from oodrl.testing.pipeline import lock_hashes
from oodrl.warm import stop_servers


def forced_repro(project: Path, stages: list[str], warm: bool) -> tuple[float, int]:
    env = {**os.environ, "OODRL_WARM": "1" if warm else "0"}
    stop_servers()  # so that a warm run pays its server's start-up
    time.sleep(0.5)
    start = time.perf_counter()
    done = subprocess.run(
        ["dvc", "repro", "-f", *(["-s", *stages] if stages else [])],
        cwd=project, env=env, capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"dvc repro -f failed in {project}:\n{done.stdout[-3000:]}{done.stderr}")
    wall = time.perf_counter() - start
    return wall, done.stdout.count("Running stage '")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("project", type=Path)
    parser.add_argument("--stages", nargs="*", default=[])
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    before = lock_hashes(args.project)
    walls: dict[bool, list[float]] = {False: [], True: []}
    for round_ in range(args.rounds):
        for warm in (False, True):
            wall, stages = forced_repro(args.project, args.stages, warm)
            same = lock_hashes(args.project) == before
            walls[warm].append(wall)
            print(
                f"round {round_ + 1} {'warm' if warm else 'cold'}: {wall:.1f} s, {stages} stages, "
                f"outputs {'the same bytes' if same else 'CHANGED (see git diff of the locks)'}",
                flush=True,
            )
            if not same:
                raise SystemExit(1)
    cold, warm = sum(walls[False]), sum(walls[True])
    print(f"warm / cold: {warm / cold:.2f} ({warm:.1f} s / {cold:.1f} s over {args.rounds} rounds)")
    stop_servers()


if __name__ == "__main__":
    main()
