"""What resuming stateful detectors at the onset would save: the profile #61 asks for first.

    python benchmarks/stateful_prefix.py [--project pipeline/pendulum] [--json OUT]

A `row_independent` detector already scores a faulty stream only from its first step that
differs from its seed's first stream (`oodrl.protocol.scoring.SharedPrefixes`); the others
(recursive state, windows) score every stream in full. Resumed from a snapshot of its state at
that step, such a detector would still score each stream's suffix. In a built project (every
scoring stage's inputs in the workspace), for each detector that is not row-independent and each
injector, this times the scoring its `score` and `score_variants` stages do (headline set, sweep
and tier streams, every stream in full, as they do) and the scoring of the suffixes alone (the
cost a resumed detector would keep; its scores are not the real ones and are thrown away).
Store reads and process start-up are left out of both: they stay. The saving is at most the
difference, before the cost of taking and restoring the snapshots. Prints it per detector and
in all, against the seconds inside all of the project's stage commands from its last build
(`.oodrl/timings`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from oodrl.config import load_params
from oodrl.io.store import load_detector, read_sweep, read_tier_sets, read_trajectories
from oodrl.protocol.scoring import SharedPrefixes, _steps_from


def injector_sets(project: Path, injector: str) -> list:
    """The trajectory sets a detector's `score` and `score_variants` stages read for `injector`,
    in the order they score them."""
    sets = []
    headline = project / "data" / "ood" / f"{injector}.zarr"
    if headline.exists():
        sets.append(read_trajectories(headline))
    sweep = project / "data" / "sweep" / f"{injector}.zarr"
    if sweep.exists():
        sets += list(read_sweep(sweep).values())
    tiers = project / "data" / "tiers" / f"{injector}.zarr"
    if tiers.exists():
        sets += list(read_tier_sets(tiers)[0].values())
    return sets


def suffixes_after_shared_prefixes(lists: list[list]) -> list[list]:
    """Each stream's steps from the first one that differs from its seed's first stream, found
    by the stages' own `SharedPrefixes` (fed zeros for scores: only the steps matter here)."""
    shared, cut = SharedPrefixes(), []
    for trajectories in lists:
        kept = []
        for trajectory in trajectories:
            start = shared.first_new_step(trajectory)
            shared.joined(trajectory, start, np.zeros(max(trajectory.T - start, 0)))
            if (suffix := _steps_from(trajectory, start)) is not None:
                kept.append(suffix)
        cut.append(kept)
    return cut


def timed_scoring(detector, trajectory_lists: list[list]) -> float:
    start = time.perf_counter()
    for trajectories in trajectory_lists:
        if trajectories:
            detector.score_many(trajectories)
    return time.perf_counter() - start


def profile(project: Path) -> dict:
    params = load_params(project / "params.yaml")
    injectors = list(params.benchmark.injectors)
    streams = {name: [s.trajectories() for s in injector_sets(project, name)] for name in injectors}
    suffixes = {name: suffixes_after_shared_prefixes(lists) for name, lists in streams.items()}
    steps = sum(t.T for lists in streams.values() for ts in lists for t in ts)
    suffix_steps = sum(t.T for lists in suffixes.values() for ts in lists for t in ts)
    rows = []
    for name in params.benchmark.detectors:
        detector = load_detector(project / "models" / "detectors" / f"{name}.pkl", stage=None)
        if detector.row_independent:
            continue
        full = sum(timed_scoring(detector, streams[i]) for i in injectors)
        resumed = sum(timed_scoring(detector, suffixes[i]) for i in injectors)
        rows.append({"detector": name, "full_s": full, "suffixes_s": resumed})
        print(f"{name}: full streams {full:.2f} s, suffixes {resumed:.2f} s, at most "
              f"{full - resumed:.2f} s saved", flush=True)  # fmt: skip
    timings = [json.loads(p.read_text()) for p in (project / ".oodrl" / "timings").glob("*.json")]
    in_stages = sum(t["wall_s"] for t in timings)
    saved = sum(r["full_s"] - r["suffixes_s"] for r in rows)
    print(f"{len(rows)} detectors not row-independent; {steps} stream-steps scored each, "
          f"{suffix_steps} of them after the shared prefixes ({suffix_steps / steps:.0%}); at most "
          f"{saved:.1f} s saved, against {in_stages:.1f} s inside the project's stage commands "
          f"({saved / in_stages:.1%})")  # fmt: skip
    return {"rows": rows, "steps": steps, "suffix_steps": suffix_steps,
            "in_stages_s": in_stages, "saved_s": saved}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--project", type=Path, default=Path("pipeline/pendulum"))
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    figures = profile(args.project)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
