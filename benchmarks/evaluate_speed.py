"""How long the Python API takes (SPEC §25): loading results, and evaluating a PyOD class
in-process on CartPole.

    python benchmarks/evaluate_speed.py [--size small] [--class pyod.models.knn:KNN]
                                        [--check-full mahalanobis_distance]

Each measurement runs in a fresh Python process (imports included, as a notebook's first call
pays them), from the project root:

1. `oodrl.load_results("pipeline/suite")`: the committed leaderboard's cells;
2. `oodrl.load_results("pipeline/cartpole", kind="tiers")`: one pipeline's tier results;
3. `oodrl.evaluate(<class>(), env="cartpole", size=...)` at the mild tier, and where its mean
   detection rate over the verified cells ranks among the leaderboard's CartPole detectors;
4. with --check-full NAME: `oodrl.evaluate` of that built-in detector at size "full" (the
   pipeline's params), its rows compared with the committed tier results
   (reports/tier_results.json, or a protocol-4 pipeline's reports/tier_results.yaml): every
   value, CI and count equal, or the script exits 1.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

LOAD = """
import oodrl
frame = oodrl.load_results({where!r}, kind={kind!r})
print(len(frame))
"""

EVALUATE = """
import importlib, json, oodrl
module, _, name = {path!r}.partition(":")
detector = getattr(importlib.import_module(module), name)()
frame = oodrl.evaluate(detector, env="cartpole", tiers=["mild"], size={size!r})
rates = frame[(frame.metric == "detection_rate@100") & frame.verified.astype(bool)]
board = oodrl.load_results("pipeline/suite")
cells = board[(board.env == "CartPole-v1") & (board.policy == "0") & (board.tier == "mild")
              & (board.metric == "detection_rate@100") & board.fault.isin(rates.fault)]
means = cells.groupby("detector").value.mean()
ours = float(rates.value.mean())
print(json.dumps({{"cells": len(rates), "mean": ours, "rank": int((means > ours).sum()) + 1,
                  "of": len(means) + 1, "streams": frame.attrs["n_streams"]}}))
"""

CHECK_FULL = """
import sys, numpy as np, oodrl
from oodrl.config import load_params
name = {name!r}
detector = load_params("pipeline/cartpole/params.yaml", components=False).detector(name)
ours = oodrl.evaluate(detector, env="cartpole", tiers=["mild"], size="full", name=name)
ours = ours[ours.fault.notna()]
committed = oodrl.load_results("pipeline/cartpole", kind="tiers")
committed = committed[(committed.detector == name) & (committed.tier == "mild")]
keys = ["fault", "tier", "metric"]
both = ours.merge(committed, on=keys, suffixes=("", "_committed"))
assert len(both) == len(ours) == len(committed), (len(both), len(ours), len(committed))
for column in ["value", "ci_low", "ci_high", "n_streams", "severity"]:
    a, b = both[column].to_numpy(float), both[column + "_committed"].to_numpy(float)
    if not ((a == b) | (np.isnan(a) & np.isnan(b))).all():
        sys.exit(f"{{column}} differs from the committed tier results")
print(len(both))
"""


def timed(code: str) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"error: {done.stderr.strip().splitlines()[-1]}")
    return seconds, done.stdout.strip().splitlines()[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="small", choices=["tiny", "small", "full"])
    parser.add_argument("--class", dest="path", default="pyod.models.knn:KNN")
    parser.add_argument("--check-full", metavar="DETECTOR")
    args = parser.parse_args()

    seconds, rows = timed(LOAD.format(where="pipeline/suite", kind=None))
    print(f"load_results('pipeline/suite'): {seconds:.1f} s ({rows} rows)")
    seconds, rows = timed(LOAD.format(where="pipeline/cartpole", kind="tiers"))
    print(f"load_results('pipeline/cartpole', kind='tiers'): {seconds:.1f} s ({rows} rows)")
    seconds, line = timed(EVALUATE.format(path=args.path, size=args.size))
    result = json.loads(line)
    name = args.path.partition(":")[2]
    print(
        f"evaluate({name}(), env='cartpole', size={args.size!r}): {seconds:.1f} s; mild "
        f"detection_rate@100 {result['mean']:.3f} over {result['cells']} verified cells "
        f"({result['streams']} streams each), rank {result['rank']} of {result['of']} beside "
        "the leaderboard's CartPole detectors"
    )
    if args.check_full:
        seconds, rows = timed(CHECK_FULL.format(name=args.check_full))
        print(f"evaluate({args.check_full}, size='full'): {seconds:.1f} s; {rows} rows equal "
              "pipeline/cartpole's committed tier results")  # fmt: skip


if __name__ == "__main__":
    main()
