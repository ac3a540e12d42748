"""Protocol version 4's tier search (SPEC §19): common random numbers, a monotone fit of every
probe, and planned verification. Not yet called by any stage; `oodrl.protocol.impact`'s
`searched_tiers` (protocol 3) is what the impact stage runs.

Why. Protocol 3 probes each tier on fresh seeds and stops at the first probe whose 50-episode
R̃ lands within the tolerance of the level: stopping on a noisy estimate selects its luck (a
fresh check found 4 of 9 verified tiers missing their level), and tiers searched apart need not
come out ordered (on a bimodal-return agent, mild at a larger σ than moderate).

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
  target, `max_verify_batches` batches are spent, or the budget is. A tier is verified when its
  CI meets level ± tolerance (`ci_meets_level`).
* Budget. At most `budget` impact episodes a fault, search and verification together (the
  coarse curve, shared with protocol 3, not counted): with the defaults, 6 probes × 100 +
  6 batches × 50 = 900, against protocol 3's 4 tiers × (4 probes × 50 + 100) = 1,200.

Seeds (same style as `search_seeds`/`verify_seeds`, other streams). The search's episodes reset
from `seed + CRN_SEARCH_SEED_OFFSET + j`, j < search_episodes; tier i's verification batch b
from `seed + CRN_VERIFY_SEED_OFFSET + (i · max_verify_batches + b) · verify_batch + j`,
j < verify_batch. Both blocks lie in [seed + 900,000, seed + 1,000,000): clear of the policy's,
random policy's, protocol 3's probes' and verifications' blocks (`oodrl.config`'s
`*_SEED_OFFSET`, 100,000 seeds each), and of each other (`CrnSearchConfig` refuses sizes that
would overflow a block). Every draw is a function of `seed` and the evaluator, so the search is
deterministic given both.

Continuous faults only: a stepped fault's tier is a step (`tier_severities`, stepped), which
keeps protocol 3's rule.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from oodrl.errors import ConfigError, ContractError
from oodrl.protocol.impact import (
    LEVELS,
    Estimate,
    Reference,
    _rounded,
    first_crossing,
    monotone_curve,
    paired_estimate,
    tier_tolerance,
)

#: How the record says it was searched (protocol 3's records have no `method`).
METHOD = "common random numbers"
#: The search's common episodes at seed + CRN_SEARCH_SEED_OFFSET + j; the verification batches
#: at seed + CRN_VERIFY_SEED_OFFSET + … (module docstring). Both inside the block of 100,000
#: seeds from seed + 900,000, which no other impact seed uses.
CRN_SEARCH_SEED_OFFSET = 900_000
CRN_VERIFY_SEED_OFFSET = 950_000
_BLOCK_END = 1_000_000
#: A tier whose level the fit has not reached when the probes ran out short of `max_severity`
#: (unlike UNREACHABLE, shown at `max_severity`).
NOT_REACHED = "not reached"

#: π's whole-episode returns under the fault at severity σ, one per reset seed, in order.
FaultyReturns = Callable[[float, Sequence[int]], np.ndarray]


@dataclass(frozen=True)
class CrnSearchConfig:
    """Protocol 4's tier search settings (module docstring). `tolerance` is the tiers' as in
    `TierSearchConfig` (capped per tier by `tier_tolerance`); `ci_target` the verification CI's
    half-width to reach; `budget` the most search + verification episodes a fault."""

    search_episodes: int = 100
    max_probes: int = 6
    tolerance: float = 0.015
    verify_batch: int = 50
    max_verify_batches: int = 6
    ci_target: float = 0.02
    budget: int = 900
    max_severity: float = 1.0
    resolution: float = 1e-3

    def __post_init__(self) -> None:
        checks = [
            (self.search_episodes >= 2, "search_episodes must be >= 2"),
            (self.max_probes >= 1, "max_probes must be >= 1"),
            (0 < self.tolerance < 1, "tolerance must be in (0, 1)"),
            (self.verify_batch >= 2, "verify_batch must be >= 2"),
            (self.max_verify_batches >= 1, "max_verify_batches must be >= 1"),
            (self.ci_target > 0, "ci_target must be > 0"),
            (0 < self.max_severity <= 1, "max_severity must be in (0, 1]"),
            (self.resolution > 0, "resolution must be > 0"),
            (
                self.search_episodes <= CRN_VERIFY_SEED_OFFSET - CRN_SEARCH_SEED_OFFSET,
                "search_episodes overflows the search's seed block",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"Tier search (protocol 4): {message}; got {self}.")

    def check_budget(self, n_tiers: int) -> None:
        """Refuse settings whose verification seeds overflow their block, or whose budget
        cannot give every tier one verification batch after the most probes."""
        if n_tiers * self.max_verify_batches * self.verify_batch > _BLOCK_END - (
            CRN_VERIFY_SEED_OFFSET
        ):
            raise ConfigError(
                f"Tier search (protocol 4): {n_tiers} tiers × {self.max_verify_batches} batches "
                f"× {self.verify_batch} episodes overflow the verification's seed block."
            )
        need = self.max_probes * self.search_episodes + n_tiers * self.verify_batch
        if need > self.budget:
            raise ConfigError(
                f"Tier search (protocol 4): budget {self.budget} is below {need}, the most "
                f"probes ({self.max_probes} × {self.search_episodes}) and one verification "
                f"batch of {self.verify_batch} for each of {n_tiers} tiers."
            )


def crn_search_seeds(seed: int, config: CrnSearchConfig) -> list[int]:
    """The reset seeds every probe of a fault's tier search shares (common random numbers)."""
    first = seed + CRN_SEARCH_SEED_OFFSET
    return list(range(first, first + config.search_episodes))


def crn_verify_seeds(seed: int, config: CrnSearchConfig, tier_index: int, batch: int) -> list[int]:
    """The fresh reset seeds of verification batch `batch` of the `tier_index`-th tier."""
    first = (
        seed
        + CRN_VERIFY_SEED_OFFSET
        + (tier_index * config.max_verify_batches + batch) * config.verify_batch
    )
    return list(range(first, first + config.verify_batch))


def crn_reference_seeds(
    seed: int, config: CrnSearchConfig, levels: Mapping[str, float] = LEVELS
) -> list[int]:
    """Every reset seed whose clean return the search may read (the `Reference` must hold
    them): the common search seeds, then every verification batch of every tier."""
    verify = [
        s
        for tier_index in range(len(levels))
        for batch in range(config.max_verify_batches)
        for s in crn_verify_seeds(seed, config, tier_index, batch)
    ]
    return [*crn_search_seeds(seed, config), *verify]


def ci_meets_level(estimate: Estimate, level: float, tolerance: float) -> bool:
    """Whether the estimate's CI meets the band level ± `tier_tolerance(level, tolerance)`."""
    low, high = estimate.ci
    widen = tier_tolerance(level, tolerance)
    return bool(low <= level + widen and high >= level - widen)


def half_width(estimate: Estimate) -> float:
    """Half the CI's width."""
    return (estimate.ci[1] - estimate.ci[0]) / 2


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
    fitted points around it (upper end None: not crossed), whether the search resolved it (both
    ends within the tolerance, a jump, or shown unreachable), and its verification (None if
    not measured)."""

    name: str
    level: float
    severity: float | None
    bracket: tuple[float, float | None]
    resolved: bool
    unreachable: bool = False
    verification: Estimate | None = None
    batches: int = 0
    verified: bool = False

    def as_dict(self, ci_target: float) -> dict[str, Any]:
        severity = _rounded(self.severity)
        if self.severity is None and not self.unreachable:
            severity = NOT_REACHED
        lo, hi = self.bracket
        record: dict[str, Any] = {
            "level": self.level,
            "severity": severity,
            "search": {
                "bracket": [_rounded(lo), None if hi is None else _rounded(hi)],
                "resolved": self.resolved,
            },
        }
        if self.verification is not None:
            record["verification"] = {
                **self.verification.as_dict(),
                "batches": self.batches,
                "half_width": _rounded(half_width(self.verification)),
                "ci_target_met": half_width(self.verification) <= ci_target,
                "verified": self.verified,
            }
        return record


@dataclass(frozen=True)
class FaultTiers:
    """A fault's protocol-4 tiers: every probe (in probe order), the fitted curve (σ = 0
    included), each tier, and the episodes spent."""

    probes: list[Estimate]
    curve: tuple[list[float], list[float]]
    tiers: dict[str, TierResult]
    search_episodes: int
    verification_episodes: int
    config: CrnSearchConfig
    seed: int
    verify_seeds: dict[str, list[int]] = field(default_factory=dict)

    @property
    def episodes(self) -> int:
        return self.search_episodes + self.verification_episodes

    def severities(self) -> dict[str, float | None]:
        return {name: tier.severity for name, tier in self.tiers.items()}

    def as_dict(self) -> dict[str, Any]:
        """The record as YAML holds it (floats rounded as impact.yaml's)."""
        search = crn_search_seeds(self.seed, self.config)
        return {
            "method": METHOD,
            "search": asdict(self.config),
            "seeds": {
                "search": [search[0], search[-1]],
                "verification": {
                    name: [seeds[0], seeds[-1]] for name, seeds in self.verify_seeds.items()
                },
            },
            "probes": [p.as_dict() for p in self.probes],
            "curve": [
                {"severity": _rounded(x), "monotone": _rounded(y)}
                for x, y in zip(*self.curve, strict=True)
            ],
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
    config: CrnSearchConfig,
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
    for _ in range(batches):
        first = [name for name in targets if name not in estimates]
        if first:
            name = first[0]
        else:
            wide = [n for n in targets if half_width(estimates[n]) > config.ci_target]
            if not wide:
                break
            name = max(wide, key=lambda n: (half_width(estimates[n]), -index[n]))
        returns_list, clean_list = data.setdefault(name, ([], []))
        if len(returns_list) >= config.max_verify_batches:
            break
        seeds = crn_verify_seeds(seed, config, index[name], len(returns_list))
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
    """Every tier of one continuous fault by protocol 4's search and planned verification
    (module docstring). `faulty(σ, seeds)`: π's returns under the fault at σ, one per seed;
    `reference`: π's clean returns on every seed of `crn_reference_seeds` and the random
    policy's; `coarse`: the coarse monotone curve (σ = 0 included, `impact_curve_points`), a
    guide for where to probe, never part of the fit."""
    config = config or CrnSearchConfig()
    config.check_budget(len(levels))
    missing = sorted(set(crn_reference_seeds(seed, config, levels)) - set(reference.clean))
    if missing:
        raise ContractError(
            f"The impact reference holds no clean return of {len(missing)} seeds the tier "
            f"search (protocol 4) may use (first {missing[0]}); measure it on "
            "`crn_reference_seeds`."
        )
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
    search_spent = len(probes) * config.search_episodes
    batches = min(config.max_verify_batches, (config.budget - search_spent) // config.verify_batch)
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
        tiers[name] = TierResult(
            name=name,
            level=level,
            severity=severities[name],
            bracket=plans[name].bracket,
            resolved=plans[name].resolved,
            unreachable=plans[name].unreachable,
            verification=estimate,
            batches=n_batches,
            verified=estimate is not None and ci_meets_level(estimate, level, config.tolerance),
        )
    return FaultTiers(
        probes=probes,
        curve=([float(x) for x in xs], [float(y) for y in fit]),
        tiers=tiers,
        search_episodes=search_spent,
        verification_episodes=sum(len(s) for s in used.values()),
        config=config,
        seed=seed,
        verify_seeds=used,
    )
