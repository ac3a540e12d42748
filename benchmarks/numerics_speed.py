"""Old vs new machine-independent detector arithmetic, timed in the same run (ratios new/old).

Both versions are exported from git (``git archive``, nothing in the checkout changes) and run
in fresh interpreters with ``PYTHONPATH`` pointing at their ``src``, alternating old and new
so that load on the machine hits both alike; each workload reports the best of ``--repeats``
and whether the two versions' outputs are the same bytes. Workloads, on the data of the
checkout (``data/``, ``models/detectors/``):

- ``kde_score``, ``time_series_score``, ``pedm_score``, ``ensemble_score``: a fitted
  detector's ``score_many`` on the gaussian_state_noise headline set and every sweep severity
  (what ``oodrl score <det> --injector gaussian_state_noise …`` computes, without the I/O);
- ``pedm_fit``: ``pedm`` fitted on the ID fit split with the checkout's params (what
  ``oodrl fit pedm`` computes);
- ``linear``: ``numerics.linear`` on the shapes of one pedm training step, repeated.

``--cli`` times the whole commands instead (interpreter start, imports, reading and writing
stores; where a revision's CLI scores the headline set and the sweep in separate commands,
the two are timed together). Example::

    python benchmarks/numerics_speed.py --base 83c1784 --new HEAD --repeats 3
    python benchmarks/numerics_speed.py --base 83c1784 --new HEAD --cli \
        --only src/oodrl/numerics.py src/oodrl/detectors/kde.py src/oodrl/detectors/mlp.py

``OPENBLAS_NUM_THREADS`` defaults to 1 (set it to compare multi-threaded BLAS): on a shared,
loaded machine a second BLAS thread mostly waits for a core.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
INJECTOR = "gaussian_state_noise"

#: Runs one workload in the interpreter it is given; prints {"seconds", "digest"} as JSON.
DRIVER = r"""
import hashlib, json, pickle, sys, time
from pathlib import Path
import numpy as np

root, workload = Path(sys.argv[1]), sys.argv[2]
injector = "gaussian_state_noise"


def score_sets():
    from oodrl.io.store import read_sweep, read_trajectories

    headline = read_trajectories(root / f"data/ood/{injector}.zarr", stage="benchmark")
    sweep = read_sweep(root / f"data/sweep/{injector}.zarr", stage="benchmark")
    return [headline.trajectories()] + [s.trajectories() for s in sweep.values()]


def fit_set():
    from oodrl.io.store import read_trajectories

    ids = read_trajectories(root / "data/id.zarr", stage="benchmark")
    return ids.subset(ids.attrs["split"]["fit"]).trajectories()


def run():
    if workload.endswith("_score"):
        from oodrl.io.store import load_detector

        name = {"kde": "kde_density", "time_series": "time_series_features", "pedm": "pedm",
                "ensemble": "ensemble_disagreement"}[workload[: -len("_score")]]
        detector = load_detector(root / f"models/detectors/{name}.pkl", stage="benchmark")
        sets = score_sets()
        start = time.perf_counter()
        scores = [np.stack([o.scores for o in detector.score_many(s)]) for s in sets]
        return time.perf_counter() - start, b"".join(s.tobytes() for s in scores)
    if workload == "pedm_fit":
        import yaml
        from oodrl.detectors import DETECTORS

        params = yaml.safe_load((root / "params.yaml").read_text())["detectors"]["pedm"]
        params = {k: v for k, v in params.items() if not k.startswith("threshold")}
        trajectories = fit_set()
        start = time.perf_counter()
        detector = DETECTORS.get("pedm")(**params).fit(trajectories)
        return time.perf_counter() - start, pickle.dumps(detector.weights_)
    if workload == "linear":
        from oodrl import numerics

        rng = np.random.default_rng(0)
        f32 = lambda *shape: rng.standard_normal(shape).astype(np.float32)
        relu = lambda *shape: np.maximum(f32(*shape), 0)
        M, B, n_in, h, n_out = 5, 256, 12, 64, 16
        calls = [
            (f32(M, B, n_in), f32(M, h, n_in), f32(M, 1, h)),
            (relu(M, B, h), f32(M, h, h), f32(M, 1, h)),
            (relu(M, B, h), f32(M, n_out, h), f32(M, 1, n_out)),
            (f32(M, n_out, B) * 1e-3, np.swapaxes(relu(M, B, h), -1, -2), None),
            (np.ones((1, B), np.float32), f32(M, n_out, B) * 1e-3, None),
            (f32(M, B, n_out) * 1e-3, np.swapaxes(f32(M, n_out, h), -1, -2), None),
            (f32(M, h, B) * 1e-3, np.swapaxes(relu(M, B, h), -1, -2), None),
            (np.ones((1, B), np.float32), f32(M, h, B) * 1e-3, None),
            (f32(M, B, h) * 1e-3, np.swapaxes(f32(M, h, h), -1, -2), None),
            (f32(M, h, B) * 1e-3, np.swapaxes(f32(M, B, n_in), -1, -2), None),
            (np.ones((1, B), np.float32), f32(M, h, B) * 1e-3, None),
        ]
        start = time.perf_counter()
        for _ in range(100):
            outputs = [numerics.linear(*call) for call in calls]
        return time.perf_counter() - start, b"".join(o.tobytes() for o in outputs)
    raise SystemExit(f"unknown workload {workload}")


seconds, output = run()
print(json.dumps({"seconds": seconds, "digest": hashlib.sha256(output).hexdigest()}))
"""

WORKLOADS = ("kde_score", "time_series_score", "pedm_score", "ensemble_score", "pedm_fit", "linear")

#: The commands timed by --cli (verb, detector), as in the profile that motivated this work.
CLI = {
    "kde_score": ["score", "kde_density"],
    "time_series_score": ["score", "time_series_features"],
    "pedm_score": ["score", "pedm"],
    "ensemble_score": ["score", "ensemble_disagreement"],
    "pedm_fit": ["fit", "pedm"],
}


def export(revision: str, into: Path) -> Path:
    """``src/`` of a git revision under ``into`` (or the working tree's for "worktree")."""
    if revision == "worktree":
        return ROOT / "src"
    archive = subprocess.run(
        ["git", "archive", revision, "src"], cwd=ROOT, capture_output=True, check=True
    ).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(into, filter="data")
    return into / "src"


def run_once(src: Path, workload: str, cli: bool, scratch: Path) -> tuple[float, str]:
    env = {**os.environ, "PYTHONPATH": str(src)}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    if not cli:
        done = subprocess.run(
            [sys.executable, "-c", DRIVER, str(ROOT), workload],
            cwd=scratch, env=env, capture_output=True, text=True, check=False,
        )  # fmt: skip
        if done.returncode != 0:
            raise RuntimeError(f"{workload} under {src} failed:\n{done.stderr[-3000:]}")
        result = json.loads(done.stdout.strip().splitlines()[-1])
        return result["seconds"], result["digest"]
    verb, name = CLI[workload]
    model = f"models/detectors/{name}.pkl"
    if verb == "fit":
        commands = [["fit", name, "--id", "data/id.zarr", "--out", str(scratch / "fit.pkl")]]
    else:
        ood, sweep = f"data/ood/{INJECTOR}.zarr", f"data/sweep/{INJECTOR}.zarr"
        score = ["score", name, "--injector", INJECTOR, "--model", model]
        commands = [[*score, "--ood", ood, "--sweep", sweep, "--out", str(scratch / "s.zarr")]]
        if not _takes_ood_and_sweep_together(src):
            # Later CLIs score the headline set and the sweep in two commands (two stages).
            commands = [
                [*score, "--ood", ood, "--out", str(scratch / "headline.zarr")],
                [*score, "--sweep", sweep, "--out", str(scratch / "sweep.zarr")],
            ]
    seconds = 0.0
    for command in commands:
        start = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "oodrl", *command],
            cwd=ROOT, env=env, capture_output=True, text=True, check=False,
        )  # fmt: skip
        seconds += time.perf_counter() - start
        if done.returncode != 0:
            raise RuntimeError(f"oodrl {' '.join(command)} under {src} failed:\n{done.stderr}")
    return seconds, "-"


def _takes_ood_and_sweep_together(src: Path) -> bool:
    """Whether this revision's ``oodrl score`` scores --ood and --sweep in one command."""
    return "exactly one of --eval" not in (src / "oodrl" / "cli.py").read_text()


def revisions_parser(description: str) -> argparse.ArgumentParser:
    """The arguments of a benchmark that times two revisions alternately (see `export`)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--base", required=True, help="old revision (git)")
    parser.add_argument("--new", default="worktree", help="new revision, or 'worktree'")
    parser.add_argument("--repeats", type=int, default=3)
    return parser


def main() -> None:
    parser = revisions_parser(__doc__.split("\n")[0])
    parser.add_argument("--cli", action="store_true", help="time the whole oodrl commands")
    parser.add_argument(
        "--only", nargs="+", metavar="PATH", help="new = base with only these src/ files from --new"
    )
    parser.add_argument("workloads", nargs="*", default=None, help=f"of {', '.join(WORKLOADS)}")
    options = parser.parse_args()
    workloads = options.workloads or (list(CLI) if options.cli else list(WORKLOADS))
    with tempfile.TemporaryDirectory() as temporary:
        scratch = Path(temporary)
        trees = {
            "old": export(options.base, scratch / "old"),
            "new": export(options.new, scratch / "new"),
        }
        if options.only:
            # The base tree with only these files from the new revision: isolates them from
            # whatever else changed between the revisions (a CLI's commands, say).
            mixed = export(options.base, scratch / "mixed")
            for path in options.only:
                relative = Path(path).relative_to("src")
                (mixed / relative).write_bytes((trees["new"] / relative).read_bytes())
            trees["new"] = mixed
        only = f" (only {', '.join(options.only)})" if options.only else ""
        print(f"old = {options.base}, new = {options.new}{only}, best of {options.repeats}")
        print(f"{'workload':<20} {'old s':>8} {'new s':>8} {'new/old':>8}  outputs")
        for workload in workloads:
            times: dict[str, list[float]] = {"old": [], "new": []}
            digests: dict[str, str] = {}
            for _ in range(options.repeats):
                for version, src in trees.items():
                    seconds, digest = run_once(src, workload, options.cli, scratch)
                    times[version].append(seconds)
                    digests[version] = digest
            old, new = min(times["old"]), min(times["new"])
            same = (
                "-" if options.cli else ("same" if digests["old"] == digests["new"] else "differ")
            )
            print(f"{workload:<20} {old:8.3f} {new:8.3f} {new / old:8.2f}  {same}", flush=True)


if __name__ == "__main__":
    main()
