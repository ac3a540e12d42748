"""Nominal vs achieved clean false-alarm rates of each threshold rule, per detector.

    python benchmarks/false_alarms.py [--env CartPole-v1] [--steps 200] [--calibration 19]
    python benchmarks/false_alarms.py --pipeline . [--alpha 0.15]

Fit on `--fit` clean streams, calibrate on `--calibration` more, and count alarms on
`--evaluation` further clean streams: the share of steps that alarm and the share of streams
with any alarm. With `--pipeline DIR`, use a built pipeline's own sets instead: its fitted
detectors, recalibrated under each rule on its held-out ID episodes, counted on its clean
evaluation set (data/eval.zarr). Nominal rates: "percentile" 1 − p/100 per step; "max" (the
n-th of n stream maxima) 1/(n + 1) per stream; "episode_max" α per stream (a bound, reached
with equality for continuous scores only when (n + 1)(1 − α) is an integer).
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import numpy as np
from detector_cost import clean_streams
from threadpoolctl import threadpool_limits

RULES = {
    "percentile": {"threshold_rule": "percentile", "threshold_percentile": 99.0},
    "max": {"threshold_rule": "max"},
    "episode_max": {"threshold_rule": "episode_max", "alpha": 0.1},
}


def nominal(rule: str, n: int) -> str:
    if rule == "percentile":
        return "1.0% / step"
    if rule == "max":
        return f"{100 / (n + 1):.1f}% / stream"
    return f"{100 * RULES[rule]['alpha']:.1f}% / stream"


def with_rule(fitted, params: dict):
    """A copy of a fitted detector with other threshold parameters (they do not affect fit)."""
    detector = copy.deepcopy(fitted)
    for key, value in params.items():
        setattr(detector, key, value)
    return detector


def pipeline_sets(pipeline: Path) -> tuple[dict, list, list]:
    """A built pipeline's fitted detectors, held-out ID (calibration) and clean evaluation sets."""
    from oodrl.config import load_params
    from oodrl.io.store import load_detector, read_trajectories

    params = load_params(pipeline / "params.yaml")
    id_set = read_trajectories(pipeline / "data/id.zarr")
    calibration = id_set.subset(id_set.attrs["split"]["calibration"]).trajectories()
    evaluation = read_trajectories(pipeline / "data/eval.zarr").trajectories()
    fitted = {
        name: load_detector(pipeline / f"models/detectors/{name}.pkl", stage=None)
        for name in params.benchmark.detectors
    }
    return fitted, calibration, evaluation


def main() -> None:
    from oodrl.detectors import DETECTORS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", default=DETECTORS.names())
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--fit", type=int, default=6)
    parser.add_argument("--calibration", type=int, default=19)
    parser.add_argument("--evaluation", type=int, default=40)
    parser.add_argument("--pipeline", type=Path, help="a built pipeline's directory")
    parser.add_argument("--alpha", type=float, default=0.1, help="episode_max's α")
    args = parser.parse_args()
    RULES["episode_max"]["alpha"] = args.alpha
    if args.pipeline:
        fitted_by_name, calibration, evaluation = pipeline_sets(args.pipeline)
        print(f"{args.pipeline}: {len(calibration)} held-out ID (calibration) and "
              f"{len(evaluation)} clean evaluation streams of {evaluation[0].T} steps")  # fmt: skip
    else:
        data = clean_streams(args.env, args.fit + args.calibration + args.evaluation, args.steps)
        fit = data[: args.fit]
        calibration = data[args.fit : args.fit + args.calibration]
        evaluation = data[args.fit + args.calibration :]
        fitted_by_name = {name: None for name in args.names}
        print(
            f"{args.env}: {args.fit} fit, {args.calibration} calibration, {args.evaluation} "
            f"evaluation clean streams of {args.steps} steps"
        )
    print(f"{'detector':24} {'rule':12} {'nominal':>16} {'steps alarmed':>14} {'streams':>8}")
    with threadpool_limits(limits=1):
        for name, fitted in fitted_by_name.items():
            fitted = fitted or DETECTORS.get(name)().fit(fit)
            for rule, params in RULES.items():
                detector = with_rule(fitted, params).calibrate(calibration)
                alarms = [o.alarms for o in detector.score_many(evaluation)]
                per_step = 100 * np.mean(np.concatenate(alarms))
                per_stream = 100 * np.mean([a.any() for a in alarms])
                print(
                    f"{name:24} {rule:12} {nominal(rule, len(calibration)):>16} "
                    f"{per_step:13.2f}% {per_stream:7.1f}%",
                    flush=True,
                )


if __name__ == "__main__":
    main()
