"""A run's provenance (run_meta.yaml): versions, host, stage wall times, params, seeds, policy,
and each detector's cost (fit time, fitted size, streaming latency).

Not a DVC output: it holds timings and host facts by design.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from oodrl.config import Params
from oodrl.io.fileio import library_versions


def _git_commit() -> str:
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True)
    except OSError:
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 else "unknown"


def _device() -> str:
    return f"cpu ({len(os.sched_getaffinity(0))} cores available)"


def timing_records(timings_dir: Path) -> list[dict[str, Any]]:
    """The records `timed_stage` wrote under `timings_dir`, one per stage, by file name."""
    return [json.loads(path.read_text()) for path in sorted(timings_dir.glob("*.json"))]


def fit_seconds(records: list[dict[str, Any]]) -> dict[str, float]:
    """detector -> seconds its last fit stage spent in fit and calibrate."""
    return {r["detector"]: r["fit_s"] for r in records if "fit_s" in r}


def run_meta(
    params: Params,
    policy_path: Path,
    records: list[dict[str, Any]],
    cost: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """Provenance of this run: stage wall times from the `timing_records`, and each detector's
    `cost` (fit time, fitted size, µs per streamed step) beside its accuracy in results.yaml."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.protocol.streams import eval_seeds, id_seeds

    timings = {record["stage"]: record["wall_s"] for record in records}
    return {
        "oodrl_version": library_versions()["oodrl"],
        "git_commit": _git_commit(),
        "versions": library_versions(),
        "platform": platform.platform(),
        "device": _device(),
        "stage_wall_s": timings,
        "total_stage_wall_s": round(sum(timings.values()), 3),
        "params": params.model_dump(mode="json"),
        "seeds": {"id": id_seeds(params), "eval": eval_seeds(params)},
        "env": {"id": params.env.id, "version": ENVIRONMENTS.get(params.env.id).version()},
        "policy_sha256": hashlib.sha256(Path(policy_path).read_bytes()).hexdigest(),
        "cost": cost,
    }


def write_run_meta(
    params: Params, policy_path: Path, models_dir: Path, eval_path: Path, timings_dir: Path,
    meta_path: Path,
) -> None:  # fmt: skip
    """run_meta.yaml: provenance, stage timings, and every benchmark detector's cost (§13)."""
    from oodrl.io import yamlio
    from oodrl.io.fileio import atomic_write_text
    from oodrl.io.store import read_trajectories
    from oodrl.metrics.cost import detector_costs

    records = timing_records(timings_dir)
    models = {name: models_dir / f"{name}.pkl" for name in params.benchmark.detectors}
    clean = read_trajectories(eval_path, stage="collect_eval").trajectories()
    cost = detector_costs(models, clean, fit_seconds(records))
    atomic_write_text(meta_path, yamlio.dump(run_meta(params, policy_path, records, cost)))
