"""Nominal vs achieved clean false-alarm rates of each threshold rule, per detector.

    python benchmarks/false_alarms.py [--env CartPole-v1] [--steps 200] [--calibration 19]

Fit on `--fit` clean streams, calibrate on `--calibration` more, and count alarms on
`--evaluation` further clean streams: the share of steps that alarm and the share of streams
with any alarm. Nominal rates: "percentile" 1 − p/100 per step; "max" (the n-th of n stream
maxima) 1/(n + 1) per stream; "episode_max" α per stream (a bound, reached with equality for
continuous scores only when (n + 1)(1 − α) is an integer).
"""

from __future__ import annotations

import argparse
import copy

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


def main() -> None:
    from oodrl.detectors import DETECTORS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", default=DETECTORS.names())
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--fit", type=int, default=6)
    parser.add_argument("--calibration", type=int, default=19)
    parser.add_argument("--evaluation", type=int, default=40)
    args = parser.parse_args()
    data = clean_streams(args.env, args.fit + args.calibration + args.evaluation, args.steps)
    fit = data[: args.fit]
    calibration = data[args.fit : args.fit + args.calibration]
    evaluation = data[args.fit + args.calibration :]
    print(
        f"{args.env}: {args.fit} fit, {args.calibration} calibration, {args.evaluation} "
        f"evaluation clean streams of {args.steps} steps"
    )
    print(f"{'detector':24} {'rule':12} {'nominal':>16} {'steps alarmed':>14} {'streams':>8}")
    with threadpool_limits(limits=1):
        for name in args.names:
            fitted = DETECTORS.get(name)().fit(fit)
            for rule, params in RULES.items():
                detector = with_rule(fitted, params).calibrate(calibration)
                alarms = [o.alarms for o in detector.score_many(evaluation)]
                per_step = 100 * np.mean(np.concatenate(alarms))
                per_stream = 100 * np.mean([a.any() for a in alarms])
                print(
                    f"{name:24} {rule:12} {nominal(rule, args.calibration):>16} "
                    f"{per_step:13.2f}% {per_stream:7.1f}%",
                    flush=True,
                )


if __name__ == "__main__":
    main()
