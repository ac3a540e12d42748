"""The tier search (SPEC §19) on impact curves known in closed form, measured with noise: every
level is found within the tolerance, including levels the curve crosses below the coarse grid's
first point, where reading the coarse curve linearly misses by far; a level the curve reaches
only past the grid is unreachable; a jump that no severity lands on is never verified. The
search's own machinery (seeds, budget, ordering, verification batches): test_tier_search_crn."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from oodrl.config import TierSearchConfig
from oodrl.protocol.impact import (
    LEVELS,
    UNREACHABLE,
    Reference,
    first_crossing,
    policy_seeds,
    tier_tolerance,
)
from oodrl.protocol.tier_search import (
    CrnSearchConfig,
    crn_reference_seeds,
    reference_seeds,
    search_fault,
)

GRID = [0.2, 0.4, 0.6, 0.8, 1.0]
CLEAN, RANDOM = 200.0, -100.0  # π's clean mean return, the random policy's
N_BOOT = 300


class Fault:
    """π's return per reset seed: CLEAN + 30 z clean, less (CLEAN − RANDOM)·(1 − R̃(σ))·(1 +
    0.1 w) under the fault (z, w standard normal per seed): episodes are functions of (σ, seed),
    as the collector's are."""

    def __init__(self, curve, seeds: Sequence[int], world: int = 0) -> None:
        self.curve = curve
        self.latent = {
            int(s): np.random.default_rng([world, int(s)]).standard_normal(2) for s in seeds
        }
        random = np.random.default_rng([world, 10**9]).normal(RANDOM, 30.0, 200)
        clean = {s: CLEAN + 30.0 * z for s, (z, _) in self.latent.items()}
        self.reference = Reference(clean, random, "closed-form")

    def __call__(self, severity: float, seeds: Sequence[int]) -> np.ndarray:
        return np.array(
            [
                self.reference.clean[s]
                - (CLEAN - RANDOM) * (1 - self.curve(severity)) * (1 + 0.1 * self.latent[s][1])
                for s in seeds
            ]
        )


def concave(severity):
    """R̃(σ) = 1 − 0.6·√σ: steep near 0, so every tier lies below the first grid point."""
    return 1.0 - 0.6 * np.sqrt(severity)


def coarse(curve) -> tuple[list[float], list[float]]:
    return [0.0, *GRID], [1.0, *(float(curve(s)) for s in GRID)]


def _search(curve, *, world: int = 0, config: CrnSearchConfig | None = None):
    config = config or CrnSearchConfig()
    fault = Fault(curve, crn_reference_seeds(0, config), world)
    result = search_fault(
        fault, fault.reference, seed=0, config=config, coarse=coarse(curve), n_boot=N_BOOT
    )
    return result


@pytest.mark.parametrize("world", range(4))
def test_every_level_is_found_within_tolerance_below_the_first_grid_point(world):
    """On a curve this steep near 0 the benign tier needs probes down to σ ≈ 0.0003: with ten
    probes every tier is found within the tolerance, and verified."""
    result = _search(concave, world=world, config=CrnSearchConfig(max_probes=10, budget=1_300))
    for name, level in LEVELS.items():
        assert ((1 - level) / 0.6) ** 2 < GRID[0]  # every tier crossed before the first point
        tier = result.tiers[name]
        # Within the tolerance on the sample curve, so within it plus the common episodes'
        # noise (the loss's 10% spread over 100 episodes) in truth.
        noise = 0.03 * (1 - level)
        assert abs(concave(tier.severity) - level) <= tier_tolerance(level, 0.015) + noise
        assert tier.verified
    severities = [result.tiers[name].severity for name in LEVELS]
    assert severities == sorted(severities)


@pytest.mark.parametrize("world", range(4))
def test_a_tier_the_default_probes_leave_off_its_level_is_flagged(world):
    """With the default six probes the benign tier of that curve is left unresolved, off its
    level in truth: its verification on fresh episodes says so. Every tier verified is on its
    level within the tolerance and the verification's noise."""
    result = _search(concave, world=world)
    assert len(result.probes) == 6 and result.episodes <= result.config.budget
    for name, level in LEVELS.items():
        tier = result.tiers[name]
        error = abs(concave(tier.severity) - level)
        if tier.verified:
            assert error <= tier_tolerance(level, 0.015) + 0.03 * (1 - level)
        else:
            assert error > tier_tolerance(level, 0.015) and not tier.resolved
    assert not result.tiers["benign"].verified


def test_the_linear_read_below_the_first_grid_point_is_not_the_tier():
    """What the search replaces: the line from (0, 1) to the first grid point names a severity
    whose true cost is far from the level's (here over twice it; on a convex curve, a fraction
    of it, as the issue's 0.3% for a "mild" 5%)."""
    xs, ys = coarse(concave)
    read = first_crossing(xs, ys, LEVELS["mild"])
    assert 1 - concave(read) > 2 * (1 - LEVELS["mild"])


def test_a_level_reached_only_past_the_largest_severity_is_unreachable():
    """The impact stage searches up to its grid's largest severity (`max_severity`): a level the
    curve reaches only beyond it is unreachable, probed at that severity, never extrapolated."""
    linear = lambda s: 1.0 - 0.3 * s  # noqa: E731  severe (0.75) at σ = 0.83
    result = _search(linear, config=CrnSearchConfig(max_severity=0.6))
    severe = result.tiers["severe"]
    assert severe.severity is None and severe.unreachable and severe.verification is None
    assert 0.6 in [p.severity for p in result.probes]
    assert max(p.severity for p in result.probes) <= 0.6
    assert result.as_dict()["tiers"]["severe"]["severity"] == UNREACHABLE
    assert result.tiers["moderate"].severity == pytest.approx(1 / 3, abs=0.02)


def test_a_jump_is_bracketed_to_the_resolution_and_its_verification_misses():
    """A fault that costs nothing below σ = 0.3 and half the return above: no severity has
    R̃ near any level. The search narrows the jump's bracket; every tier's verification there
    reads 1 or 0.5 (or a mix), never the level, and is flagged."""
    jump = lambda s: 1.0 if s < 0.3 else 0.5  # noqa: E731
    config = CrnSearchConfig(max_probes=12, budget=1_500)
    result = _search(jump, config=config)
    for name in LEVELS:
        tier = result.tiers[name]
        lo, hi = tier.bracket
        assert lo < 0.3 <= hi and lo <= tier.severity <= hi
        assert tier.verification is not None and not tier.verified
    assert hi - lo < 0.05


def test_the_reference_holds_every_seed_an_impact_stage_reads():
    """The coarse curve's seeds, the search's common seeds and every verification batch's,
    each once: what impact_reference measures, so every fault's paired estimates reuse them."""
    search = TierSearchConfig()
    seeds = reference_seeds(0, 30, search)
    assert len(seeds) == len(set(seeds)) == 30 + 100 + 50 * 50
    assert seeds[:30] == policy_seeds(0, 30) and seeds[30:] == crn_reference_seeds(0, search)
