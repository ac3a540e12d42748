"""A run's provenance (run_meta.yaml): versions, host, stage wall times, params, seeds, policy.

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
from oodrl.fileio import library_versions


def _git_commit() -> str:
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True)
    except OSError:
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 else "unknown"


def _device() -> str:
    return f"cpu ({len(os.sched_getaffinity(0))} cores available)"


def run_meta(params: Params, policy_path: Path, timings_dir: Path) -> dict[str, Any]:
    """Provenance of this run; stage wall times from the records under `timings_dir`."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.protocol import eval_seeds, id_seeds

    timings = {}
    for path in sorted(timings_dir.glob("*.json")):
        record = json.loads(path.read_text())
        timings[record["stage"]] = record["wall_s"]
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
    }
