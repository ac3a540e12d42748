"""The impact stage (SPEC §15): every benchmarked fault's impact curve and tiers for one
(environment, policy), as impact.yaml, a markdown table and a figure (`oodrl.impact`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from oodrl import yamlio
from oodrl.config import Params
from oodrl.core.injector import OnlineInjector
from oodrl.errors import ConfigError
from oodrl.fileio import atomic_write_text

#: The default severity grid: 0.1 to 1.0 in steps of 0.1.
DEFAULT_GRID = tuple(round(0.1 * i, 1) for i in range(1, 11))


def live_injectors(
    params: Params, names: Sequence[str], id_path: Path | None = None
) -> dict[str, OnlineInjector]:
    """Each named fault as an online injector from its params block: a post-hoc observation
    fault becomes its live counterpart (same parameters), whose `mean`/`scale` are the clean ID
    set's statistics when `id_path` is given (else running statistics, see
    `oodrl.injectors.live_observation`)."""
    from oodrl.injectors import INJECTORS
    from oodrl.injectors.live_observation import LIVE_COUNTERPARTS, reference_statistics

    reference = None
    if id_path is not None:
        from oodrl.store import read_trajectories

        reference = reference_statistics(read_trajectories(id_path, stage="collect_id").states)
    injectors = {}
    for name in names:
        block = {k: v for k, v in params.anomaly.injectors.get(name, {}).items() if k != "severity"}
        live = LIVE_COUNTERPARTS.get(name, name)
        cls = INJECTORS.get(live)
        if cls.mode != "online":
            raise ConfigError(f"Injector '{name}' has no live version; impact needs online faults.")
        if reference is not None and "scale" in cls().get_params():
            block = {**reference, **block}
        injectors[name] = cls.from_params(block)
    return injectors


def run_impact(
    params: Params,
    policy_path: Path,
    out: Path,
    table: Path,
    figure: Path,
    *,
    id_path: Path | None = None,
    injectors: Sequence[str] | None = None,
    grid: Sequence[float] = DEFAULT_GRID,
    n_episodes: int = 100,
    n_boot: int | None = None,
    horizon: int | None = None,
) -> dict:
    """Calibrate the impact of `injectors` (default: benchmark.injectors) and write the
    document, its table and its figure; returns the document."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.impact import calibrate_impact, impact_table, plot_impact_curves
    from oodrl.policies.load import load_policy

    if not grid or any(not 0 < s <= 1 for s in grid) or list(grid) != sorted(set(grid)):
        raise ConfigError(
            f"--grid must be increasing severities in (0, 1], each once; got {list(grid)}."
        )
    names = list(injectors or params.benchmark.injectors)
    adapter = ENVIRONMENTS.get(params.env.id)()
    policy = load_policy(policy_path, mode=params.policy.mode)
    document = calibrate_impact(
        adapter,
        policy,
        live_injectors(params, names, id_path),
        grid,
        n_episodes,
        seed=params.seed,
        horizon=horizon,
        n_boot=n_boot or params.metrics.n_boot,
        ci=params.metrics.ci,
        workers=params.executor.resolved_workers,
    )
    atomic_write_text(out, yamlio.dump(document))
    atomic_write_text(table, impact_table(document))
    plot_impact_curves(document, figure)
    return document
