"""What pruning a test copy's locks saves (`oodrl.testing.pipeline.prune_locks`).

    python benchmarks/lock_prune.py

The tests' two-environment suite (tests/suite_repo.py) made from HEAD, in two copies: one as the
tests make it (each dvc.lock keeping only the stages its DVC files define), one with the
committed locks put back (entries for every detector and injector the tiny params left out).
Both are built by `dvc repro` of each project in turn, at the same time, so that both see the
same machine; the CPU seconds of each build's processes (user + system) are the figure to read,
the walls are printed beside them.
"""

from __future__ import annotations

import resource
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def build(repo: str) -> tuple[float, float, int]:
    """Wall seconds, CPU seconds of the build's processes, stages that ran."""
    from suite_repo import serial_suite

    start = time.perf_counter()
    ran = serial_suite(Path(repo))
    wall = time.perf_counter() - start
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, used.ru_utime + used.ru_stime, len(ran)


def with_committed_locks(repo: Path, commit: str) -> None:
    from oodrl.testing.pipeline import run

    for lock in sorted(repo.rglob("dvc.lock")):
        path = lock.relative_to(repo).as_posix()
        shown = run(ROOT, "git", "show", f"{commit}:{path}", check=False)
        if shown.returncode == 0:
            lock.write_text(shown.stdout)
    run(repo, "git", "commit", "-q", "-am", "the committed locks")


def main() -> int:
    from suite_repo import head_commit, two_environment_suite

    commit = head_commit(ROOT)
    with tempfile.TemporaryDirectory(prefix="oodrl-lock-prune-") as scratch:
        copies = {}
        for name in ("pruned", "committed"):
            copies[name] = two_environment_suite(ROOT, commit, Path(scratch) / name / "repo")
        with_committed_locks(copies["committed"], commit)
        sizes = {
            name: sum(lock.stat().st_size for lock in repo.rglob("dvc.lock"))
            for name, repo in copies.items()
        }
        with ProcessPoolExecutor(max_workers=2, max_tasks_per_child=1) as pool:  # own rusage
            builds = dict(zip(copies, pool.map(build, map(str, copies.values())), strict=True))
    for name, (wall, cpu, stages) in builds.items():
        print(f"{name:9s} locks {sizes[name] / 1000:5.0f} KB before the build: {stages} stages, "
              f"{cpu:6.1f} CPU s, wall {wall:6.1f} s")  # fmt: skip
    ratio = builds["pruned"][1] / builds["committed"][1]
    print(f"pruned / committed CPU seconds: {ratio:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
