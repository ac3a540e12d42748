"""Collection stages: clean ID, evaluation and calibration sets, perturbed headline and sweep
sets (the tier sets: `oodrl.stages.impact`).

What each set holds (seeds, split, anomalies) is the protocol's: `oodrl.protocol.streams`.
"""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params
from oodrl.io.store import write_sweep, write_trajectories
from oodrl.protocol import streams


def collect_id(params: Params, policy_path: Path, out: Path) -> None:
    write_trajectories(out, streams.id_set(params, policy_path))


def collect_eval(params: Params, policy_path: Path, out: Path) -> None:
    write_trajectories(out, streams.eval_set(params, policy_path))


def collect_ood(
    params: Params, injector_name: str, policy_path: Path, eval_path: Path, out: Path
) -> None:
    severity = params.injector_severity(injector_name)
    (tset,) = streams.perturbed_sets(params, injector_name, [severity], policy_path, eval_path)
    write_trajectories(out, tset)


def collect_sweep(
    params: Params, injector_name: str, policy_path: Path, eval_path: Path, out: Path
) -> None:
    grid = params.anomaly.sweep
    sets = streams.perturbed_sets(params, injector_name, grid, policy_path, eval_path)
    write_sweep(out, dict(zip(grid, sets, strict=True)),
                {"injector": injector_name, "mode": sets[0].attrs.get("mode")})  # fmt: skip


def collect_heldout(params: Params, which: str, policy_path: Path, out: Path) -> None:
    """Stages collect_calibration, collect_audit, collect_twins
    (`oodrl.protocol.streams.heldout_set`)."""
    write_trajectories(out, streams.heldout_set(params, which, policy_path))
