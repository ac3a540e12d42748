"""What the time-aware rule changes (SPEC §24): per detector, time-aware minus constant.

Input: the per-stream detections of both rules, each in the leaderboard's shape
(`oodrl.metrics.leaderboard.CellValues`): ``{cell: {detector: per-stream values}}``, a cell
being (environment, policy, fault, tier) and the values the 0/1 `detection_rate@K` of its faulty
streams (`oodrl.metrics.time_aware.stream_detections`). The two mappings hold the same cells,
detectors and stream counts: value i of a cell is the same stream under either rule, so the rules
are compared stream by stream (paired). A cell given as one rate per rule (a list of one value)
is allowed; it then adds no sampling variance.

Per detector (`rule_change`, for one tier; `rule_change_by_tier` splits by the cell's tier):

- the difference: the mean over cells of the cell's time-aware rate minus its constant rate;
- its CI: a paired stratified percentile bootstrap, the strata being the cells (each cell a run
  of a task): replicate b redraws every cell's streams with replacement, one draw per cell
  shared by both rules and every detector (they score the same streams), so cells are never
  mixed and each keeps its weight. Cell number c (in sorted order) draws from
  `bootstrap.bootstrap_indices` seeded with [seed, c], as the leaderboard's tasks do;
- the detectors whose CI excludes 0 (`changed`);
- Kendall's τ between the detectors' IQMs of cell rates under the two rules
  (`aggregate.interquartile_mean`, scipy's τ-b): 1 when the rule leaves the ranking alone.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from oodrl.metrics.aggregate import interquartile_mean
from oodrl.metrics.bootstrap import bootstrap_indices

#: The leaderboard's cells of per-stream values (`oodrl.metrics.leaderboard.CellValues`, not
#: imported: the leaderboard imports this module): {cell: {detector: per-stream values}}, a cell
#: a `leaderboard.Cell` or the tuple (environment, policy, fault, tier).
CellValues = Mapping[Any, Mapping[str, Sequence[float]]]


def _tier(cell: Sequence[str]) -> str:
    return cell[3]  # leaderboard.Cell's `tier`


@dataclass(frozen=True)
class RuleDifference:
    """A detector's mean time-aware − constant rate over cells, with its bootstrap CI."""

    mean: float
    ci_low: float
    ci_high: float
    n_cells: int

    @property
    def excludes_zero(self) -> bool:
        return self.ci_low > 0 or self.ci_high < 0


@dataclass(frozen=True)
class RuleChange:
    """One tier's comparison of the two rules (see the module doc)."""

    detectors: tuple[str, ...]
    differences: dict[str, RuleDifference]
    #: rule ("constant", "time_aware") → detector → IQM of its cell rates.
    iqm: dict[str, dict[str, float]]
    kendall_tau: float

    @property
    def changed(self) -> tuple[str, ...]:
        """The detectors whose difference's CI excludes 0."""
        return tuple(d for d in self.detectors if self.differences[d].excludes_zero)


def _paired(constant: CellValues, time_aware: CellValues) -> tuple[list, tuple[str, ...]]:
    """Per cell in sorted order, (detectors, streams) arrays under each rule."""
    if set(constant) != set(time_aware) or not constant:
        raise ValueError("both rules need the same, non-empty set of cells")
    detectors = tuple(sorted(next(iter(constant.values()))))
    cells = []
    for cell in sorted(constant):
        rules = [constant[cell], time_aware[cell]]
        if any(tuple(sorted(r)) != detectors for r in rules):
            raise ValueError(f"cell {tuple(cell)} must hold detectors {detectors} under both rules")
        try:
            pair = [np.array([r[d] for d in detectors], dtype=np.float64) for r in rules]
        except ValueError:
            raise ValueError(f"cell {tuple(cell)}: one stream count for all values") from None
        if pair[0].shape != pair[1].shape or pair[0].ndim != 2 or pair[0].shape[1] == 0:
            raise ValueError(f"cell {tuple(cell)}: the rules need the same, non-empty streams")
        if not all(np.isfinite(p).all() for p in pair):
            raise ValueError(f"cell {tuple(cell)}: values must be finite")
        cells.append(pair)
    return cells, detectors


def rule_change(
    constant: CellValues,
    time_aware: CellValues,
    *,
    n_boot: int = 1000,
    ci: float = 0.95,
    seed: int = 0,
) -> RuleChange:
    """Time-aware minus constant per detector over the cells of one tier, with its paired
    stratified bootstrap CI, and Kendall's τ between the two IQM rankings (module doc)."""
    from scipy.stats import kendalltau

    cells, detectors = _paired(constant, time_aware)
    differences = [ta - c for c, ta in cells]  # (detectors, streams) per cell
    point = np.mean([d.mean(axis=1) for d in differences], axis=0)  # (detectors,)
    replicates = np.zeros((len(detectors), n_boot))
    for number, diff in enumerate(differences):
        index = bootstrap_indices(diff.shape[1], n_boot, [seed, number])
        replicates += diff[:, index].mean(axis=2)
    replicates /= len(differences)
    low, high = np.quantile(replicates, [(1 - ci) / 2, (1 + ci) / 2], axis=1)
    iqm = {
        rule: {
            d: float(interquartile_mean(np.array([pair[i][j].mean() for pair in cells])))
            for j, d in enumerate(detectors)
        }
        for i, rule in enumerate(("constant", "time_aware"))
    }
    tau = kendalltau(
        [iqm["constant"][d] for d in detectors], [iqm["time_aware"][d] for d in detectors]
    ).statistic
    return RuleChange(
        detectors,
        {
            d: RuleDifference(float(point[j]), float(low[j]), float(high[j]), len(cells))
            for j, d in enumerate(detectors)
        },
        iqm,
        float(tau),
    )


def rule_change_by_tier(
    constant: CellValues, time_aware: CellValues, **kwargs: Any
) -> dict[str, RuleChange]:
    """`rule_change` per tier of the cells (a cell's `tier`), tiers in sorted order."""
    if set(constant) != set(time_aware):
        raise ValueError("both rules need the same set of cells")
    tiers = sorted({_tier(cell) for cell in constant})
    return {
        tier: rule_change(
            *(
                {c: v for c, v in rule.items() if _tier(c) == tier}
                for rule in (constant, time_aware)
            ),
            **kwargs,
        )
        for tier in tiers
    }
