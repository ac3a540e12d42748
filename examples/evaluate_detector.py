"""Evaluate your own detector class in-process on CartPole and place it in the leaderboard.

    python examples/evaluate_detector.py [--size small|full] [--tier mild]

1. `oodrl.check_detector` runs the detector contract on cheap synthetic trajectories (what a
   detector must do to be benchmarked: fit, calibrate, score, stream, pickle).
2. `oodrl.evaluate` fits it on CartPole's clean streams and scores it at the impact tier, with
   the pipeline's own protocol code, seeds, committed policy and tier severities. At
   `--size small` (the default) it takes about a minute on two cores; `--size full` is the
   pipeline's own params, whose numbers equal the pipeline's.
3. Its detection rate is set beside the committed leaderboard's detectors on the same cells.
   (At `small` size the other detectors' numbers are the pipeline's full-size ones: compare
   with the CIs in mind.)
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import oodrl

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
# check_detector builds the detector again in a fresh Python process, which must import its
# module: a plugin installed as a package needs no such line.
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE), os.environ.get("PYTHONPATH")]))
sys.path.insert(0, str(HERE))

from my_detector import MaxAbsZScore  # noqa: E402 - after the path above


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="small", choices=["tiny", "small", "full"])
    parser.add_argument("--tier", default="mild")
    args = parser.parse_args()

    from oodrl.testing import linear_system_trajectories

    data = linear_system_trajectories(12, seed=0)
    oodrl.check_detector(MaxAbsZScore, data[:6], data[6:9], data[9:])
    print("MaxAbsZScore passes the detector contract (oodrl.check_detector)")

    frame = oodrl.evaluate(MaxAbsZScore(), env="cartpole", tiers=[args.tier], size=args.size)
    metric = f"detection_rate@{frame.attrs['k']}"
    cells = frame[frame.metric == metric]
    print(f"\n{metric} at α = {frame.attrs['alpha']} on CartPole ({frame.attrs['size']} size: "
          f"{frame.attrs['n_streams']} faulty streams a cell):")  # fmt: skip
    print(cells[["fault", "severity", "value", "ci_low", "ci_high"]].to_string(index=False))
    cost = frame[frame.metric == "step_us_median"].value.iloc[0]
    print(f"streaming cost: {cost:.1f} µs per step (median, one thread)")

    # The leaderboard leaves out the cells whose tier's verification missed (SPEC §19).
    verified = cells[cells.verified.astype(bool)]
    board = oodrl.load_results(ROOT / "pipeline" / "suite")
    same = board[(board.env == "CartPole-v1") & (board.policy == "0") & (board.tier == args.tier)
                 & (board.metric == metric) & board.fault.isin(verified.fault)]  # fmt: skip
    means = same.groupby("detector").value.mean()
    means["MaxAbsZScore (yours)"] = verified.value.mean()
    print(f"\nmean {metric} over the {len(verified)} verified cells, yours among the "
          "leaderboard's detectors:")  # fmt: skip
    print(means.sort_values(ascending=False).round(3).to_string())


if __name__ == "__main__":
    main()
