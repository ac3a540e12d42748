"""The impact tier stages (SPEC §15, §19): `impact_reference` measures π's clean returns and
the random policy's once; `impact` measures faults' impact curves and searches and verifies
their tiers for one (environment, policy) as impact.yaml (`oodrl.protocol.impact`; the table and
figure of the tiers are tier_metrics', `oodrl.report.impact`); `collect_tiers` collects a fault's
tier streams."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from oodrl.config import Params
from oodrl.errors import ConfigError
from oodrl.io import yamlio
from oodrl.io.fileio import atomic_write_text

#: The default severity grid: 0.1 to 1.0 in steps of 0.1.
DEFAULT_GRID = tuple(round(0.1 * i, 1) for i in range(1, 11))


def run_impact_reference(
    params: Params, policy_path: Path, out: Path, *, horizon: int | None = None
) -> None:
    """Stage impact_reference: π's clean returns on every seed the impact stages use (the
    coarse curves', and the tier search's common seeds and every verification batch's,
    `oodrl.protocol.tier_search.crn_reference_seeds`) and the random policy's, measured once
    for every fault, whose paired estimates all reuse them
    (`oodrl.protocol.tier_search.measure_reference`)."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.policies.load import load_policy
    from oodrl.protocol.impact import episode_limit
    from oodrl.protocol.tier_search import measure_reference

    adapter = ENVIRONMENTS.get(params.env.id)()
    policy = load_policy(policy_path, mode=params.policy.mode)
    reference = measure_reference(
        adapter, policy, params.tiers.episodes, params.tiers.search, seed=params.seed,
        horizon=horizon or episode_limit(adapter), workers=params.executor.resolved_workers,
    )  # fmt: skip
    atomic_write_text(out, yamlio.dump(reference.as_dict()))


def run_impact(
    params: Params,
    policy_path: Path,
    out: Path,
    *,
    id_path: Path | None = None,
    reference_path: Path | None = None,
    injectors: Sequence[str] | None = None,
    grid: Sequence[float] = DEFAULT_GRID,
    n_episodes: int = 100,
    n_boot: int | None = None,
    horizon: int | None = None,
) -> dict:
    """Calibrate the impact of `injectors` (default: benchmark.injectors), search and verify
    their tiers (protocol 4's search, `tiers.search`, up to the grid's largest severity), and
    write the document; returns it. `reference_path`: impact_reference's document (measured
    here when not given)."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.policies.load import load_policy
    from oodrl.protocol.impact import Reference, live_injectors
    from oodrl.protocol.tier_search import calibrate_impact

    if not grid or any(not 0 < s <= 1 for s in grid) or list(grid) != sorted(set(grid)):
        raise ConfigError(
            f"--grid must be increasing severities in (0, 1], each once; got {list(grid)}."
        )
    names = list(injectors or params.benchmark.injectors)
    adapter = ENVIRONMENTS.get(params.env.id)()
    policy = load_policy(policy_path, mode=params.policy.mode)
    reference = None
    if reference_path is not None:
        reference = Reference.from_dict(read_reference(reference_path))
    document = calibrate_impact(
        adapter,
        policy,
        live_injectors(params, names, id_path),
        grid,
        n_episodes,
        search=params.tiers.search,
        reference=reference,
        seed=params.seed,
        horizon=horizon,
        n_boot=n_boot or params.metrics.n_boot,
        ci=params.metrics.ci,
        workers=params.executor.resolved_workers,
    )
    atomic_write_text(out, yamlio.dump(document))
    return document


def read_reference(path: Path) -> dict:
    """impact_reference's document, or a one-line error saying how to restore it."""
    from oodrl.errors import StoreError
    from oodrl.io.store import restore_hint

    if not Path(path).is_file():
        raise StoreError(f"{path}: missing; {restore_hint(path, 'impact_reference')}.")
    document = yamlio.load(Path(path).read_text())
    if not isinstance(document, dict) or not {"clean", "random"} <= set(document):
        raise StoreError(
            f"{path}: not an impact reference; {restore_hint(path, 'impact_reference')}."
        )
    return document


def collect_tiers(
    params: Params, fault: str, policy_path: Path, impact_path: Path, id_path: Path, out: Path
) -> None:
    """Stage collect_tiers: the evaluation streams with `fault` live at each tier its impact
    curve reaches (a store like the sweep's, one group per severity; its attributes map each
    tier to its severity and list the unreachable ones)."""
    from oodrl.io.store import write_sweep
    from oodrl.protocol.tiers import read_tiers, tier_sets

    tiers, unreachable = read_tiers(impact_path, fault)
    sets = tier_sets(params, fault, tiers, policy_path, id_path)
    attrs = {"injector": fault, "mode": "online", "tiers": tiers, "unreachable": unreachable}
    write_sweep(out, dict(zip(tiers.values(), sets, strict=True)), attrs)
