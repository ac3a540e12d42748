"""Impact tiers in the pipelines (SPEC §15): where each pipeline keeps them, the tiers an
impact document gives, and the evaluation streams collected at them.

The stages (one pipeline, `oodrl.suite.pipeline`):
- `impact@<fault>` writes `data/impact/<fault>.yaml` (`oodrl.protocol.impact`): the fault's impact
  curve, the severity of each tier (or "unreachable", "not reached") with its verification, and
  the probes of its tier search (`oodrl.protocol.tier_search`);
- `collect_tiers@<fault>` collects the evaluation streams with the fault live from the onset at
  each reachable tier (`tier_sets`): `data/tiers/<fault>.zarr`;
- `collect_calibration`, `collect_audit` and `collect_twins` collect the held-out clean
  streams (`oodrl.protocol.streams.HELDOUT_SETS`);
- each detector's `score_clean` and `score@<fault>` score them (`oodrl.io.layout` names the stores);
- `tier_metrics` writes `reports/tier_results.json` (a protocol-4 pipeline holds
  `reports/tier_results.yaml` until it is rebuilt) and `reports/tiers/` (`oodrl.metrics.tiers`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from oodrl.config import Params
from oodrl.core.trajectory import TrajectorySet
from oodrl.errors import StoreError
from oodrl.io import yamlio
from oodrl.io.store import restore_hint

#: Where a pipeline keeps each fault's impact document, tier streams and their scores.
IMPACT_DIR = "data/impact"
TIERS_DIR = "data/tiers"
CALIBRATION_STORE = "data/calibration.zarr"


def impact_path(impact_dir: Path, fault: str) -> Path:
    return Path(impact_dir) / f"{fault}.yaml"


def read_impact(path: Path, fault: str) -> dict[str, Any]:
    """One fault's record of an impact document (`oodrl impact --injector <fault>`)."""
    if not Path(path).is_file():
        raise StoreError(f"{path}: missing; {restore_hint(path, f'impact@{fault}')}.")
    document = yamlio.load(Path(path).read_text())
    faults = document.get("faults") or {}
    if fault not in faults:
        raise StoreError(
            f"{path}: holds no impact curve of {fault!r}; {restore_hint(path, f'impact@{fault}')}."
        )
    return {**document, "fault": faults[fault]}


def read_tiers(path: Path, fault: str) -> tuple[dict[str, float], list[str]]:
    """The tiers that have a severity (tier -> σ, in level order) and those that have none
    ("unreachable", or "not reached" by a search whose probes ran out): no streams there."""
    from oodrl.protocol.impact import tier_severity

    tiers = read_impact(path, fault)["fault"]["tiers"]
    severities = {name: tier_severity(tier) for name, tier in tiers.items()}
    reachable = {n: s for n, s in severities.items() if s is not None}
    return reachable, [n for n, s in severities.items() if s is None]


def tier_sets(
    params: Params,
    injector_name: str,
    tiers: dict[str, float],
    policy_path: Path,
    id_path: Path,
) -> list[TrajectorySet]:
    """The evaluation streams with one fault live from the onset at each tier's severity
    (`tiers`: tier name -> severity, the reachable tiers of its impact curve).

    Observation faults run as their live counterparts (the policy acts on the faulty sensor),
    with the same parameters and the clean ID set's reference statistics, as in the impact
    calibration that set the severities (`oodrl.protocol.impact.live_injectors`). The streams' seeds
    are the first `tiers.n_streams` evaluation seeds, so each is the matched twin of a stream
    of the clean twins set (`collect_twins`).
    """
    from oodrl.protocol.impact import live_injectors
    from oodrl.protocol.streams import online_sets, twin_seeds

    injector = live_injectors(params, [injector_name], id_path)[injector_name]
    label = f"{injector_name} ({len(tiers)} tiers)"
    sets = online_sets(
        params, injector, list(tiers.values()), policy_path, label, twin_seeds(params)
    )
    return [
        dataclasses.replace(t, attrs={**t.attrs, "tier": tier})
        for tier, t in zip(tiers, sets, strict=True)
    ]
