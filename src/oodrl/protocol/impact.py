"""Impact calibration (SPEC §15): what a fault at severity σ costs the agent, and the tiers.

For a policy π and an online fault f, R̃(σ) = (R(σ) − R_rand) / (R_clean − R_rand): R(σ) is π's
mean return over whole episodes with f active from their first step, R_clean the same without
the fault, R_rand a uniformly random policy's. Episodes run in the collector
(`oodrl.envs.collect`) with the fault's live hooks (`oodrl.injectors.apply`), one episode per
stream: each stream may run as long as the environment's time limit, so its first episode always
ends within it; that episode is the one counted, and the stream stops there (the collector's
`first_episode`: the same returns as simulating the rest of the horizon, at a third of the steps
on LunarLander).

Seeds, never the protocol's (ID `seed + i`, evaluation `seed + 10000 + j`, policy tuning
`seed + 100000 + i`, final policy check 1000000 + i): π's episodes reset from
`seed + POLICY_SEED_OFFSET + j`, the random policy's from `seed + RANDOM_SEED_OFFSET + j`,
j < n_episodes. The clean run and every severity share π's seeds (common random numbers):
differences along the curve are the fault's, not the start states'. The fault of stream j
draws from `injector_rng(seed, name, j)`. The tier search and its verification have blocks of
their own (`oodrl.protocol.tier_search`); π's clean returns on all of them are measured once per
(environment, policy) by `tier_search.measure_reference` (the impact_reference stage).

Noise and non-monotone estimates: the point estimates R̃(σ) (with the exact anchor R̃(0) = 1,
since severity 0 reproduces the clean episodes) are fitted by an isotonic, monotone
non-increasing regression (pool-adjacent-violators, scikit-learn's IsotonicRegression, equal
weights). A fault is taken not to help the agent more as it grows stronger; where the raw
estimates go up, noise is the explanation, and pooling adjacent violators is the least-squares
curve that respects it. Severities whose whole CI lies above R̃ = 1 (the fault raises the
return) are listed in `return_above_clean`. Tiers are read on that fitted curve: the severity at
which it first falls to the level, interpolated linearly between grid points, so
mild ≤ moderate ≤ severe by construction. A level the fitted curve does not reach on the grid
is "unreachable", never clipped to the largest σ. Confidence intervals: a percentile bootstrap
(π's episodes resampled jointly across the clean run and every σ, the random policy's on their
own), the isotonic fit and the tier read again in every replicate.

Stepped faults. A fault that changes in whole steps (`correlation_break`: ⌈σ·d⌉ coordinates;
`observation_delay`: ⌈σ·max_delay⌉ steps of delay; `severity_steps` of its live injector) is the
same fault for every σ of a step, so its curve is measured once per step, at the step's midpoint
(k − ½)/n (safe from the rounding of σ·n at the step's edges), instead of on the grid, and
nothing is interpolated between steps: a tier is the first step whose fitted R̃ falls to its
level, if that step does not also fall past the level where the next tier begins (below
SEVERE_FLOOR for `severe`); otherwise no step lands in the tier and it is unreachable. Reading
such a curve linearly would name severities, between σ = 0 and the first step, that give the
first step's fault with the first step's impact.

Tiers (`oodrl.protocol.tier_search.calibrate_impact`, SPEC §19, §23). The tiers read on the
coarse curve are where a tier search starts, never a tier: a continuous fault's tiers are
searched for and verified by the tier search (`oodrl.protocol.tier_search.search_fault`:
protocol 4's common random numbers, monotone fit of every probe and planned verification;
protocol 5's rule that a tier is verified only once its CI reaches the target width), the
coarse curve guiding its probes; a
stepped fault's tiers are its steps, verified the same way (`verify_steps`). Each tier carries
its verification (R̃ re-measured on fresh seeds, with its CI and episodes) and each fault the
probes its search made.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from oodrl.config import POLICY_SEED_OFFSET, RANDOM_SEED_OFFSET
from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.injector import OnlineInjector
from oodrl.core.policy import Policy
from oodrl.errors import ConfigError, ContractError

if TYPE_CHECKING:
    from oodrl.config import Params

#: The tiers: the normalised return R̃ at which each begins (SPEC §15, §19). `benign` is the
#: harmless-shift control: a shift that costs the agent 1% of its return, on which an alarm is a
#: cost (Anomaly-Gym's "tiny" level, 0.99).
LEVELS = {"benign": 0.99, "mild": 0.95, "moderate": 0.90, "severe": 0.75}
#: A stepped fault's `severe` step keeps R̃ ≥ this: a step that costs more than half the return
#: is beyond the tiers (ANOMRL's lowest calibration level; the RIQN benchmark leaves out faults
#: that make the agent fail at once).
SEVERE_FLOOR = 0.5
UNREACHABLE = "unreachable"
BEYOND_RANGE = "beyond range"
#: A minimum detectable impact already reached at the first measured severity is a bound, not a
#: value (SPEC §19): `{AT_MOST: loss there}`, shown "≤ loss".
AT_MOST = "at_most"


class UniformRandomPolicy:
    """Uniformly random actions of an adapter's action space; row i draws from `rngs[i]` (the
    collector's per-stream generator), so its episodes are reproducible."""

    mode = "random"
    sha256 = "uniform-random"

    def __init__(self, adapter: EnvironmentAdapter) -> None:
        self.adapter = adapter
        self.state_dim = adapter.state_dim
        self.action_kind = adapter.action_kind
        self.action_size = adapter.action_size

    def act(self, observations: np.ndarray, rngs: Sequence[np.random.Generator]) -> np.ndarray:
        if self.action_kind == "discrete":
            return np.array([rng.integers(self.action_size) for rng in rngs], dtype=np.int64)
        low, high = self.adapter.action_low, self.adapter.action_high
        return np.stack([rng.uniform(low, high).astype(np.float32) for rng in rngs])


def episode_limit(adapter: EnvironmentAdapter) -> int:
    """The environment's time limit (its `max_episode_steps`): the length of an impact stream."""
    env = adapter.make()
    try:
        limit = env.spec.max_episode_steps if env.spec is not None else None
    finally:
        env.close()
    if not limit:
        raise ConfigError(
            f"{adapter.env_id} has no time limit (max_episode_steps); impact calibration needs "
            "whole episodes: pass --horizon, the most steps an episode may take."
        )
    return int(limit)


def first_episode_returns(tset: Any) -> np.ndarray:
    """The return of each stream's first episode; refused if one did not end in the stream."""
    first = tset.episode_index == 0
    ended = (tset.dones & first).any(axis=1)
    if not ended.all():
        raise ContractError(
            f"{int((~ended).sum())} of {len(ended)} streams did not finish their first episode "
            f"within {tset.dones.shape[1]} steps; raise the horizon to the episode limit."
        )
    return np.where(first, tset.rewards.astype(np.float64), 0.0).sum(axis=1)


@dataclass(frozen=True)
class Returns:
    """Per-episode returns: π clean (n,), π under the fault per severity (n,) each (the same
    seeds), the random policy's (m,)."""

    clean: np.ndarray
    faulty: dict[float, np.ndarray]
    random: np.ndarray


def policy_seeds(seed: int, n_episodes: int) -> list[int]:
    """The reset seeds of π's impact episodes (clean and every severity)."""
    return [seed + POLICY_SEED_OFFSET + j for j in range(n_episodes)]


def clean_returns(
    adapter: EnvironmentAdapter, policy: Policy, n_episodes: int, *, seed: int, horizon: int,
    workers: int = 1, seeds: Sequence[int] | None = None,
) -> np.ndarray:  # fmt: skip
    """Whole-episode returns of π without a fault (on `seeds`, else π's impact seeds)."""
    from oodrl.envs.collect import collect

    seeds = list(seeds) if seeds is not None else policy_seeds(seed, n_episodes)
    tset = collect(
        adapter, policy, seeds, horizon, policy_seed=seed, workers=workers, first_episode=True
    )
    return first_episode_returns(tset)


def faulty_returns(
    adapter: EnvironmentAdapter,
    policy: Policy,
    injector: OnlineInjector,
    severities: Sequence[float],
    n_episodes: int,
    *,
    seed: int,
    horizon: int,
    workers: int = 1,
    seeds: Sequence[int] | None = None,
) -> dict[float, np.ndarray]:
    """Whole-episode returns of π under `injector` at each severity, active from step 0, on
    π's impact seeds (stream j's fault draws from `injector_rng(seed, name, j)`), or on `seeds`
    (a probe's: its faults draw from `injector_rng(seeds[0], name, j)`, so no two probes share
    a fault's noise)."""
    from oodrl.injectors.apply import collect_online_sets

    fault_seed = seed if seeds is None else int(seeds[0])
    seeds = list(seeds) if seeds is not None else policy_seeds(seed, n_episodes)
    specs = [injector.spec(float(s), 0) for s in severities]
    sets = collect_online_sets(
        injector, adapter, policy, seeds, horizon, specs, fault_seed, policy_seed=seed,
        workers=workers, first_episode=True,
    )  # fmt: skip
    return {float(s): first_episode_returns(t) for s, t in zip(severities, sets, strict=True)}


def random_policy_returns(
    adapter: EnvironmentAdapter, n_episodes: int, *, seed: int, horizon: int
) -> np.ndarray:
    """Whole-episode returns of the uniformly random policy on its own seeds."""
    from oodrl.envs.collect import collect

    seeds = [seed + RANDOM_SEED_OFFSET + j for j in range(n_episodes)]
    tset = collect(
        adapter, UniformRandomPolicy(adapter), seeds, horizon, policy_seed=seed, first_episode=True
    )
    return first_episode_returns(tset)


def severity_steps(injector: OnlineInjector, adapter: EnvironmentAdapter) -> int | None:
    """The number of steps of a stepped fault on `adapter`, None for a continuous one (the live
    observation faults declare it; every dynamics and action fault changes continuously)."""
    from oodrl.injectors.live_observation import LiveObservationInjector

    if isinstance(injector, LiveObservationInjector):
        return injector.severity_steps(adapter)
    return None


def step_severities(n_steps: int) -> list[float]:
    """One severity per step of a stepped fault: step k's midpoint (k − ½)/n."""
    return [(k - 0.5) / n_steps for k in range(1, n_steps + 1)]


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
        from oodrl.io.store import read_trajectories

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


def monotone_curve(severities: Sequence[float], values: Sequence[float]) -> np.ndarray:
    """The least-squares monotone non-increasing fit of `values` over `severities`."""
    from sklearn.isotonic import IsotonicRegression

    fit = IsotonicRegression(increasing=False).fit_transform(
        np.asarray(severities, dtype=np.float64), np.asarray(values, dtype=np.float64)
    )
    return np.asarray(fit, dtype=np.float64)


def first_crossing(xs: Sequence[float], ys: Sequence[float], level: float) -> float | None:
    """The x at which the curve (xs, ys), linear between points, first falls to `level`;
    None if it never does. ys[0] must be above the level (the curve starts above it)."""
    xs, ys = np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)
    below = np.flatnonzero(ys <= level)
    if below.size == 0:
        return None
    i = int(below[0])
    if i == 0:
        return float(xs[0])
    fraction = (ys[i - 1] - level) / (ys[i - 1] - ys[i])
    return float(xs[i - 1] + fraction * (xs[i] - xs[i - 1]))


def first_rise(xs: Sequence[float], ys: Sequence[float], level: float) -> float | None:
    """The x at which the curve (xs, ys), linear between points, first rises to `level`."""
    return first_crossing(xs, -np.asarray(ys, dtype=np.float64), -level)


def tier_severities(
    severities: Sequence[float],
    monotone: Sequence[float],
    levels: Mapping[str, float] = LEVELS,
    stepped: bool = False,
) -> dict[str, float | None]:
    """Each tier's severity on a monotone curve that includes σ = 0; None = unreachable. A
    stepped fault's curve has one point per step and is not interpolated (module docstring)."""
    if not stepped:
        return {name: first_crossing(severities, monotone, lvl) for name, lvl in levels.items()}
    ys = np.asarray(monotone, dtype=np.float64)
    tiers: dict[str, float | None] = {}
    for name, level in levels.items():
        below = np.flatnonzero(ys <= level)
        floor = _tier_floor(name, levels)
        tiers[name] = float(severities[below[0]]) if below.size and ys[below[0]] >= floor else None
    return tiers


def _tier_floor(name: str, levels: Mapping[str, float] = LEVELS) -> float:
    """Where a stepped fault's tier ends: the next tier's level, SEVERE_FLOOR after the last."""
    later = [lvl for lvl in sorted(levels.values(), reverse=True) if lvl < levels[name]]
    return later[0] if later else SEVERE_FLOOR


def tier_severity(tier: Mapping[str, Any]) -> float | None:
    """A tier record's severity; None when it has none: "unreachable", or "not reached" (a
    search whose probes ran out before its fit fell to the level)."""
    value = tier.get("severity")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


def _normalised(faulty_mean, clean_mean, random_mean):
    return (faulty_mean - random_mean) / (clean_mean - random_mean)


def _rounded(value: float | None) -> float | str:
    return UNREACHABLE if value is None else round(float(value), 6) + 0.0


def impact_record(
    returns: Returns,
    *,
    levels: Mapping[str, float] = LEVELS,
    n_boot: int = 1000,
    ci: float = 0.95,
    seed: int = 0,
    stepped: bool = False,
) -> dict[str, Any]:
    """The coarse impact curve (raw and monotone, with bootstrap CIs) and the tiers read on it
    (where the tier search starts, `tier_search.calibrate_impact`), as YAML holds it;
    `stepped`: the severities are a stepped fault's steps (module docstring)."""
    severities = sorted(returns.faulty)
    if not severities or severities[0] <= 0:
        raise ConfigError(f"The severity grid must be positive severities; got {severities}.")
    clean, random = returns.clean, returns.random
    faulty = np.stack([returns.faulty[s] for s in severities])  # (n_severities, n)
    gap = clean.mean() - random.mean()
    if gap <= 0:
        raise ContractError(
            f"The policy's clean mean return ({clean.mean():.3f}) is not above the random "
            f"policy's ({random.mean():.3f}): the normalised return is undefined."
        )
    xs = [0.0, *severities]
    raw = np.concatenate([[1.0], _normalised(faulty.mean(axis=1), clean.mean(), random.mean())])
    monotone = monotone_curve(xs, raw)
    rng = np.random.default_rng(seed)
    policy_index = rng.integers(0, clean.size, size=(n_boot, clean.size))
    random_index = rng.integers(0, random.size, size=(n_boot, random.size))
    replicates = _normalised(
        faulty[:, policy_index].mean(axis=2),  # (n_severities, n_boot)
        clean[policy_index].mean(axis=1),
        random[random_index].mean(axis=1),
    ).T
    tail = (1 - ci) / 2
    low, high = np.quantile(replicates, [tail, 1 - tail], axis=0)
    # The coarse read: where the tier search starts (`tier_search.calibrate_impact`), never a
    # tier itself.
    tiers = {
        name: {"level": levels[name], "severity": _rounded(value)}
        for name, value in tier_severities(xs, monotone, levels, stepped).items()
    }
    curve = [
        {
            "severity": float(s),
            "mean_return": _rounded(faulty[i].mean()),
            "normalised": _rounded(raw[i + 1]),
            "ci": [_rounded(low[i]), _rounded(high[i])],
            "monotone": _rounded(monotone[i + 1]),
        }
        for i, s in enumerate(severities)
    ]
    # A fault that raises the return beyond its CI is worth a look before trusting its tiers
    # (LunarLander's dynamics faults: rewards that do not telescope, docs/SPEC.md §15).
    above = [float(s) for i, s in enumerate(severities) if low[i] > 1.0]
    return {"curve": curve, "tiers": tiers, "return_above_clean": above}


@dataclass(frozen=True)
class Reference:
    """π's clean whole-episode returns by reset seed (every seed the coarse curve, the tier
    search and the verification use) and the random policy's returns: one measurement per
    (environment, policy), shared by every fault's impact stage."""

    clean: dict[int, float]
    random: np.ndarray
    policy_sha256: str

    def returns(self, seeds: Sequence[int]) -> np.ndarray:
        return np.array([self.clean[int(s)] for s in seeds], dtype=np.float64)

    def as_dict(self) -> dict[str, Any]:
        seeds = sorted(self.clean)
        return {
            "policy_sha256": self.policy_sha256,
            "clean": {"seeds": seeds, "returns": [self.clean[s] for s in seeds]},
            "random": [float(r) for r in self.random],
        }

    @classmethod
    def from_dict(cls, document: Mapping[str, Any]) -> Reference:
        clean = document["clean"]
        return cls(
            {int(s): float(r) for s, r in zip(clean["seeds"], clean["returns"], strict=True)},
            np.asarray(document["random"], dtype=np.float64),
            str(document["policy_sha256"]),
        )


@dataclass(frozen=True)
class Estimate:
    """R̃ at one severity from paired episodes, with its percentile-bootstrap CI."""

    severity: float
    normalised: float
    ci: tuple[float, float]
    episodes: int

    def as_dict(self) -> dict[str, Any]:
        return {
            "severity": _rounded(self.severity),
            "normalised": _rounded(self.normalised),
            "ci": [_rounded(self.ci[0]), _rounded(self.ci[1])],
            "episodes": self.episodes,
        }


def paired_estimate(
    severity: float,
    faulty: np.ndarray,
    paired_clean: np.ndarray,
    reference: Reference,
    *,
    n_boot: int,
    ci: float,
    seed: int,
) -> Estimate:
    """R̃(σ) = 1 − mean(C_j − F_j) / (mean C − mean R_rand): the return lost on each episode
    against π's clean episode from the same reset seed (paired, so the start state's luck
    cancels), over the gap between π's pooled clean returns and the random policy's. The CI
    resamples the pairs, the clean pool and the random episodes independently."""
    pool, random = np.array(list(reference.clean.values())), reference.random
    loss = paired_clean - faulty
    rng = np.random.default_rng(seed)
    pairs = rng.integers(0, loss.size, size=(n_boot, loss.size))
    pooled = rng.integers(0, pool.size, size=(n_boot, pool.size))
    randoms = rng.integers(0, random.size, size=(n_boot, random.size))
    replicates = 1.0 - loss[pairs].mean(axis=1) / (
        pool[pooled].mean(axis=1) - random[randoms].mean(axis=1)
    )
    tail = (1 - ci) / 2
    low, high = np.quantile(replicates, [tail, 1 - tail])
    value = 1.0 - loss.mean() / (pool.mean() - random.mean())
    return Estimate(float(severity), float(value), (float(low), float(high)), int(loss.size))


def tier_tolerance(level: float, tolerance: float) -> float:
    """How close to its level a tier's R̃ must be: `tiers.search.tolerance`, but at most half
    the tier's loss 1 − level, so that no tolerance admits a severity that costs nothing (for
    `benign`, 0.005: R̃ = 1.0 is never within it)."""
    return min(tolerance, (1.0 - level) / 2)


def minimum_detectable_impact(
    impact_severities: Sequence[float],
    impact_monotone: Sequence[float],
    metric_severities: Sequence[float],
    metric_values: Sequence[float],
    target: float = 0.9,
    steps: int | None = None,
) -> float | str | dict[str, float]:
    """The smallest return loss 1 − R̃ at which a detection metric (matched AUROC, or
    detection_rate@K) reaches `target` (SPEC §15), or "beyond range".

    The metric's curve over its severities (linear between points) gives the first σ at which it
    reaches the target; 1 − R̃ is read at that σ on the monotone impact curve (which includes
    σ = 0, R̃ = 1), linear between grid points. Beyond range when the metric never reaches the
    target, or reaches it above the impact grid's largest severity. A stepped fault (`steps`,
    one impact point per step) is read without interpolating: the first metric severity that
    reaches the target, and the impact of its step ⌈σ·n⌉, as the injector computes it.
    Reached already at the first metric severity, the loss there only bounds it from above
    (SPEC §19): `{AT_MOST: loss}`.
    """
    if steps is not None:
        reached = [s for s, v in zip(metric_severities, metric_values, strict=True) if v >= target]
        if not reached or reached[0] > 1:
            return BEYOND_RANGE
        loss = 1.0 - float(impact_monotone[math.ceil(reached[0] * steps)])
    else:
        severity = first_rise(metric_severities, metric_values, target)
        xs = np.asarray(impact_severities, dtype=np.float64)
        if severity is None or severity > xs[-1]:
            return BEYOND_RANGE
        loss = 1.0 - float(np.interp(severity, xs, np.asarray(impact_monotone, dtype=np.float64)))
    loss = round(loss, 6) + 0.0
    return {AT_MOST: loss} if metric_values[0] >= target else loss


def impact_text(value: float | str | dict[str, float]) -> str:
    """A minimum-detectable-impact cell: "3.1%", "≤ 5.0%" (a bound) or "beyond range"."""
    if isinstance(value, dict):
        return f"≤ {100 * float(value[AT_MOST]):.1f}%"
    return value if isinstance(value, str) else f"{100 * float(value):.1f}%"


def impact_curve_points(record: Mapping[str, Any]) -> tuple[list[float], list[float]]:
    """A fault's monotone impact curve from its impact.yaml record, σ = 0 (R̃ = 1) included."""
    curve = record["curve"]
    return [0.0, *(p["severity"] for p in curve)], [1.0, *(p["monotone"] for p in curve)]


def minimum_detectable_impacts(
    impact: Mapping[str, Any],
    metric_by_severity: Mapping[str, Mapping[str, Mapping[float, float]]],
    target: float = 0.9,
) -> dict[str, dict[str, float | str]]:
    """Per detector and fault: `minimum_detectable_impact` of a metric given as
    {fault: {detector: {severity: value}}} (e.g. matched AUROC from sweep_results.yaml), on the
    fault's impact curve in an impact document; faults without an impact record are left out."""
    table: dict[str, dict[str, float | str]] = {}
    for fault, per_detector in sorted(metric_by_severity.items()):
        if fault not in impact["faults"]:
            continue
        xs, curve = impact_curve_points(impact["faults"][fault])
        steps = impact["faults"][fault].get("severity_steps")
        for detector, values in sorted(per_detector.items()):
            severities = sorted(values)
            table.setdefault(detector, {})[fault] = minimum_detectable_impact(
                xs, curve, severities, [values[s] for s in severities], target, steps
            )
    return table


def sweep_metric(sweep: Mapping[str, Any], metric: str = "matched_auroc"):
    """{fault: {detector: {severity: mean}}} of a metric in a sweep_results.yaml document."""
    out: dict[str, dict[str, dict[float, float]]] = {}
    for fault, by_severity in sweep["sweep"].items():
        for severity, by_detector in by_severity.items():
            for detector, summary in by_detector.items():
                value = summary[metric]["mean"]
                out.setdefault(fault, {}).setdefault(detector, {})[float(severity)] = value
    return out
