"""The tier search (SPEC §19) on an impact curve known in closed form and measured with noise:
every level is found within the tolerance, including levels the curve crosses below the coarse
grid's first point, where reading the coarse curve linearly misses by far."""

import numpy as np
import pytest

from oodrl.config import TierSearchConfig
from oodrl.protocol.impact import LEVELS, Estimate, first_crossing, search_tier, searched_tiers

GRID = [0.1, 0.2, 0.4, 0.6, 0.8, 1.0]
NOISE = 0.004  # the standard error of one probe's R̃


def concave_impact(severity: float) -> float:
    """R̃(σ) = 1 − 0.8·√σ: steep near 0, so every tier lies below the first grid point."""
    return 1.0 - 0.8 * np.sqrt(severity)


def inverse(level: float) -> float:
    return ((1.0 - level) / 0.8) ** 2


def noisy_measure(rng: np.random.Generator):
    def measure(severity, _seeds) -> Estimate:
        value = concave_impact(severity) + rng.normal(0.0, NOISE)
        return Estimate(severity, value, (value - 2 * NOISE, value + 2 * NOISE), 50)

    return measure


def coarse_curve():
    xs = [0.0, *GRID]
    return xs, [1.0, *(concave_impact(s) for s in GRID)]


@pytest.mark.parametrize("draw", range(20))
def test_every_level_is_found_within_tolerance_below_the_first_grid_point(draw):
    search = TierSearchConfig(tolerance=0.015, max_probes=6)
    xs, ys = coarse_curve()
    measure = noisy_measure(np.random.default_rng(draw))
    for level in LEVELS.values():
        assert inverse(level) < GRID[0]  # every tier is crossed before the first grid point
        severity, probes, converged = search_tier(level, xs, ys, lambda s, p: measure(s, p), search)
        assert converged and probes[-1].severity == severity
        # Within the tolerance as measured, so within it plus the probe's noise in truth.
        assert abs(concave_impact(severity) - level) <= search.tolerance + 4 * NOISE


def test_the_linear_read_below_the_first_grid_point_is_not_the_tier():
    """What the search replaces: the line from (0, 1) to the first grid point names a severity
    whose true cost is far from the level's (here over twice it; on a convex curve, a fraction
    of it, as the issue's 0.3% for a "mild" 5%)."""
    xs, ys = coarse_curve()
    read = first_crossing(xs, ys, LEVELS["mild"])
    assert 1 - concave_impact(read) > 2 * (1 - LEVELS["mild"])


def test_a_level_the_coarse_curve_never_reaches_is_unreachable():
    xs, ys = [0.0, 0.5, 1.0], [1.0, 0.97, 0.96]
    measure = noisy_measure(np.random.default_rng(0))
    assert search_tier(0.9, xs, ys, measure, TierSearchConfig()) == (None, [], False)


def test_an_exhausted_search_reports_the_closest_probe_and_verification_flags_a_miss():
    """A curve whose every probe lands far from the level (a jump): the closest probe is
    reported, not converged, and a verification that misses the level is flagged."""

    def jump(severity, _seeds):
        value = 1.0 if severity < 0.3 else 0.5
        return Estimate(severity, value, (value - 0.01, value + 0.01), 50)

    search = TierSearchConfig(max_probes=3)
    tiers = searched_tiers(
        {}, [0.0, 0.5, 1.0], [1.0, 0.5, 0.4], jump, search, seed=0, stepped=False
    )
    mild = tiers["mild"]
    assert mild["search"]["converged"] is False and len(mild["search"]["probes"]) == 3
    chosen = min(mild["search"]["probes"], key=lambda p: abs(p["normalised"] - 0.95))
    assert mild["severity"] == chosen["severity"]
    assert mild["verification"]["verified"] is False


def test_probes_and_the_verification_use_disjoint_fresh_seeds():
    from oodrl.protocol.impact import reference_seeds, search_seeds, verify_seeds

    search = TierSearchConfig()
    probes = [
        tuple(search_seeds(0, search, tier, probe))
        for tier in range(len(LEVELS))
        for probe in range(search.max_probes)
    ]
    flat = [s for block in probes for s in block]
    assert len(set(flat)) == len(flat)
    assert not set(flat) & set(verify_seeds(0, search))
    assert len(reference_seeds(0, 30, search)) == len(set(reference_seeds(0, 30, search)))
