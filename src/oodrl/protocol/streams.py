"""The benchmark protocol as params fix it (SPEC §1-§3): the seeds of the clean sets, the
fit/calibration split of the ID set, and the trajectory sets the collection stages write.

ID streams use seeds `seed + i`; evaluation streams `seed + eval_seed_offset + j`, so the two
never share a seed. Every perturbed set re-uses the evaluation seeds: its episodes are the
matched counterparts of the clean evaluation set's. The clean calibration streams of the
per-stream alarm rule (SPEC §15) use `seed + tiers.calibration_seed_offset + j`, the audit
streams (SPEC §19) `seed + tiers.audit_seed_offset + j`; the tier cells' streams and their clean
twins are the first `tiers.n_streams` evaluation seeds; impact calibration has seed ranges of
its own (`oodrl.protocol.impact`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from oodrl.config import Params
from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.injector import OnlineInjector
from oodrl.core.policy import Policy
from oodrl.core.trajectory import TrajectorySet
from oodrl.envs import ENVIRONMENTS
from oodrl.io.store import read_trajectories
from oodrl.progress import progress_bar


def id_seeds(params: Params) -> list[int]:
    return [params.seed + i for i in range(params.data.n_id)]


def eval_seeds(params: Params) -> list[int]:
    return [params.seed + params.data.eval_seed_offset + j for j in range(params.data.n_ood)]


def calibration_seeds(params: Params) -> list[int]:
    offset = params.seed + params.tiers.calibration_seed_offset
    return [offset + j for j in range(params.tiers.n_calibration)]


def audit_seeds(params: Params) -> list[int]:
    offset = params.seed + params.tiers.audit_seed_offset
    return [offset + j for j in range(params.tiers.n_audit)]


def twin_seeds(params: Params) -> list[int]:
    """The evaluation seeds of the tier cells' `tiers.n_streams` streams (the first
    `data.n_ood` of them are the clean evaluation set's)."""
    offset = params.seed + params.data.eval_seed_offset
    return [offset + j for j in range(params.tiers.n_streams)]


#: The held-out clean sets of the tiers (SPEC §19), each on seeds of its own: the per-stream
#: alarm rule's calibration streams, the audit streams that measure its achieved false-alarm
#: rate (used for nothing else), and the clean twins of the tier cells' faulty streams.
HELDOUT_SETS = {"calibration": calibration_seeds, "audit": audit_seeds, "twins": twin_seeds}


def fit_calibration_split(params: Params) -> tuple[list[int], list[int]]:
    """Trajectory indices of the fit and calibration parts: a seeded split by trajectory."""
    order = np.random.default_rng(params.seed).permutation(params.data.n_id)
    n_cal = params.data.n_calibration
    return sorted(order[n_cal:].tolist()), sorted(order[:n_cal].tolist())


def _adapter(params: Params) -> EnvironmentAdapter:
    return ENVIRONMENTS.get(params.env.id)()


def _policy(params: Params, policy_path: Path) -> Policy:
    from oodrl.policies.load import load_policy

    return load_policy(policy_path, mode=params.policy.mode)


def _set_attrs(params: Params, adapter: EnvironmentAdapter, policy: Policy) -> dict:
    """What every collected set records about the run that made it."""
    return {
        "env_id": params.env.id,
        "env_version": adapter.version(),
        "T": params.env.T,
        "onset": params.env.resolved_onset,
        "policy_mode": params.policy.mode,
        "policy_sha256": policy.sha256,
        "seed": params.seed,
    }


def _clean_set(params: Params, policy_path: Path, seeds: list[int], label: str, extra: dict):
    from oodrl.envs.collect import collect

    adapter, policy = _adapter(params), _policy(params, policy_path)
    attrs = {**_set_attrs(params, adapter, policy), "mode": "clean", "spec": None, **extra}
    with progress_bar(len(seeds), label, params.executor.progress) as bar:
        return collect(
            adapter,
            policy,
            seeds,
            params.env.T,
            policy_seed=params.seed,
            workers=params.executor.resolved_workers,
            attrs=attrs,
            progress=bar.update,
        )


def id_set(params: Params, policy_path: Path) -> TrajectorySet:
    """The clean in-distribution set; its attributes hold the fit/calibration split."""
    fit, calibration = fit_calibration_split(params)
    split = {"split": {"calibration": calibration, "fit": fit}}
    return _clean_set(params, policy_path, id_seeds(params), "collect_id", split)


def eval_set(params: Params, policy_path: Path) -> TrajectorySet:
    """The clean evaluation set: the matched counterparts of every perturbed set."""
    return _clean_set(params, policy_path, eval_seeds(params), "collect_eval", {})


def heldout_set(params: Params, which: str, policy_path: Path) -> TrajectorySet:
    """One of the `HELDOUT_SETS`: clean streams of T steps, as the evaluation streams, never
    fitted on."""
    return _clean_set(params, policy_path, HELDOUT_SETS[which](params), f"collect_{which}", {})


def perturbed_sets(
    params: Params,
    injector_name: str,
    severities: list[float],
    policy_path: Path,
    eval_path: Path,
) -> list[TrajectorySet]:
    """The evaluation set with one injector's anomaly at each severity (SPEC §3).

    Online severities are simulated together so their rollouts share the stage's workers.
    """
    from oodrl.injectors.apply import perturb_posthoc

    injector = params.injector(injector_name)
    if injector.mode == "posthoc":
        onset, offset = params.env.resolved_onset, params.anomaly.offset
        clean = read_trajectories(eval_path, stage="collect_eval")
        return [
            perturb_posthoc(injector, clean, injector.spec(s, onset, offset), params.seed)
            for s in severities
        ]
    label = f"{injector_name} ({len(severities)} severities)"
    return online_sets(params, injector, severities, policy_path, label)


def online_sets(
    params: Params, injector: OnlineInjector, severities: list[float], policy_path: Path,
    label: str, seeds: list[int] | None = None,
) -> list[TrajectorySet]:  # fmt: skip
    """The evaluation streams (or `seeds`) with an online fault from the onset at each
    severity, simulated together so their rollouts share the stage's workers: each stream is
    the matched twin of the clean stream of its seed."""
    from oodrl.injectors.apply import collect_online_sets

    onset, offset = params.env.resolved_onset, params.anomaly.offset
    specs = [injector.spec(severity, onset, offset) for severity in severities]
    adapter, policy = _adapter(params), _policy(params, policy_path)
    seeds = eval_seeds(params) if seeds is None else seeds
    with progress_bar(len(seeds) * len(specs), label, params.executor.progress) as bar:
        sets = collect_online_sets(
            injector, adapter, policy, seeds, params.env.T, specs,
            seed=params.seed, policy_seed=params.seed,
            workers=params.executor.resolved_workers, progress=bar.update,
        )  # fmt: skip
    base = _set_attrs(params, adapter, policy)
    return [dataclasses.replace(t, attrs={**base, **t.attrs}) for t in sets]
