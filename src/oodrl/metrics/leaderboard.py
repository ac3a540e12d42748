"""Cross-environment aggregates of one metric (SPEC §12): the suite's leaderboard.

A *cell* is one (environment, anomaly) pair; in it each detector has one value per evaluation
episode (matched AUROC by default). Per detector:

- the detector × environment table: the mean over that environment's anomalies of the cell means;
- over all cells: the mean and the interquartile mean (IQM, the mean of the middle 50% of cell
  means, `scipy.stats.trim_mean(·, 0.25)`), each with a stratified-bootstrap CI: a replicate
  resamples the episodes within every cell (with replacement), recomputes the cell means and
  then the aggregate, so cells are never mixed and every cell keeps its weight (Agarwal et al.
  2021, "Deep RL at the edge of the statistical precipice");
- the probability of improvement P(A > B): the chance that A's cell mean beats B's on a cell
  drawn at random (ties count ½), with the same bootstrap for its CI.

Replicate b draws its indices from ``default_rng([seed, cell number])``, so the draws of a cell
do not depend on which other cells exist, and every detector of a cell is resampled with the
same episodes (they are paired: same episodes, same seeds).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

#: One (environment, anomaly) pair.
Cell = tuple[str, str]


@dataclass(frozen=True)
class Interval:
    """A point estimate with its bootstrap percentile CI."""

    value: float
    ci_low: float
    ci_high: float

    def as_dict(self, decimals: int = 6) -> dict[str, float]:
        return {k: round(float(v), decimals) + 0.0 for k, v in vars(self).items()}


@dataclass(frozen=True)
class Leaderboard:
    detectors: tuple[str, ...]
    environments: tuple[str, ...]
    #: detector → environment → mean over that environment's anomalies of the cell means.
    table: dict[str, dict[str, float]]
    mean: dict[str, Interval]
    iqm: dict[str, Interval]
    #: (A, B) → P(A's cell mean > B's) over cells, ties ½.
    improvement: dict[tuple[str, str], Interval]
    n_cells: int


def interquartile_mean(values: np.ndarray, axis: int = -1) -> np.ndarray:
    """The mean of the middle 50% (25% trimmed from each end), as scipy's trim_mean."""
    from scipy.stats import trim_mean

    return trim_mean(values, 0.25, axis=axis)


def leaderboard(
    cells: Mapping[Cell, Mapping[str, Sequence[float]]],
    n_boot: int = 1000,
    ci: float = 0.95,
    seed: int = 0,
) -> Leaderboard:
    """Aggregate per-episode values ``cells[(env, anomaly)][detector]`` (see the module doc).

    Every cell must hold every detector, with the same number of episodes for each detector.
    """
    keys = sorted(cells)
    if not keys:
        raise ValueError("no cells to aggregate")
    detectors = tuple(sorted(cells[keys[0]]))
    for key in keys:
        if tuple(sorted(cells[key])) != detectors:
            raise ValueError(f"cell {key} has detectors {sorted(cells[key])}, not {detectors}")
    environments = tuple(sorted({env for env, _ in keys}))
    values = [np.array([cells[key][d] for d in detectors], dtype=np.float64) for key in keys]
    point = np.stack([v.mean(axis=1) for v in values], axis=1)  # (detectors, cells)
    replicates = _stratified_replicates(values, n_boot, seed)  # (n_boot, detectors, cells)

    def interval(estimate: float, draws: np.ndarray) -> Interval:
        low, high = np.quantile(draws, [(1 - ci) / 2, (1 + ci) / 2])
        return Interval(float(estimate), float(low), float(high))

    table = {
        d: {
            env: float(np.mean([point[i, j] for j, key in enumerate(keys) if key[0] == env]))
            for env in environments
        }
        for i, d in enumerate(detectors)
    }
    mean = {
        d: interval(point[i].mean(), replicates[:, i].mean(axis=1)) for i, d in enumerate(detectors)
    }
    iqm = {
        d: interval(interquartile_mean(point[i]), interquartile_mean(replicates[:, i], axis=1))
        for i, d in enumerate(detectors)
    }
    improvement = {
        (a, b): interval(
            _beats(point[i], point[j]), _beats(replicates[:, i], replicates[:, j], axis=1)
        )
        for i, a in enumerate(detectors)
        for j, b in enumerate(detectors)
        if i != j
    }
    return Leaderboard(detectors, environments, table, mean, iqm, improvement, len(keys))


def _beats(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
    """Mean over cells of 1 where a > b, ½ where equal, 0 where a < b."""
    return ((a > b) + 0.5 * (a == b)).mean(axis=axis)


def _stratified_replicates(values: list[np.ndarray], n_boot: int, seed: int) -> np.ndarray:
    """Cell means (n_boot, detectors, cells) with episodes resampled within each cell."""
    out = np.empty((n_boot, values[0].shape[0], len(values)))
    for c, cell in enumerate(values):
        n = cell.shape[1]
        index = np.random.default_rng([seed, c]).integers(0, n, size=(n_boot, n))
        out[:, :, c] = cell[:, index].mean(axis=2).T
    return out
