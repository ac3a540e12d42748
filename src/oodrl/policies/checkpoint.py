"""oodrl's policy checkpoint and its evaluation report: the one writer both trainers use.

A checkpoint is a torch file (loaded with ``weights_only=True``) holding
``{"format": "oodrl-policy", "version": 1, "architecture": {...}, "state_dict": {...}, ...}``;
the report beside it (``policy.json``) holds the held-out evaluation, the training settings, the
learning curve and the versions (SPEC §11).
"""

from __future__ import annotations

import io
import json
import platform
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from oodrl.io.fileio import atomic_write_bytes, library_versions

CHECKPOINT_FORMAT = "oodrl-policy"
CHECKPOINT_VERSION = 1
REPORT_LIBRARIES = ("numpy", "torch", "gymnasium", "stable-baselines3")


def save_policy(
    policy_path: Path,
    report_path: Path,
    *,
    architecture: Mapping[str, Any],
    state_dict: Mapping[str, torch.Tensor],
    env_id: str,
    train_config: Mapping[str, Any],
    final_returns: np.ndarray,
    final_eval_seed: int,
    tuning: Mapping[str, Any],
    steps_run: int,
    learning_curve: Sequence[Sequence[float]],
    wall_time_s: float,
    trainer: Mapping[str, str],
) -> dict[str, Any]:
    """Write the checkpoint and its report atomically; return the report."""
    versions = library_versions(REPORT_LIBRARIES)
    checkpoint = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "architecture": dict(architecture),
        "env_id": env_id,
        "train_config": dict(train_config),
        "best_step": int(tuning["best_step"]),
        "versions": versions,
        "state_dict": {k: v.detach().clone().contiguous() for k, v in state_dict.items()},
    }
    buffer = io.BytesIO()  # a buffer keeps the zip's inner folder name fixed, whatever the path
    torch.save(checkpoint, buffer)
    atomic_write_bytes(policy_path, buffer.getvalue())
    returns = np.asarray(final_returns, dtype=np.float64)
    report = {
        "env_id": env_id,
        "architecture": dict(architecture),
        "trainer": dict(trainer),
        "train_config": dict(train_config),
        "evaluation": {
            "mode": "greedy",
            "episodes": len(returns),
            "seeds": [final_eval_seed + i for i in range(len(returns))],
            "returns": [float(r) for r in returns],
            "mean": float(returns.mean()),
            "std": float(returns.std()),
            "min": float(returns.min()),
            "max": float(returns.max()),
        },
        "tuning_evaluation": dict(tuning),
        "best_step": int(tuning["best_step"]),
        "steps_run": int(steps_run),
        "learning_curve": [[int(s), float(m)] for s, m in learning_curve],
        "wall_time_s": round(float(wall_time_s), 1),
        "versions": versions,
        "platform": platform.platform(),
    }
    text = json.dumps(report, indent=2, sort_keys=True) + "\n"
    atomic_write_bytes(report_path, text.encode())
    return report
