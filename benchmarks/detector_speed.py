"""Fit time, scoring time per 1,000 steps and pickle size of every detector, one core.

    python benchmarks/detector_speed.py [--data data] [names...]

With --data (a directory the pipeline filled: id.zarr, eval.zarr, ood/, sweep/): fit on the
ID fit split, calibrate on its held-out part, and score every clean, headline and sweep
trajectory, one store per `score_many` call as the score stages do. Without it: synthetic
linear-system trajectories of the default size (24 fit, 6 calibration, 550,000 steps scored).
Detector parameters are the defaults of params.yaml.
"""

from __future__ import annotations

import argparse
import os
import pickle
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/torch, as in every oodrl stage


def pipeline_sets(data: Path):
    from oodrl.io.store import read_sweep, read_trajectories

    id_set = read_trajectories(data / "id.zarr")
    split = id_set.attrs["split"]
    stores = [read_trajectories(data / "eval.zarr")]
    stores += [read_trajectories(p) for p in sorted((data / "ood").glob("*.zarr"))]
    for path in sorted((data / "sweep").glob("*.zarr")):
        stores += list(read_sweep(path).values())
    fit = id_set.subset(split["fit"]).trajectories()
    calibration = id_set.subset(split["calibration"]).trajectories()
    return fit, calibration, [s.trajectories() for s in stores]


def synthetic_sets():
    from oodrl.testing import linear_system_trajectories

    data = linear_system_trajectories(70, seed=0, T=500, state_dim=8, n_actions=4,
                                      episode_length=200)  # fmt: skip
    pool = data[30:]
    scored = [pool[i % len(pool)] for i in range(1100)]
    return data[:24], data[24:30], [scored[i : i + 20] for i in range(0, len(scored), 20)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="the pipeline's data directory")
    parser.add_argument("--params", type=Path, default=Path("params.yaml"))
    parser.add_argument("names", nargs="*")
    args = parser.parse_args()
    from oodrl.config import load_params

    params = load_params(args.params)
    fit, calibration, batches = pipeline_sets(args.data) if args.data else synthetic_sets()
    steps = sum(t.T for batch in batches for t in batch)
    print(f"fit {sum(t.T for t in fit)} steps, score {steps} steps in {len(batches)} calls")
    for name in args.names or params.benchmark.detectors:
        detector = params.detector(name)
        start = time.perf_counter()
        detector.fit(fit).calibrate(calibration)
        fit_s = time.perf_counter() - start
        start = time.perf_counter()
        for batch in batches:
            detector.score_many(batch)
        score_s = time.perf_counter() - start
        size = len(pickle.dumps(detector))
        print(
            f"{name:22s} fit+calibrate {fit_s:6.2f} s   score {1e6 * score_s / steps:6.2f} "
            f"ms per 1k steps ({score_s:5.1f} s)   pickle {size / 1024:7.1f} KiB",
            flush=True,
        )


if __name__ == "__main__":
    main()
