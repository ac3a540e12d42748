"""Collection stages: clean ID and evaluation sets, perturbed headline and sweep sets."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from oodrl.config import Params
from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.policy import Policy
from oodrl.core.trajectory import TrajectorySet
from oodrl.envs import ENVIRONMENTS
from oodrl.stages.common import progress_bar
from oodrl.store import read_trajectories, write_sweep, write_trajectories


def _adapter(params: Params) -> EnvironmentAdapter:
    return ENVIRONMENTS.get(params.env.id)()


def _policy(params: Params, policy_path: Path) -> Policy:
    from oodrl.policies.load import load_policy

    return load_policy(policy_path, mode=params.policy.mode)


def _base_attrs(params: Params, adapter: EnvironmentAdapter, policy: Policy) -> dict:
    return {
        "env_id": params.env.id,
        "env_version": adapter.version(),
        "T": params.env.T,
        "onset": params.env.resolved_onset,
        "policy_mode": params.policy.mode,
        "policy_sha256": policy.sha256,
        "seed": params.seed,
    }


def id_seeds(params: Params) -> list[int]:
    return [params.seed + i for i in range(params.data.n_id)]


def eval_seeds(params: Params) -> list[int]:
    return [params.seed + params.data.eval_seed_offset + j for j in range(params.data.n_ood)]


def fit_calibration_split(params: Params) -> tuple[list[int], list[int]]:
    """Trajectory indices of the fit and calibration parts: a seeded split by trajectory."""
    order = np.random.default_rng(params.seed).permutation(params.data.n_id)
    n_cal = params.data.n_calibration
    return sorted(order[n_cal:].tolist()), sorted(order[:n_cal].tolist())


def _collect_clean(params: Params, policy_path: Path, seeds: list[int], label: str, extra: dict):
    from oodrl.envs.collect import collect

    adapter, policy = _adapter(params), _policy(params, policy_path)
    attrs = {**_base_attrs(params, adapter, policy), "mode": "clean", "spec": None, **extra}
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


def collect_id(params: Params, policy_path: Path, out: Path) -> TrajectorySet:
    fit, calibration = fit_calibration_split(params)
    tset = _collect_clean(
        params,
        policy_path,
        id_seeds(params),
        "collect_id",
        {"split": {"calibration": calibration, "fit": fit}},
    )
    write_trajectories(out, tset)
    return tset


def collect_eval(params: Params, policy_path: Path, out: Path) -> TrajectorySet:
    tset = _collect_clean(params, policy_path, eval_seeds(params), "collect_eval", {})
    write_trajectories(out, tset)
    return tset


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
    from oodrl.injectors.apply import collect_online_sets, perturb_posthoc

    injector = params.injector(injector_name)
    onset, offset = params.env.resolved_onset, params.anomaly.offset
    specs = [injector.spec(severity, onset, offset) for severity in severities]
    if injector.mode == "posthoc":
        clean = read_trajectories(eval_path, stage="collect_eval")
        return [perturb_posthoc(injector, clean, spec, params.seed) for spec in specs]
    adapter, policy = _adapter(params), _policy(params, policy_path)
    seeds = eval_seeds(params)
    label = f"{injector_name} ({len(specs)} severities)"
    with progress_bar(len(seeds) * len(specs), label, params.executor.progress) as bar:
        sets = collect_online_sets(
            injector, adapter, policy, seeds, params.env.T, specs,
            seed=params.seed, policy_seed=params.seed,
            workers=params.executor.resolved_workers, progress=bar.update,
        )  # fmt: skip
    base = _base_attrs(params, adapter, policy)
    return [dataclasses.replace(t, attrs={**base, **t.attrs}) for t in sets]


def collect_ood(
    params: Params, injector_name: str, policy_path: Path, eval_path: Path, out: Path
) -> None:
    severity = params.injector_severity(injector_name)
    (tset,) = perturbed_sets(params, injector_name, [severity], policy_path, eval_path)
    write_trajectories(out, tset)


def collect_sweep(
    params: Params, injector_name: str, policy_path: Path, eval_path: Path, out: Path
) -> None:
    grid = params.anomaly.sweep
    sets = perturbed_sets(params, injector_name, grid, policy_path, eval_path)
    write_sweep(out, dict(zip(grid, sets, strict=True)),
                {"injector": injector_name, "mode": sets[0].attrs.get("mode")})  # fmt: skip
