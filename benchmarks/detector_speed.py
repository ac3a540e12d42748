"""Fit and scoring time of every registered detector at the default benchmark size (one core).

Run:  python benchmarks/detector_speed.py [names...]
(BENCH_DATA=file.pkl: use a pickled list of >= 70 trajectories instead of the synthetic ones.)
Fit on 24 trajectories × T=500 (d_s=8, 4 actions), calibrate on 6, score 550,000 steps in
score_many calls of 20 trajectories (10,000 steps) each, as the pipeline scores one store.
"""

from __future__ import annotations

import os
import pickle
import sys
import time

import torch
from threadpoolctl import threadpool_limits

from oodrl.detectors import DETECTORS
from oodrl.testing import linear_system_trajectories

torch.set_num_threads(1)
threadpool_limits(1)

SHAPE = dict(T=500, state_dim=8, n_actions=4, episode_length=200)


def main(names: list[str]) -> None:
    source = os.environ.get("BENCH_DATA")  # a pickled list of >= 70 Trajectory objects
    if source:
        with open(source, "rb") as f:
            data = pickle.load(f)
    else:
        data = linear_system_trajectories(70, seed=0, **SHAPE)
    fit, calibration, pool = data[:24], data[24:30], data[30:]
    scored = [pool[i % len(pool)] for i in range(1100)]
    for name in names or DETECTORS.names():
        cls = DETECTORS.get(name)
        detector = cls(device="cpu") if cls.uses_torch else cls()
        start = time.perf_counter()
        detector.fit(fit)
        fit_s = time.perf_counter() - start
        detector.calibrate(calibration)
        start = time.perf_counter()
        for i in range(0, len(scored), 20):
            detector.score_many(scored[i : i + 20])
        score_s = time.perf_counter() - start
        steps = sum(t.T for t in scored)
        print(
            f"{name:24s} fit {fit_s:6.2f} s   score {score_s:6.2f} s / {steps} steps "
            f"= {1000 * score_s / steps * 1000:6.2f} ms per 1k steps",
            flush=True,
        )


if __name__ == "__main__":
    main(sys.argv[1:])
