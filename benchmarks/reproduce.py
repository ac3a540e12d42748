"""Prove the pipeline reproduces: two from-scratch runs in fresh copies give identical outputs.

    python benchmarks/reproduce.py --params ci/params.yaml

For each of two fresh copies of the project (own git + DVC repo, no data): `dvc repro`; then
check that every output hash in the two dvc.lock files is identical, that `dvc status -q`
exits 0, and that a further `dvc repro` runs no stage. Exit code 1 on any difference.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import yaml

from oodrl.testing.pipeline import copy_project, lock_hashes, repro, run

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=Path, default=ROOT / "ci" / "params.yaml")
    args = parser.parse_args()
    params = yaml.safe_load(args.params.read_text())
    runs = []
    with tempfile.TemporaryDirectory(prefix="oodrl-reproduce-") as scratch:
        for index in range(2):
            repo = copy_project(ROOT, Path(scratch) / f"run{index}", params)
            start = time.perf_counter()
            ran = repro(repo)
            seconds = time.perf_counter() - start
            print(f"run {index}: dvc repro ran {len(ran)} stages in {seconds:.1f} s")
            status = run(repo, "dvc", "status", "-q", check=False)
            if status.returncode != 0:
                print(f"FAIL: run {index}: `dvc status -q` exit {status.returncode}")
                return 1
            again = repro(repo)
            if again:
                print(f"FAIL: run {index}: a second dvc repro re-ran {again}")
                return 1
            runs.append(lock_hashes(repo))
    first, second = runs
    differing = sorted(p for p in set(first) | set(second) if first.get(p) != second.get(p))
    if differing:
        print(f"FAIL: {len(differing)} outputs differ between the runs: {differing}")
        return 1
    print(
        f"OK: {len(first)} outputs byte-identical across two from-scratch runs; "
        "dvc status clean; a second repro ran nothing"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
