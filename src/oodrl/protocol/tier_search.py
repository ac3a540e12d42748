"""The tier search (SPEC §19, §23): protocol version 4's common random numbers, a monotone fit
of every probe and planned verification, with protocol version 5's acceptance (a tier is
verified only once its interval reaches the target width). The impact stage runs it
(`calibrate_impact`, below): `search_fault` for a continuous fault, `verify_steps`
for a stepped one.

Why. Protocol 3 probed each tier on fresh seeds and stopped at the first probe whose 50-episode
R̃ landed within the tolerance of the level: stopping on a noisy estimate selects its luck (a
fresh check found 4 of 9 verified tiers missing their level), and tiers searched apart need not
come out ordered (on a bimodal-return agent, mild at a larger σ than moderate).
benchmarks/tier_search_sim.py compares the two.

The search (`search_fault`), for one continuous fault and every level of `levels`:

* Common random numbers. Every probe of the fault measures π on the same `search_episodes`
  reset seeds (`crn_search_seeds`), paired with π's clean return on each (`paired_estimate`,
  R̃ = 1 − mean loss / (clean mean − random mean)). The estimated curve R̂(σ) is then one
  sample curve, smooth in σ as far as the episodes are, and its crossing of a level is that
  sample's root, not whichever probe was lucky. The evaluator must make an episode a function of
  (σ, its reset seed) only (`oodrl.protocol.impact.faulty_returns` with `seeds` does: its fault
  of stream j draws from `injector_rng(seeds[0], name, j)`, the same for every probe).
* One monotone fit of every probe. The probes and the exact anchor R̃(0) = 1 are fitted by the
  isotonic non-increasing regression (`monotone_curve`); a tier's severity is where that fit
  first falls to its level, linear between fitted points (`first_crossing`). One fit for every
  tier, so mild ≤ moderate ≤ severe by construction.
* Where to probe (`_plan`). A tier is bracketed by the fitted points on either side of its
  crossing; it is resolved when both lie within the tier's tolerance (`tier_tolerance`) of the
  level (the fit, being monotone, stays within it between them, so the linear read does too),
  when the bracket is narrower than `resolution` (a jump of the sample curve), or when the fit
  stays above the level at `max_severity` (unreachable). Each probe goes to the most urgent
  unresolved tier: one the fit has not crossed yet, then one with no fitted point within its
  tolerance, then the one whose far end misses by most. It lands where a guide inside the
  bracket falls to the target (the level; half a tolerance above it when only the upper end
  misses, below it when only the lower end does): the coarse impact curve (`coarse`, if given
  and it has grid points inside the bracket) mapped affinely onto the bracket's fitted ends,
  else the monotone cubic (PCHIP) through every fitted point; kept `SAFEGUARD` (5%) of the
  bracket from either end (safeguarded regula falsi). A tier not yet crossed is aimed half a
  tolerance below its level, as far as the farther of the coarse curve's remaining drop
  (shifted through the last fitted point) and the line through the last two fitted points;
  with neither, at `max_severity`. At most `max_probes` probes; fewer when every tier is
  resolved.
* Planned verification. Each tier is re-measured at its severity on seeds of its own, never a
  probe's (`crn_verify_seeds`), in batches of `verify_batch` episodes: one batch to every tier
  (in level order), then each further batch to the tier whose CI (the paired bootstrap over all
  its batches) is widest while its half-width exceeds `ci_target`, until every tier meets the
  target, `max_verify_batches` batches are spent, or the budget is. Protocol 5's rule
  (`tier_verified`): a tier is verified only when its CI meets level ± tolerance
  (`ci_meets_level`) AND its half-width is at most `ci_target`; one still wider at the cap stays
  in the record with its CI, unverified. Why: protocol 4 accepted a CI of any width that met the
  band, and fresh episodes of all 21 runs (`benchmarks/verification_budget.py --fresh`) showed
  that this admits tiers off their level. Of 85 verified tiers whose CI reached ±0.02, none fails
  the fresh-data test; of 387 accepted wider, 59 do (half-width ≤ 0.025: 2 of 26; ≤ 0.03: 3 of
  23; ≤ 0.04: 16 of 79; > 0.04: 38 of 259), so no wider target than the declared ±0.02 is safe.
  A tier's precision is its CI (SPEC §23).
* Budget. At most `budget` impact episodes a fault, search and verification together (the
  coarse curve not counted): with the defaults, 6 probes × 100 + 50 batches × 50 = 3,100
  (protocol 4: 6 probes × 100 + 6 batches × 50 = 900). The cap is sized on the 530 measured
  tiers of the 21 runs' protocol-4 records: extrapolating each tier's n episodes to the target
  (n · (half-width / 0.02)²), a fault's verification needs 1,300 episodes at the median, 1,900
  at the 75th percentile, 2,510 at the 90th, 2,800 at the 95th and 3,500 at most (a tier: 300
  at the median, 1,000 at the 90th percentile); 2,500 covers about nine faults in ten. The
  half-width has a floor no batch narrows: the random policy's and π's clean means in R̃'s
  denominator (`paired_estimate` resamples them too), about 1.96 · (1 − R̃) · their standard
  error / the gap: from protocol 4's 30 random episodes, about 0.023 at a severe tier of the
  LunarLander and Pendulum runs, above the target (such a tier would spend the cap and stay
  unverified); so the random policy's return is measured on `random_episodes` (200) episodes,
  which puts the floor below 0.01 on every run.

Stepped faults (`verify_steps`). A stepped fault's tier is a step, read on its coarse curve by
`oodrl.protocol.impact.tier_severities` (every σ of a step is the same fault, so there is
nothing to search); it is verified by the same planned verification, and verified when its CI
meets the tier's band [the next tier's level (SEVERE_FLOOR after severe), its own level] widened
by the tolerance.

Settings: the params block `tiers.search` (`oodrl.config.TierSearchConfig`, whose
`check_seed_blocks` refuses sizes that overflow a seed block or the budget) and the largest
severity to probe (`CrnSearchConfig`).

Seeds (`oodrl.config`'s `CRN_*` offsets, beside every other block). The search's episodes reset
from `seed + CRN_SEARCH_SEED_OFFSET + j`, j < search_episodes; the fault's verification batch
b (numbered over the fault, whichever tier it goes to) from `seed + CRN_VERIFY_SEED_OFFSET +
b · verify_batch + j`, j < verify_batch: no two batches share a seed, and the clean reference
holds max_verify_batches × verify_batch verification seeds (2,500 by default), not one block a
tier. Its cost: π's clean return on each, measured once per run (`measure_reference`: 30 + 100
+ 2,500 = 2,630 clean episodes by default, protocol 4's 430; and the random policy's 200,
protocol 4's 30), against about 17,000 faulty episodes of a nine-fault run's impact stages (300
coarse and, by the extrapolation above, about 1,550 searched and verified a fault). Both
blocks lie in [seed + 900,000, seed + 1,000,000): clear of the policy's, random policy's and
protocol 3's blocks (100,000 seeds each), and of each other. Every draw is a function of `seed`
and the evaluator, so the search is deterministic given both.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import Field

from oodrl.config import (
    CRN_SEARCH_SEED_OFFSET,
    CRN_VERIFY_SEED_OFFSET,
    POLICY_SEED_OFFSET,
    RANDOM_SEED_OFFSET,
    TierSearchConfig,
)
from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.injector import OnlineInjector
from oodrl.core.policy import Policy
from oodrl.errors import ConfigError, ContractError
from oodrl.protocol.impact import (
    LEVELS,
    Estimate,
    Reference,
    Returns,
    _rounded,
    _tier_floor,
    clean_returns,
    episode_limit,
    faulty_returns,
    first_crossing,
    impact_curve_points,
    impact_record,
    monotone_curve,
    paired_estimate,
    policy_seeds,
    random_policy_returns,
    severity_steps,
    step_severities,
    tier_severity,
    tier_tolerance,
)

#: How the record says its tiers were found (protocol 3's records have no `method`).
METHOD = "common random numbers"
STEPPED_METHOD = "steps"
#: A tier whose level the fit has not reached when the probes ran out short of `max_severity`
#: (unlike UNREACHABLE, shown at `max_severity`).
NOT_REACHED = "not reached"

#: π's whole-episode returns under the fault at severity σ, one per reset seed, in order.
FaultyReturns = Callable[[float, Sequence[int]], np.ndarray]


class CrnSearchConfig(TierSearchConfig):
    """The search's settings: the params block `tiers.search` (`TierSearchConfig`: its keys,
    defaults and ranges) and `max_severity`, the largest severity it probes (the impact stage's:
    its coarse grid's largest)."""

    max_severity: float = Field(1.0, gt=0, le=1)

    @classmethod
    def from_params(cls, search: TierSearchConfig, max_severity: float = 1.0) -> CrnSearchConfig:
        """`search`'s settings, searched up to `max_severity`."""
        return cls(**{**search.model_dump(), "max_severity": float(max_severity)})


def crn_search_seeds(seed: int, config: TierSearchConfig) -> list[int]:
    """The reset seeds every probe of a fault's tier search shares (common random numbers)."""
    first = seed + CRN_SEARCH_SEED_OFFSET
    return list(range(first, first + config.search_episodes))


def crn_verify_seeds(seed: int, config: TierSearchConfig, batch: int) -> list[int]:
    """The fresh reset seeds of a fault's `batch`-th verification batch (numbered over the
    fault, whichever tier it goes to: no two batches share a seed)."""
    first = seed + CRN_VERIFY_SEED_OFFSET + batch * config.verify_batch
    return list(range(first, first + config.verify_batch))


def crn_reference_seeds(seed: int, config: TierSearchConfig) -> list[int]:
    """Every reset seed whose clean return the search or a verification may read (the
    `Reference` must hold them, `measure_reference` measures them): the
    common search seeds, then every verification batch a fault may spend."""
    verify = [
        s
        for batch in range(config.max_verify_batches)
        for s in crn_verify_seeds(seed, config, batch)
    ]
    return [*crn_search_seeds(seed, config), *verify]


def ci_meets_level(
    estimate: Estimate, level: float, tolerance: float, floor: float | None = None
) -> bool:
    """Whether the estimate's CI meets the band level ± `tier_tolerance(level, tolerance)`;
    a stepped tier's band is [floor, level] (floor: the next tier's level) widened as much."""
    low, high = estimate.ci
    widen = tier_tolerance(level, tolerance)
    return bool(low <= level + widen and high >= (level if floor is None else floor) - widen)


def half_width(estimate: Estimate) -> float:
    """Half the CI's width."""
    return (estimate.ci[1] - estimate.ci[0]) / 2


def ci_target_met(estimate: Estimate, ci_target: float) -> bool:
    """Whether the CI is as narrow as the verification aims for: half-width ≤ `ci_target`."""
    return bool(half_width(estimate) <= ci_target)


def tier_verified(
    estimate: Estimate, level: float, config: TierSearchConfig, floor: float | None = None
) -> bool:
    """Protocol 5's rule: a tier is verified only when its verification CI meets its band
    (`ci_meets_level`) and is no wider than ± `config.ci_target`. A wide CI meets the band
    by its width alone: fresh episodes show tiers accepted that way off their level (module
    docstring), none of those whose CI reached ±0.02."""
    return ci_meets_level(estimate, level, config.tolerance, floor) and ci_target_met(
        estimate, config.ci_target
    )


def fitted_curve(probes: Sequence[Estimate]) -> tuple[np.ndarray, np.ndarray]:
    """(severities, monotone R̃) of the probes with the anchor (0, 1), sorted by severity."""
    ordered = sorted(probes, key=lambda e: e.severity)
    xs = np.array([0.0, *(e.severity for e in ordered)], dtype=np.float64)
    ys = np.array([1.0, *(e.normalised for e in ordered)], dtype=np.float64)
    return xs, monotone_curve(xs, ys)


@dataclass(frozen=True)
class _Plan:
    """One tier's state on the fitted curve: its bracket, whether it is resolved (or
    unreachable), where it would be probed next (None when resolved), and how urgently: first
    tiers the fit has not crossed yet (the farthest above its level first), then tiers with no
    fitted point within the tolerance (the farthest nearest point first), then the rest (the
    farthest far end first)."""

    bracket: tuple[float, float | None]
    resolved: bool
    unreachable: bool
    next_severity: float | None
    priority: tuple[int, float]


#: A probe inside a bracket lands at least this share of its width from either end
#: (safeguarded regula falsi: every probe shrinks the bracket by at least that much).
SAFEGUARD = 0.05
#: Points per unit of σ at which the guide is evaluated to find its crossing.
_GUIDE_POINTS = 1024


def _guide_crossing(
    lo: float,
    hi: float,
    y_lo: float,
    y_hi: float,
    target: float,
    xs: np.ndarray,
    fit: np.ndarray,
    coarse,
) -> float | None:
    """Where the guide falls to `target` inside the bracket [lo, hi] (fitted values y_lo >
    target ≥ y_hi): the coarse curve mapped affinely through (lo, y_lo) and (hi, y_hi) where
    the coarse grid has points inside the bracket, else the monotone cubic (PCHIP) through
    every fitted point, whose curvature the neighbouring probes give."""
    if coarse is not None:
        cx, cy = coarse
        inner = [float(x) for x in cx if lo < x < hi]
        c_lo, c_hi = float(np.interp(lo, cx, cy)), float(np.interp(hi, cx, cy))
        if inner and c_lo - c_hi > 1e-12:
            mapped = c_lo - (y_lo - target) / (y_lo - y_hi) * (c_lo - c_hi)
            sub_y = [c_lo, *(float(np.interp(x, cx, cy)) for x in inner), c_hi]
            return first_crossing([lo, *inner, hi], sub_y, mapped)
    if xs.size < 3:
        return lo + (y_lo - target) / (y_lo - y_hi) * (hi - lo)
    from scipy.interpolate import PchipInterpolator

    grid = np.linspace(lo, hi, max(int(_GUIDE_POINTS * (hi - lo)), 16) + 1)
    curve = PchipInterpolator(xs, fit)(grid)
    curve[0], curve[-1] = y_lo, y_hi
    return first_crossing(grid, curve, target)


def _plan(
    level: float,
    tolerance: float,
    xs: np.ndarray,
    fit: np.ndarray,
    config: CrnSearchConfig,
    coarse,
) -> _Plan:
    """The tier's bracket on the fitted curve and, unless it is resolved, its next probe."""
    below = np.flatnonzero(fit <= level)
    if below.size == 0:
        lo, y_lo = float(xs[-1]), float(fit[-1])
        if lo >= config.max_severity:
            return _Plan((lo, None), True, True, None, (0, 0.0))
        # Aimed half a tolerance past the level, so that the probe likely closes the bracket,
        # as far as the larger of two guesses: the coarse curve's remaining drop past lo
        # shifted through the fitted value there, and the line through the last two fitted
        # points. Neither (no coarse curve, no probe yet): the largest severity.
        target = level - tolerance / 2
        guesses = []
        if coarse is not None:
            cx, cy = coarse
            shifted = np.asarray(cy, dtype=np.float64) - float(np.interp(lo, cx, cy)) + y_lo
            sub_x = [lo, *(x for x in cx if lo < x < config.max_severity), config.max_severity]
            crossing = first_crossing(sub_x, np.interp(sub_x, cx, shifted), target)
            guesses.append(config.max_severity if crossing is None else crossing)
        if xs.size >= 2 and fit[-2] > fit[-1]:
            slope = (fit[-2] - fit[-1]) / (xs[-1] - xs[-2])
            guesses.append(lo + (y_lo - target) / slope)
        severity = max(guesses) if guesses else config.max_severity
        width = config.max_severity - lo
        severity = min(max(severity, lo + SAFEGUARD * width), config.max_severity)
        return _Plan((lo, None), False, False, round(float(severity), 6), (2, y_lo - level))
    i = int(below[0])  # ≥ 1: the fit starts at ≥ 1 (the anchor), above every level
    lo, hi, y_lo, y_hi = float(xs[i - 1]), float(xs[i]), float(fit[i - 1]), float(fit[i])
    above, under = y_lo - level, level - y_hi
    miss = max(above, under)
    if miss <= tolerance or hi - lo <= config.resolution:
        return _Plan((lo, hi), True, False, None, (0, 0.0))
    # Aim so that the probe closes the side still out of tolerance: half a tolerance above the
    # level when only the upper end misses, below it when only the lower end does.
    target = level
    if under <= tolerance:
        target = level + tolerance / 2
    elif above <= tolerance:
        target = level - tolerance / 2
    guess = _guide_crossing(lo, hi, y_lo, y_hi, target, xs, fit, coarse)
    guess = lo + 0.5 * (hi - lo) if guess is None else guess
    width = hi - lo
    severity = min(max(guess, lo + SAFEGUARD * width), hi - SAFEGUARD * width)
    nearest = min(above, under)
    priority = (1, nearest) if nearest > tolerance else (0, miss)
    return _Plan((lo, hi), False, False, round(float(severity), 6), priority)


@dataclass(frozen=True)
class TierResult:
    """One tier: its severity (None: the fit never falls to the level, `unreachable` when it
    was probed at `max_severity`, else not reached before the probes ran out), the bracket of
    fitted points around it (upper end None: not crossed; no bracket: a stepped fault's step),
    whether the search resolved it (both ends within the tolerance, a jump, or shown
    unreachable), and its verification (None if not measured)."""

    name: str
    level: float
    severity: float | None
    bracket: tuple[float, float | None] | None
    resolved: bool
    unreachable: bool = False
    verification: Estimate | None = None
    batches: int = 0
    verified: bool = False

    def as_dict(self, ci_target: float) -> dict[str, Any]:
        """The tier as impact.yaml holds it: level, severity (a number, "unreachable" or "not
        reached"), the search's bracket, and the verification: R̃ there with its CI and
        episodes, the batches, the CI's half-width against `ci_target`, and `verified`."""
        severity = _rounded(self.severity)
        if self.severity is None and not self.unreachable:
            severity = NOT_REACHED
        record: dict[str, Any] = {"level": float(self.level), "severity": severity}
        if self.bracket is not None:
            lo, hi = self.bracket
            record["search"] = {
                "bracket": [_rounded(lo), None if hi is None else _rounded(hi)],
                "resolved": bool(self.resolved),
            }
        if self.verification is not None:
            record["verification"] = {
                **self.verification.as_dict(),
                "batches": int(self.batches),
                "half_width": _rounded(half_width(self.verification)),
                "ci_target_met": ci_target_met(self.verification, ci_target),
                "verified": bool(self.verified),
            }
        return record


@dataclass(frozen=True)
class FaultTiers:
    """A fault's tiers: every probe (in probe order), the fitted curve (σ = 0
    included; None for a stepped fault, whose tiers are steps), each tier, and the episodes
    spent."""

    probes: list[Estimate]
    curve: tuple[list[float], list[float]] | None
    tiers: dict[str, TierResult]
    search_episodes: int
    verification_episodes: int
    config: TierSearchConfig
    seed: int
    verify_seeds: dict[str, list[int]] = field(default_factory=dict)

    @property
    def episodes(self) -> int:
        return self.search_episodes + self.verification_episodes

    def severities(self) -> dict[str, float | None]:
        return {name: tier.severity for name, tier in self.tiers.items()}

    def as_dict(self) -> dict[str, Any]:
        """The record as YAML holds it (floats rounded as impact.yaml's; plain values only):
        how the tiers were found, the seeds, every probe (σ, R̃ with its CI, episodes) and the
        monotone fit of them (continuous faults), each tier, and the episodes spent."""
        # Each tier's batches, [first, last] seed of each (numbered over the fault, a tier's
        # batches need not be adjacent).
        size = self.config.verify_batch
        verification = {
            name: [[seeds[i], seeds[i + size - 1]] for i in range(0, len(seeds), size)]
            for name, seeds in self.verify_seeds.items()
        }
        record: dict[str, Any] = {"method": STEPPED_METHOD}
        if self.curve is not None:
            search = crn_search_seeds(self.seed, self.config)
            record = {
                "method": METHOD,
                "seeds": {"search": [search[0], search[-1]], "verification": verification},
                "probes": [p.as_dict() for p in self.probes],
                "fit": [
                    {"severity": _rounded(x), "monotone": _rounded(y)}
                    for x, y in zip(*self.curve, strict=True)
                ],
            }
        else:
            record["seeds"] = {"verification": verification}
        return {
            **record,
            "tiers": {name: t.as_dict(self.config.ci_target) for name, t in self.tiers.items()},
            "episodes": {
                "search": self.search_episodes,
                "verification": self.verification_episodes,
                "total": self.episodes,
                "budget": self.config.budget,
            },
        }


def _measure(
    faulty: FaultyReturns,
    reference: Reference,
    severity: float,
    seeds: Sequence[int],
) -> tuple[np.ndarray, np.ndarray]:
    """(π's returns under the fault on `seeds`, π's clean returns on the same seeds)."""
    returns = np.asarray(faulty(float(severity), list(seeds)), dtype=np.float64)
    if returns.shape != (len(seeds),):
        raise ContractError(
            f"The evaluator returned shape {returns.shape} for {len(seeds)} seeds at "
            f"severity {severity}; one return per seed is required."
        )
    return returns, reference.returns(seeds)


def search_curve(
    faulty: FaultyReturns,
    reference: Reference,
    *,
    seed: int,
    config: CrnSearchConfig,
    levels: Mapping[str, float] = LEVELS,
    coarse: tuple[Sequence[float], Sequence[float]] | None = None,
    n_boot: int = 1000,
    ci: float = 0.95,
) -> list[Estimate]:
    """The probes of one fault's search on its common seeds (module docstring), in order."""
    seeds = crn_search_seeds(seed, config)
    probes: list[Estimate] = []
    for _ in range(config.max_probes):
        xs, fit = fitted_curve(probes)
        plans = [
            _plan(level, tier_tolerance(level, config.tolerance), xs, fit, config, coarse)
            for level in levels.values()
        ]
        pending = [p for p in plans if p.next_severity is not None]
        probed = {e.severity for e in probes}
        pending = [p for p in pending if p.next_severity not in probed]
        if not pending:
            break
        # The most urgent (`_Plan`); among equals, the first tier (the highest level).
        plan = max(pending, key=lambda p: p.priority)
        returns, clean = _measure(faulty, reference, plan.next_severity, seeds)
        probes.append(
            paired_estimate(
                plan.next_severity, returns, clean, reference, n_boot=n_boot, ci=ci, seed=seed
            )
        )
    return probes


def verify_tiers(
    faulty: FaultyReturns,
    reference: Reference,
    severities: Mapping[str, float | None],
    *,
    seed: int,
    config: TierSearchConfig,
    batches: int,
    levels: Mapping[str, float] = LEVELS,
    n_boot: int = 1000,
    ci: float = 0.95,
) -> tuple[dict[str, tuple[Estimate, int]], dict[str, list[int]]]:
    """Planned verification of the tiers at `severities` (None: not measured) with at most
    `batches` batches: one to each tier in level order, then to the widest CI above the target.
    Returns ({tier: (estimate over its batches, batches)}, {tier: the seeds it used})."""
    index = {name: i for i, name in enumerate(levels)}
    data: dict[str, tuple[list[np.ndarray], list[np.ndarray]]] = {}
    estimates: dict[str, Estimate] = {}
    used: dict[str, list[int]] = {}
    targets = [name for name in levels if severities.get(name) is not None]
    for batch in range(batches):  # each iteration measures one batch or stops
        first = [name for name in targets if name not in estimates]
        if first:
            name = first[0]
        else:
            wide = [n for n in targets if not ci_target_met(estimates[n], config.ci_target)]
            if not wide:
                break
            name = max(wide, key=lambda n: (half_width(estimates[n]), -index[n]))
        returns_list, clean_list = data.setdefault(name, ([], []))
        if len(returns_list) >= config.max_verify_batches:
            break
        seeds = crn_verify_seeds(seed, config, batch)
        returns, clean = _measure(faulty, reference, severities[name], seeds)
        returns_list.append(returns)
        clean_list.append(clean)
        used.setdefault(name, []).extend(seeds)
        estimates[name] = paired_estimate(
            severities[name],
            np.concatenate(returns_list),
            np.concatenate(clean_list),
            reference,
            n_boot=n_boot,
            ci=ci,
            seed=seed,
        )
    return {n: (estimates[n], len(data[n][0])) for n in estimates}, used


def search_fault(
    faulty: FaultyReturns,
    reference: Reference,
    *,
    seed: int,
    config: CrnSearchConfig | None = None,
    levels: Mapping[str, float] = LEVELS,
    coarse: tuple[Sequence[float], Sequence[float]] | None = None,
    n_boot: int = 1000,
    ci: float = 0.95,
) -> FaultTiers:
    """Every tier of one continuous fault by the search and planned verification
    (module docstring). `faulty(σ, seeds)`: π's returns under the fault at σ, one per seed;
    `reference`: π's clean returns on every seed of `crn_reference_seeds` and the random
    policy's; `coarse`: the coarse monotone curve (σ = 0 included, `impact_curve_points`), a
    guide for where to probe, never part of the fit."""
    config = config or CrnSearchConfig()
    _check(reference, seed, config, levels)
    if coarse is not None:
        coarse = (
            np.asarray(coarse[0], dtype=np.float64),
            np.asarray(coarse[1], dtype=np.float64),
        )
    probes = search_curve(
        faulty,
        reference,
        seed=seed,
        config=config,
        levels=levels,
        coarse=coarse,
        n_boot=n_boot,
        ci=ci,
    )
    xs, fit = fitted_curve(probes)
    severities: dict[str, float | None] = {}
    plans: dict[str, _Plan] = {}
    for name, level in levels.items():
        plans[name] = _plan(level, tier_tolerance(level, config.tolerance), xs, fit, config, None)
        crossing = first_crossing(xs, fit, level)
        severities[name] = None if crossing is None else round(crossing, 6)
    return _verified(
        faulty, reference, severities, plans, probes, (xs, fit),
        seed=seed, config=config, levels=levels, n_boot=n_boot, ci=ci,
    )  # fmt: skip


def verify_steps(
    faulty: FaultyReturns,
    reference: Reference,
    severities: Mapping[str, float | None],
    *,
    seed: int,
    config: TierSearchConfig | None = None,
    levels: Mapping[str, float] = LEVELS,
    n_boot: int = 1000,
    ci: float = 0.95,
) -> FaultTiers:
    """Every tier of one stepped fault: the step its coarse curve gives (`severities`, None =
    unreachable: `oodrl.protocol.impact.tier_severities` with `stepped`), verified by the
    planned verification against the tier's band (module docstring). `faulty` and `reference`
    as `search_fault`'s."""
    config = config or TierSearchConfig()
    _check(reference, seed, config, levels)
    return _verified(
        faulty, reference, severities, None, [], None,
        seed=seed, config=config, levels=levels, n_boot=n_boot, ci=ci,
    )  # fmt: skip


def _verified(
    faulty: FaultyReturns,
    reference: Reference,
    severities: Mapping[str, float | None],
    plans: Mapping[str, _Plan] | None,
    probes: list,
    curve: tuple[np.ndarray, np.ndarray] | None,
    *,
    seed: int,
    config: TierSearchConfig,
    levels: Mapping[str, float],
    n_boot: int,
    ci: float,
) -> FaultTiers:
    """The planned verification of `severities` on what the search (`probes`) left of the
    budget, and the fault's record. A searched tier carries its plan (`plans`) and is verified
    against level ± tolerance; without plans (a stepped fault) each tier is a step, verified
    against its band."""
    spent = len(probes) * config.search_episodes
    batches = min(config.max_verify_batches, (config.budget - spent) // config.verify_batch)
    verified, used = verify_tiers(
        faulty,
        reference,
        severities,
        seed=seed,
        config=config,
        batches=batches,
        levels=levels,
        n_boot=n_boot,
        ci=ci,
    )
    tiers = {}
    for name, level in levels.items():
        estimate, n_batches = verified.get(name, (None, 0))
        plan = plans[name] if plans is not None else None
        floor = None if plans is not None else _tier_floor(name, levels)
        tiers[name] = TierResult(
            name=name,
            level=level,
            severity=severities.get(name),
            bracket=plan.bracket if plan else None,
            resolved=plan.resolved if plan else True,
            unreachable=plan.unreachable if plan else severities.get(name) is None,
            verification=estimate,
            batches=n_batches,
            verified=estimate is not None and tier_verified(estimate, level, config, floor),
        )
    return FaultTiers(
        probes=probes,
        curve=None
        if curve is None
        else ([float(x) for x in curve[0]], [float(y) for y in curve[1]]),
        tiers=tiers,
        search_episodes=spent,
        verification_episodes=sum(len(s) for s in used.values()),
        config=config,
        seed=seed,
        verify_seeds=used,
    )


def _check(
    reference: Reference, seed: int, config: TierSearchConfig, levels: Mapping[str, float]
) -> None:
    """Refuse settings that overflow a seed block or the budget, and a reference that lacks a
    clean return the search or a verification may read."""
    config.check_seed_blocks(len(levels))
    missing = sorted(set(crn_reference_seeds(seed, config)) - set(reference.clean))
    if missing:
        raise ContractError(
            f"The impact reference holds no clean return of {len(missing)} seeds the tier "
            f"search may use (first {missing[0]}); measure it on "
            "`crn_reference_seeds` (re-run the impact_reference stage)."
        )


# -- the impact stage's calibration: the coarse curve, then the tiers ------------------------
def reference_seeds(seed: int, n_episodes: int, search: TierSearchConfig) -> list[int]:
    """Every reset seed whose clean return an impact stage reads: the coarse curve's, then the
    tier search's and every verification batch's (`tier_search.crn_reference_seeds`)."""
    return [*policy_seeds(seed, n_episodes), *crn_reference_seeds(seed, search)]


def measure_reference(
    adapter: EnvironmentAdapter,
    policy: Policy,
    n_episodes: int,
    search: TierSearchConfig,
    *,
    seed: int,
    horizon: int,
    workers: int = 1,
) -> Reference:
    """π's clean returns on every seed of `reference_seeds` (one collection) and the random
    policy's on `search.random_episodes` seeds of its own."""
    seeds = reference_seeds(seed, n_episodes, search)
    clean = clean_returns(
        adapter, policy, len(seeds), seed=seed, horizon=horizon, workers=workers, seeds=seeds
    )
    random = random_policy_returns(adapter, search.random_episodes, seed=seed, horizon=horizon)
    return Reference(
        {s: float(r) for s, r in zip(seeds, clean, strict=True)}, random, policy.sha256
    )


def calibrate_impact(
    adapter: EnvironmentAdapter,
    policy: Policy,
    injectors: Mapping[str, OnlineInjector],
    severities: Sequence[float],
    n_episodes: int,
    *,
    search: TierSearchConfig | None = None,
    reference: Reference | None = None,
    seed: int = 0,
    horizon: int | None = None,
    n_boot: int = 1000,
    ci: float = 0.95,
    workers: int = 1,
) -> dict[str, Any]:
    """The impact document of one (environment, policy): every fault's coarse curve on
    `severities` and its tiers, searched for and verified by the tier search up to the
    grid's largest severity (SPEC §19, §23; module docstring). `reference`: π's clean returns on
    every seed used and the random policy's (`measure_reference`; measured here when not
    given)."""
    if n_episodes < 2:
        raise ConfigError(f"Impact calibration needs n_episodes >= 2; got {n_episodes}.")
    if not severities:
        raise ConfigError("The severity grid must hold at least one severity.")
    config = CrnSearchConfig.from_params(search or TierSearchConfig(), max(severities))
    config.check_seed_blocks(len(LEVELS))
    horizon = horizon or episode_limit(adapter)
    if reference is None:
        reference = measure_reference(
            adapter, policy, n_episodes, config, seed=seed, horizon=horizon, workers=workers
        )
    if reference.policy_sha256 != policy.sha256:
        raise ContractError(
            f"The impact reference was measured with policy {reference.policy_sha256[:12]}, "
            f"not this one ({policy.sha256[:12]}); re-run its stage (impact_reference)."
        )
    missing = sorted(set(reference_seeds(seed, n_episodes, config)) - set(reference.clean))
    if missing:
        raise ContractError(
            f"The impact reference holds no clean return of {len(missing)} seeds this search "
            f"uses (first {missing[0]}); re-run its stage (impact_reference) with these params."
        )
    if len(reference.random) != config.random_episodes:
        raise ContractError(
            f"The impact reference holds {len(reference.random)} random-policy returns, not the "
            f"{config.random_episodes} of tiers.search.random_episodes; re-run its stage "
            "(impact_reference) with these params."
        )
    clean, random = reference.returns(policy_seeds(seed, n_episodes)), reference.random
    faults = {}
    for name in sorted(injectors):
        injector = injectors[name]
        steps = severity_steps(injector, adapter)
        faulty = faulty_returns(
            adapter, policy, injector, step_severities(steps) if steps else severities,
            n_episodes, seed=seed, horizon=horizon, workers=workers,
        )  # fmt: skip
        record = impact_record(
            Returns(clean, faulty, random), n_boot=n_boot, ci=ci, seed=seed, stepped=bool(steps)
        )

        def evaluate(severity: float, seeds: Sequence[int], injector=injector) -> np.ndarray:
            """π's returns under the fault at `severity` on `seeds` (a function of both)."""
            return faulty_returns(
                adapter, policy, injector, [severity], len(seeds), seed=seed, horizon=horizon,
                workers=workers, seeds=seeds,
            )[float(severity)]  # fmt: skip

        if steps:
            found = verify_steps(
                evaluate, reference, {n: tier_severity(t) for n, t in record["tiers"].items()},
                seed=seed, config=config, n_boot=n_boot, ci=ci,
            )  # fmt: skip
        else:
            found = search_fault(
                evaluate, reference, seed=seed, config=config,
                coarse=impact_curve_points(record), n_boot=n_boot, ci=ci,
            )  # fmt: skip
        tier_search = found.as_dict()
        record["tiers"] = tier_search.pop("tiers")
        faults[name] = {
            **record,
            "tier_search": tier_search,
            "mode": injector.mode,
            "params": {k: v for k, v in sorted(injector.get_params().items()) if k != "severity"},
            **({"severity_steps": steps} if steps else {}),
        }
    n = n_episodes
    crn = reference_seeds(seed, n, config)[n:]
    return {
        "env_id": adapter.env_id,
        "policy_sha256": policy.sha256,
        "levels": dict(LEVELS),
        "horizon": horizon,
        "n_episodes": n,
        "n_boot": n_boot,
        "ci": ci,
        "seed": seed,
        "search": config.model_dump(mode="json"),
        "seeds": {
            "policy": [seed + POLICY_SEED_OFFSET, seed + POLICY_SEED_OFFSET + n - 1],
            "random": [seed + RANDOM_SEED_OFFSET, seed + RANDOM_SEED_OFFSET + len(random) - 1],
            "search": [crn[0], crn[config.search_episodes - 1]],
            "verification": [crn[config.search_episodes], crn[-1]],
        },
        "clean_return": _rounded(clean.mean()),
        "random_return": _rounded(random.mean()),
        "faults": faults,
    }
