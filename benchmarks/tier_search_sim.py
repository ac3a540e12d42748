"""Protocol 3's tier search against protocol 4's on a simulated fault with a known impact curve.

    python benchmarks/tier_search_sim.py [--draws 100] [--fault bimodal|smooth] [--n-boot 1000]
        [--seed 0]

No simulator: π's whole-episode return is a closed-form function of (σ, reset seed), as the
collector's episodes are of theirs, so both searches see common random numbers wherever they
reuse a seed. The `bimodal` fault (the default) is the agent of the fresh check: π's clean
return comes from two modes (240 ± 15 with probability 0.7, else 40 ± 20), the random policy's
is −100 ± 30, and under the fault each episode crashes to −60 ± 30 once σ passes a threshold of
its own (P(τ < σ) = σ²), losing 10σ besides; R̃_true(σ) = 1 − (240 σ² + 10σ) / 280. The
`smooth` fault loses 300 (1 − R̃_true(σ)) (1 + 0.2 z) + 5σ w per episode (z, w standard normal
per seed), R̃_true(σ) = 1 − 0.5σ − 0.25σ².

Each draw is a fresh world (every episode's latent variables drawn anew) and runs, on the same
coarse impact curve (`impact_record` over the default `tiers.grid` on 30 episodes, the impact
stage's), both:

* protocol 3: its search (`searched_tiers` below, the impact stage's until protocol 4, kept
  here only for this comparison) with version 3's default `tiers.search` (`Protocol3Search`:
  tolerance 0.015, 50 fresh episodes a probe, 4 probes a tier, 100 verification episodes), its
  `measure` the impact stage's (`paired_estimate` on the evaluator's returns);
* protocol 4: `oodrl.protocol.tier_search.search_fault` with its defaults (100 common search
  episodes, 6 probes, verification batches of 50, at most 6, CI target ±0.02, budget 900).

Per tier, over the draws: mean |R̃_true(σ̂) − level| (σ̂ the reported severity; draws where
a search reports none are counted apart), the share within the tier's tolerance in truth, the
share verified, the share of verified tiers missing the tolerance in truth, and the share
whose verification CI reached ±0.02 (protocol 4's target; protocol 3 has none); per fault: draws
whose tiers come out out of order, and the impact episodes each protocol spent (the coarse
curve, shared, not counted). Ratios are protocol 4 / protocol 3.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from oodrl.config import SEARCH_SEED_OFFSET, VERIFY_SEED_OFFSET, TiersConfig
from oodrl.protocol.impact import (
    LEVELS,
    Estimate,
    Reference,
    Returns,
    _rounded,
    impact_curve_points,
    impact_record,
    paired_estimate,
    policy_seeds,
    tier_tolerance,
)
from oodrl.protocol.tier_search import (
    CrnSearchConfig,
    crn_reference_seeds,
    half_width,
    search_fault,
)

COARSE_EPISODES = 30
CI_TARGET = CrnSearchConfig().ci_target


# -- protocol 3's tier search (SPEC §19 at version 3), continuous faults ------------------------
@dataclass(frozen=True)
class Protocol3Search:
    """Version 3's `tiers.search` block and defaults."""

    tolerance: float = 0.015
    probe_episodes: int = 50
    max_probes: int = 4
    verify_episodes: int = 100


def search_seeds(seed: int, search: Protocol3Search, tier_index: int, probe: int) -> list[int]:
    """The fresh reset seeds of probe p of the i-th tier."""
    first = (
        seed
        + SEARCH_SEED_OFFSET
        + (tier_index * search.max_probes + probe) * (search.probe_episodes)
    )
    return list(range(first, first + search.probe_episodes))


def verify_seeds(seed: int, search: Protocol3Search) -> list[int]:
    """The held-out reset seeds of every tier's verification (no probe ever uses them)."""
    first = seed + VERIFY_SEED_OFFSET
    return list(range(first, first + search.verify_episodes))


def protocol3_seeds(seed: int, search: Protocol3Search) -> list[int]:
    """Every reset seed whose clean return version 3's search may read."""
    probes = [
        s
        for tier_index in range(len(LEVELS))
        for probe in range(search.max_probes)
        for s in search_seeds(seed, search, tier_index, probe)
    ]
    return [*probes, *verify_seeds(seed, search)]


def _on_target(estimate: Estimate, level: float, tolerance: float) -> bool:
    return abs(estimate.normalised - level) <= tier_tolerance(level, tolerance)


def search_tier(
    level: float,
    xs: Sequence[float],
    monotone: Sequence[float],
    measure: Callable[[float, int], Estimate],
    search: Protocol3Search,
) -> tuple[float | None, list[Estimate], bool]:
    """Bracket the level on the coarse monotone curve (σ = 0 included), then probe inside the
    bracket by safeguarded regula falsi (10%-90% of it), each probe on fresh episodes, until a
    probe's R̃ is within the tolerance or the probes run out. Returns (σ: the first probe on
    target, else the closest; None when the curve never reaches the level, probes, converged)."""
    xs, ys = np.asarray(xs, dtype=np.float64), np.asarray(monotone, dtype=np.float64)
    below = np.flatnonzero(ys <= level)
    if below.size == 0:
        return None, [], False
    i = max(int(below[0]), 1)
    lo, y_lo, hi, y_hi = xs[i - 1], ys[i - 1], xs[i], ys[i]
    probes: list[Estimate] = []
    for probe in range(search.max_probes):
        fraction = (y_lo - level) / (y_lo - y_hi) if y_lo > y_hi else 0.5
        severity = round(float(lo + min(max(fraction, 0.1), 0.9) * (hi - lo)), 6)
        estimate = measure(severity, probe)
        probes.append(estimate)
        if _on_target(estimate, level, search.tolerance):
            return severity, probes, True
        if estimate.normalised > level:
            lo, y_lo = severity, min(estimate.normalised, y_lo)
        else:
            hi, y_hi = severity, max(estimate.normalised, y_hi)
    closest = min(probes, key=lambda e: (abs(e.normalised - level), e.severity))
    return closest.severity, probes, False


def searched_tiers(
    xs: Sequence[float],
    monotone: Sequence[float],
    measure: Callable[[float, Sequence[int]], Estimate],
    search: Protocol3Search,
    *,
    seed: int,
) -> dict[str, Any]:
    """Every tier of a continuous fault by `search_tier`, each re-measured on the held-out
    verification seeds: verified when R̃ there is within the tolerance or its CI covers the
    level."""
    tiers: dict[str, Any] = {}
    for index, (name, level) in enumerate(LEVELS.items()):
        severity, probes, converged = search_tier(
            level, xs, monotone,
            lambda s, p, index=index: measure(s, search_seeds(seed, search, index, p)),
            search,
        )  # fmt: skip
        record: dict[str, Any] = {"level": level, "severity": _rounded(severity)}
        if severity is not None:
            check = measure(severity, verify_seeds(seed, search))
            low, high = check.ci
            verified = _on_target(check, level, search.tolerance) or low <= level <= high
            record["verification"] = {**check.as_dict(), "verified": bool(verified)}
            record["search"] = {"converged": converged, "probes": [p.as_dict() for p in probes]}
        tiers[name] = record
    return tiers


# -- the comparison ------------------------------------------------------------------------------


class World:
    """One draw: every episode's latent variables, keyed by (draw, reset seed)."""

    gap = 280.0

    def __init__(self, draw: int, seeds: Sequence[int]) -> None:
        self.draw = draw
        self.episodes = 0
        self.latent = {int(s): self.latents(np.random.default_rng([draw, int(s)])) for s in seeds}
        self.random = np.random.default_rng([draw, 10**9]).normal(-100.0, 30.0, COARSE_EPISODES)

    def reference(self) -> Reference:
        return Reference({s: v[0] for s, v in self.latent.items()}, self.random, "simulated")

    def __call__(self, severity: float, seeds: Sequence[int]) -> np.ndarray:
        self.episodes += len(seeds)
        return np.array([self.faulty(severity, self.latent[int(s)]) for s in seeds])


class Bimodal(World):
    def latents(self, rng: np.random.Generator) -> tuple[float, ...]:
        good = rng.random() < 0.7
        clean = rng.normal(240.0, 15.0) if good else rng.normal(40.0, 20.0)
        return clean, float(np.sqrt(rng.random())), rng.normal(-60.0, 30.0)

    def faulty(self, severity: float, latent: tuple[float, ...]) -> float:
        clean, tau, crash = latent
        return (crash if severity > tau else clean) - 10.0 * severity

    @staticmethod
    def true(severity: float) -> float:
        return 1.0 - (240.0 * severity**2 + 10.0 * severity) / 280.0


class Smooth(World):
    gap = 300.0

    def latents(self, rng: np.random.Generator) -> tuple[float, ...]:
        return 200.0 + 30.0 * rng.standard_normal(), rng.standard_normal(), rng.standard_normal()

    def faulty(self, severity: float, latent: tuple[float, ...]) -> float:
        clean, z, w = latent
        return clean - 300.0 * (1 - self.true(severity)) * (1 + 0.2 * z) - 5.0 * severity * w

    @staticmethod
    def true(severity: float) -> float:
        return 1.0 - 0.5 * severity - 0.25 * severity**2


FAULTS = {"bimodal": Bimodal, "smooth": Smooth}


def one_draw(kind, draw: int, *, seed: int, n_boot: int) -> dict[str, dict]:
    """Both protocols' tiers on one world: {protocol: {tier: (σ | None, verified), episodes}}."""
    p3, p4 = Protocol3Search(), CrnSearchConfig()
    coarse_seeds = policy_seeds(seed, COARSE_EPISODES)
    world = kind(draw, [*coarse_seeds, *protocol3_seeds(seed, p3), *crn_reference_seeds(seed, p4)])
    reference = world.reference()
    grid = TiersConfig().grid
    clean = reference.returns(coarse_seeds)
    faulty = {float(s): world(s, coarse_seeds) for s in grid}
    record = impact_record(
        Returns(clean, faulty, reference.random), n_boot=n_boot, seed=seed, stepped=False
    )
    xs, ys = impact_curve_points(record)
    world.episodes = 0

    def measure(severity: float, seeds: Sequence[int]) -> Estimate:
        return paired_estimate(
            severity, world(severity, seeds), reference.returns(seeds), reference,
            n_boot=n_boot, ci=0.95, seed=seed,
        )  # fmt: skip

    tiers3 = searched_tiers(xs, ys, measure, p3, seed=seed)
    episodes3 = world.episodes
    world.episodes = 0
    result4 = search_fault(world, reference, seed=seed, config=p4, coarse=(xs, ys), n_boot=n_boot)
    assert world.episodes == result4.episodes
    out = {
        "p3": {
            name: (
                None if isinstance(t["severity"], str) else float(t["severity"]),
                bool(t.get("verification", {}).get("verified", False)),
                "verification" in t
                and (t["verification"]["ci"][1] - t["verification"]["ci"][0]) / 2 <= CI_TARGET,
            )
            for name, t in tiers3.items()
        },
        "p4": {
            name: (
                t.severity,
                t.verified,
                t.verification is not None and half_width(t.verification) <= CI_TARGET,
            )
            for name, t in result4.tiers.items()
        },
    }
    out["p3"]["episodes"], out["p4"]["episodes"] = episodes3, result4.episodes
    return out


def _summary(kind, draws: list[dict], protocol: str, name: str) -> dict[str, float]:
    level, tolerance = LEVELS[name], tier_tolerance(LEVELS[name], 0.015)
    rows = [d[protocol][name] for d in draws]
    found = [row for row in rows if row[0] is not None]
    errors = np.array([abs(kind.true(row[0]) - level) for row in found])
    within = errors <= tolerance
    verified = np.array([row[1] for row in found], dtype=bool)
    n = len(rows)
    return {
        "error": float(errors.mean()) if found else float("nan"),
        "within": float(within.sum() / n),
        "verified": float(verified.sum() / n),
        "false_verified": float((verified & ~within).sum() / max(int(verified.sum()), 1)),
        "missing": n - len(found),
        "ci_met": float(sum(row[2] for row in rows) / n),
    }


def _ordered(tiers: dict) -> bool:
    severities = [tiers[name][0] for name in LEVELS if tiers[name][0] is not None]
    return severities == sorted(severities)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=100)
    parser.add_argument("--fault", choices=sorted(FAULTS), default="bimodal")
    parser.add_argument("--n-boot", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    kind = FAULTS[args.fault]
    start = time.process_time()
    draws = [one_draw(kind, d, seed=args.seed, n_boot=args.n_boot) for d in range(args.draws)]
    print(
        f"{args.fault} fault, {args.draws} draws, seed {args.seed}, n_boot {args.n_boot} "
        f"({time.process_time() - start:.1f} s CPU)\n"
    )
    print(
        "| tier | level | tol | mean abs(R̃_true(σ̂) − level) p3 | p4 | ratio "
        "| within tol p3 | p4 | verified p3 | p4 | verified but missing p3 | p4 "
        "| no σ̂ p3 | p4 | CI ±0.02 reached p3 | p4 |"
    )
    print("|" + "---|" * 16)
    for name, level in LEVELS.items():
        a, b = _summary(kind, draws, "p3", name), _summary(kind, draws, "p4", name)
        ratio = b["error"] / a["error"] if a["error"] > 0 else float("nan")
        print(
            f"| {name} | {level} | {tier_tolerance(level, 0.015):.3f} "
            f"| {a['error']:.4f} | {b['error']:.4f} | {ratio:.2f} "
            f"| {a['within']:.0%} | {b['within']:.0%} | {a['verified']:.0%} | {b['verified']:.0%} "
            f"| {a['false_verified']:.0%} | {b['false_verified']:.0%} "
            f"| {a['missing']} | {b['missing']} | {a['ci_met']:.0%} | {b['ci_met']:.0%} |"
        )
    e3 = np.array([d["p3"]["episodes"] for d in draws])
    e4 = np.array([d["p4"]["episodes"] for d in draws])
    disorder3 = sum(not _ordered(d["p3"]) for d in draws)
    disorder4 = sum(not _ordered(d["p4"]) for d in draws)
    print(
        f"\nImpact episodes a fault (search + verification; the coarse curve, "
        f"{COARSE_EPISODES} × {len(TiersConfig().grid)}, shared and not counted):\n"
        f"| protocol | mean | max |\n|---|---|---|\n"
        f"| p3 | {e3.mean():.0f} | {e3.max()} |\n| p4 | {e4.mean():.0f} | {e4.max()} |\n"
        f"| ratio p4/p3 | {e4.mean() / e3.mean():.2f} | |\n"
        f"\nDraws with tiers out of order (σ_mild > σ_moderate etc.): "
        f"p3 {disorder3}/{args.draws}, p4 {disorder4}/{args.draws}"
    )


if __name__ == "__main__":
    main()
