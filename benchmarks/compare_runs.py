"""Same-run cost of a change: a full default `dvc repro` of a baseline commit and of HEAD.

    python benchmarks/compare_runs.py --baseline 42aafad

Each revision is checked out into a fresh copy of the project (own git + DVC repo, no data) and
runs `dvc repro` from scratch with its own code (PYTHONPATH points at the copy's sources); the
two runs happen one after the other on the same machine. Prints each wall time, the ratio, and
the stage-body seconds per stage kind from each run's reports/run_meta.yaml.
"""

from __future__ import annotations

import argparse
import collections
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from oodrl.testing.pipeline import copy_project, environment

ROOT = Path(__file__).resolve().parents[1]


def full_run(source: Path, dest: Path) -> tuple[float, dict[str, float]]:
    repo = copy_project(source, dest)
    env = environment({"PYTHONPATH": str(repo / "src")})
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "dvc", "repro"], cwd=repo, env=env, capture_output=True, text=True
    )
    seconds = time.perf_counter() - start
    if done.returncode:
        sys.exit(f"{source}: dvc repro failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    meta = yaml.safe_load((repo / "reports" / "run_meta.yaml").read_text())
    kinds: dict[str, float] = collections.defaultdict(float)
    for stage, wall in meta["stage_wall_s"].items():
        # 'score@d-i' (old layout) and 'detectors/d/dvc.yaml:score@i' are both kind 'score'.
        kinds[stage.rpartition(":")[2].split("@")[0]] += float(wall)
    return seconds, dict(kinds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, help="git revision to compare HEAD with")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="oodrl-compare-") as scratch:
        baseline = Path(scratch) / "baseline-source"
        subprocess.run(["git", "worktree", "add", "-q", "--detach", str(baseline), args.baseline],
                       cwd=ROOT, check=True)  # fmt: skip
        try:
            runs = {
                args.baseline: full_run(baseline, Path(scratch) / "baseline"),
                "HEAD": full_run(ROOT, Path(scratch) / "head"),
            }
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(baseline)], cwd=ROOT)
    for name, (seconds, kinds) in runs.items():
        bodies = ", ".join(f"{k} {v:.1f}" for k, v in sorted(kinds.items()))
        print(f"{name}: {seconds:.1f} s; stage bodies {sum(kinds.values()):.1f} s ({bodies})")
    (base, _), (head, _) = runs.values()
    print(f"HEAD / {args.baseline} = {head / base:.3f}")


if __name__ == "__main__":
    main()
