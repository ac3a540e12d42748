"""Episode bootstrap of per-episode metric values (SPEC §6): mean, std and a percentile CI.

The resampling unit is the episode. Replicate b draws N episode indices with replacement from
`numpy.random.default_rng(seed)`; the indices depend only on (seed, N, n_boot), so every
metric of one episode set is resampled with the same draws — the metrics of a record stay
paired with each other and with their null counterparts.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from oodrl.errors import ContractError


@dataclass(frozen=True)
class BootstrapSummary:
    """Mean and sample std (ddof 1; 0 for one episode) over episodes, and the percentile CI."""

    mean: float
    std: float
    ci_low: float
    ci_high: float
    n_episodes: int

    def as_dict(self, decimals: int = 6) -> dict[str, float | int]:
        """Plain Python numbers, rounded so that written files are stable (YAML/JSON-safe)."""

        def clean(value: float) -> float:
            return round(float(value), decimals) + 0.0  # + 0.0 turns -0.0 into 0.0

        return {
            "mean": clean(self.mean),
            "std": clean(self.std),
            "ci_low": clean(self.ci_low),
            "ci_high": clean(self.ci_high),
            "n_episodes": int(self.n_episodes),
        }


def _values(values: np.ndarray, what: str) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 1 or values.size == 0:
        raise ContractError(f"{what} must be a non-empty 1-D array; got shape {values.shape}.")
    if not np.isfinite(values).all():
        raise ContractError(f"{what} contains NaN or inf; per-episode values must be finite.")
    return values


def _check_settings(n_boot: int, ci: float) -> None:
    if n_boot < 1:
        raise ContractError(f"n_boot must be >= 1; got {n_boot}.")
    if not 0.0 < ci < 1.0:
        raise ContractError(f"ci must be in (0, 1); got {ci}.")


def bootstrap_indices(n_episodes: int, n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, n_episodes) episode indices drawn with replacement, reproducible from `seed`."""
    return np.random.default_rng(seed).integers(0, n_episodes, size=(n_boot, n_episodes))


def _summary(per_episode: np.ndarray, replicate_means: np.ndarray, ci: float) -> BootstrapSummary:
    tail = 100 * (1 - ci) / 2
    low, high = np.percentile(replicate_means, [tail, 100 - tail])
    n = per_episode.size
    return BootstrapSummary(
        mean=float(per_episode.mean()),
        std=float(per_episode.std(ddof=1)) if n > 1 else 0.0,
        ci_low=float(low),
        ci_high=float(high),
        n_episodes=n,
    )


def episode_bootstrap(
    values: np.ndarray, *, n_boot: int = 1000, ci: float = 0.95, seed: int = 0
) -> BootstrapSummary:
    """Mean, std and the `ci` percentile interval of the mean of per-episode `values`."""
    _check_settings(n_boot, ci)
    values = _values(values, "values")
    index = bootstrap_indices(values.size, n_boot, seed)
    return _summary(values, values[index].mean(axis=1), ci)


def paired_bootstrap(
    raw: np.ndarray,
    null: np.ndarray,
    combine: Callable[[np.ndarray, np.ndarray], np.ndarray],
    *,
    n_boot: int = 1000,
    ci: float = 0.95,
    seed: int = 0,
) -> BootstrapSummary:
    """Bootstrap of mean(combine(raw, null)) resampling raw and null with the same episodes.

    `raw[i]` and `null[i]` belong to episode i (a perturbed episode and its matched clean one);
    `combine` is element-wise (e.g. raw − null). Because one index draw selects both values of
    an episode, the episode-to-episode variation they share cancels: the interval is narrower
    than resampling the two sets independently, and identical to `episode_bootstrap` of the
    per-episode combined values with the same seed.
    """
    _check_settings(n_boot, ci)
    raw = _values(raw, "raw")
    null = _values(null, "null")
    if raw.shape != null.shape:
        raise ContractError(
            f"Paired values need one length per episode; got {raw.size} and {null.size}."
        )
    index = bootstrap_indices(raw.size, n_boot, seed)
    replicates = combine(raw[index], null[index]).mean(axis=1)
    return _summary(combine(raw, null), replicates, ci)
