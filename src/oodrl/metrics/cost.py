"""Cost beside accuracy (SPEC §13): a fitted detector's size and its streaming latency per step.

Latency is the wall time of each `stream().update` (a stream's `flush` added to its last step),
one thread, over whole clean streams of at least `MIN_STEPS` steps. The render stage measures
every benchmark detector into run_meta.yaml, never into a DVC output: timings differ between
runs and machines (SPEC §14). `benchmarks/detector_cost.py` measures detectors fitted ad hoc.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from threadpoolctl import threadpool_limits

if TYPE_CHECKING:
    from oodrl.core.detector import BaseDetector
    from oodrl.core.trajectory import Trajectory

#: Steps timed per detector: enough that the p99 is set by the 10 slowest steps, not one.
MIN_STEPS = 1000
#: Untimed updates first, so that first-call costs (lazy imports, caches) are not a step's.
WARMUP_STEPS = 20


def timed_streams(
    trajectories: Sequence[Trajectory], min_steps: int = MIN_STEPS
) -> list[Trajectory]:
    """The first whole trajectories that hold `min_steps` steps (all of them if fewer do)."""
    chosen, steps = [], 0
    for trajectory in trajectories:
        if steps >= min_steps:
            break
        chosen.append(trajectory)
        steps += trajectory.T
    return chosen


def _steps(trajectory: Trajectory) -> Iterator[tuple[Any, ...]]:
    for t in range(trajectory.T):
        yield (
            trajectory.states[t],
            trajectory.actions[t],
            trajectory.rewards[t],
            trajectory.next_states[t],
            trajectory.dones[t],
        )


def stream_latencies_ns(
    detector: BaseDetector, trajectories: Sequence[Trajectory], warmup_steps: int = WARMUP_STEPS
) -> np.ndarray:
    """Nanoseconds of each step's `update`, one stream per trajectory, its `flush` added to its
    last step; after `warmup_steps` untimed updates of the first trajectory."""
    stream = detector.stream()
    for _, step in zip(range(warmup_steps), _steps(trajectories[0]), strict=False):
        stream.update(*step)
    stream.flush()
    latencies = []
    for trajectory in trajectories:
        for t, step in enumerate(_steps(trajectory)):
            start = time.perf_counter_ns()
            stream.update(*step)
            if t == trajectory.T - 1:
                stream.flush()
            latencies.append(time.perf_counter_ns() - start)
    return np.array(latencies, dtype=np.int64)


def step_latency_us(detector: BaseDetector, trajectories: Sequence[Trajectory]) -> dict[str, float]:
    """Median and p99 µs per streamed step, one thread (`step_us_median`, `step_us_p99`)."""
    with threadpool_limits(limits=1):
        latencies = stream_latencies_ns(detector, trajectories)
    median, p99 = np.percentile(latencies, [50, 99]) / 1e3
    return {"step_us_median": round(float(median), 1), "step_us_p99": round(float(p99), 1)}


def detector_costs(
    models: Mapping[str, Path],
    trajectories: Sequence[Trajectory],
    fit_seconds: Mapping[str, float],
) -> dict[str, dict[str, Any]]:
    """detector -> {fit_s, fitted_bytes, step_us_median, step_us_p99} for each pickle written by
    `oodrl fit` in `models` (name -> path); `fit_s` is None where `fit_seconds` lacks it."""
    from oodrl.io.layout import detector_stage
    from oodrl.io.store import load_detector

    streams = timed_streams(trajectories)
    costs = {}
    for name, path in models.items():
        detector = load_detector(Path(path), stage=detector_stage(name, "fit"))
        costs[name] = {
            "fit_s": fit_seconds.get(name),
            "fitted_bytes": Path(path).stat().st_size,
            **step_latency_us(detector, streams),
        }
    return costs
