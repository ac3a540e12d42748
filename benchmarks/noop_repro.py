"""A no-op `dvc repro` of a built project against DVC's own floor: `dvc status` of an empty
DVC repository, timed in the same run.

    python benchmarks/noop_repro.py [--project .] [--runs 5]

The project must be built (every output in its workspace): a repro that runs a stage is
refused. The two commands alternate, `runs` times each, so both see the same machine; the
medians and their ratio are printed (#61's goal: the no-op at most 3× the empty status).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from oodrl.testing.pipeline import run

ROOT = Path(__file__).resolve().parents[1]


def timed(repo: Path, *args: str) -> tuple[float, str]:
    start = time.perf_counter()
    done = run(repo, *args)
    return time.perf_counter() - start, done.stdout


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--project", type=Path, default=ROOT, help="a built DVC project")
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    noop, empty_status = [], []
    with tempfile.TemporaryDirectory(prefix="oodrl-empty-dvc-") as empty:
        run(Path(empty), "git", "init", "-q")
        run(Path(empty), "dvc", "init", "-q")
        for _ in range(args.runs):
            seconds, output = timed(args.project, "dvc", "repro")
            if "Running stage" in output:
                sys.exit(f"error: {args.project} was not built: `dvc repro` ran stages")
            noop.append(seconds)
            empty_status.append(timed(Path(empty), "dvc", "status")[0])
    a, b = statistics.median(noop), statistics.median(empty_status)
    print(f"no-op `dvc repro` of {args.project}: median {a:.2f} s of {args.runs} "
          f"({', '.join(f'{s:.2f}' for s in noop)})")  # fmt: skip
    print(f"`dvc status` of an empty DVC repository: median {b:.2f} s "
          f"({', '.join(f'{s:.2f}' for s in empty_status)})")  # fmt: skip
    print(f"ratio: {a / b:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
