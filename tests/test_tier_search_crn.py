"""The tier search (`oodrl.protocol.tier_search`) on synthetic faults whose impact curve
R̃(σ) is known in closed form: a smooth one with per-episode noise, and a bimodal one (each
episode either keeps its return or crashes past a severity of its own, from a two-mode clean
return). Episodes are functions of (σ, reset seed) only, as the collector's are, so the common
random numbers hold."""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence

import numpy as np
import pytest

from oodrl import config as seeds_config
from oodrl.config import CRN_VERIFY_SEED_OFFSET, TierSearchConfig
from oodrl.errors import ConfigError, ContractError
from oodrl.protocol.impact import LEVELS, Estimate, Reference, tier_tolerance
from oodrl.protocol.tier_search import (
    CrnSearchConfig,
    ci_meets_level,
    ci_target_met,
    crn_reference_seeds,
    crn_search_seeds,
    crn_verify_seeds,
    search_fault,
    tier_verified,
    verify_steps,
)

N_BOOT = 400
GAP = 300.0  # clean mean − random mean
#: For tests of the search alone: protocol 4's verification (6 batches, 300 reference seeds),
#: not the default 50 (2,500 seeds to resample) that a fault whose CIs stay wide spends in full.
SEARCH_ONLY = CrnSearchConfig(max_verify_batches=6, budget=900)


@functools.cache
def _latents(world: int, seed: int) -> np.ndarray:
    return np.random.default_rng([world, seed]).standard_normal(3)


class World:
    """π's clean return and its return under the fault, per reset seed; records each call."""

    def __init__(self, world: int, seeds: Sequence[int]) -> None:
        self.world = world
        self.calls: list[tuple[float, list[int]]] = []
        self.clean = {int(s): self.clean_return(int(s)) for s in seeds}
        self.random = np.random.default_rng([world, 10**9]).normal(-100.0, 30.0, size=100)

    def reference(self) -> Reference:
        return Reference(dict(self.clean), self.random, "synthetic")

    def clean_return(self, seed: int) -> float:
        return 200.0 + 30.0 * float(_latents(self.world, seed)[0])

    def loss(self, severity: float, seed: int) -> float:
        raise NotImplementedError

    def true(self, severity: float) -> float:
        raise NotImplementedError

    def __call__(self, severity: float, seeds: Sequence[int]) -> np.ndarray:
        self.calls.append((severity, list(seeds)))
        return np.array([self.clean[s] - self.loss(severity, s) for s in seeds])


class Smooth(World):
    """R̃(σ) = 1 − 0.5σ − 0.25σ²; each episode loses its share times (1 + 0.2 z) plus 5σ·w."""

    def true(self, severity: float) -> float:
        return 1.0 - 0.5 * severity - 0.25 * severity**2

    def loss(self, severity: float, seed: int) -> float:
        _, z, w = _latents(self.world, seed)
        return GAP * (1 - self.true(severity)) * (1 + 0.2 * z) + 5.0 * severity * w


class Bimodal(World):
    """Clean returns from two modes (240 or 40); past its own threshold τ (P(τ < σ) = σ²) an
    episode crashes to −60 ± 30. R̃(σ) = 1 − (σ²·(E C − E D) + 10σ) / (E C − E R)."""

    def clean_return(self, seed: int) -> float:
        rng = np.random.default_rng([self.world, seed, 1])
        return float(rng.normal(240.0, 15.0) if rng.random() < 0.7 else rng.normal(40.0, 20.0))

    def true(self, severity: float) -> float:
        return 1.0 - (severity**2 * (180.0 + 60.0) + 10.0 * severity) / (180.0 + 100.0)

    def loss(self, severity: float, seed: int) -> float:
        rng = np.random.default_rng([self.world, seed, 2])
        tau, crash = np.sqrt(rng.random()), rng.normal(-60.0, 30.0)
        faulty = crash if severity > tau else self.clean[seed]
        return self.clean[seed] - faulty + 10.0 * severity


def run(kind: type[World], world: int, *, seed: int = 0, config=None, coarse=None):
    config = config or CrnSearchConfig()
    fault = kind(world, crn_reference_seeds(seed, config))
    result = search_fault(
        fault, fault.reference(), seed=seed, config=config, coarse=coarse, n_boot=N_BOOT
    )
    return fault, result


def _root(fault: World, level: float) -> float:
    grid = np.linspace(0.0, 1.0, 100_001)
    return float(grid[np.argmax(fault.true(grid) <= level)])


@pytest.mark.parametrize("world", range(4))
def test_each_tier_is_the_root_of_the_true_curve(world):
    """On the smooth fault every tier lands where the true curve meets its level, within the
    tolerance plus the 100 common episodes' noise."""
    fault, result = run(Smooth, world, config=SEARCH_ONLY)
    for name, level in LEVELS.items():
        severity = result.tiers[name].severity
        assert severity is not None
        assert abs(fault.true(severity) - level) <= tier_tolerance(level, 0.015) + 0.01
        assert abs(severity - _root(fault, level)) < 0.03


def test_the_coarse_curve_only_guides_and_the_root_is_the_same():
    """Probe placement from a (biased) coarse curve changes where the probes go, not what the
    fit finds: the same sample root within the tolerance."""
    grid = [0.0, *(0.1 * k for k in range(1, 11))]
    coarse = (grid, [1.0 - 0.45 * s - 0.3 * s**2 for s in grid])
    fault, guided = run(Smooth, 7, config=SEARCH_ONLY, coarse=coarse)
    _, blind = run(Smooth, 7, config=SEARCH_ONLY)
    assert [p.severity for p in guided.probes] != [p.severity for p in blind.probes]
    for name, level in LEVELS.items():
        assert abs(fault.true(guided.tiers[name].severity) - level) <= 0.035


@pytest.mark.parametrize("world", range(8))
def test_bimodal_tiers_are_ordered_and_near_their_levels(world):
    fault, result = run(Bimodal, world, config=SEARCH_ONLY)
    severities = [result.tiers[name].severity for name in LEVELS]
    assert None not in severities
    assert severities == sorted(severities)
    for name, level in LEVELS.items():
        # 100 bimodal episodes: R̃'s standard error up to ~0.03 at severe.
        assert abs(fault.true(result.tiers[name].severity) - level) <= 0.09


class Wavy(Smooth):
    """A curve that rises in places (R̃ = 1 − 0.6σ + 0.08 sin 20σ): its levels are crossed
    more than once, and the monotone fit still orders the tiers."""

    def true(self, severity):
        return 1.0 - 0.6 * severity + 0.08 * np.sin(20 * severity)


@pytest.mark.parametrize("world", range(3))
def test_tiers_stay_ordered_on_a_curve_that_rises_in_places(world):
    _, result = run(Wavy, world, config=SEARCH_ONLY)
    severities = [result.tiers[name].severity for name in LEVELS]
    assert None not in severities and severities == sorted(severities)
    xs, fit = result.curve
    assert np.all(np.diff(fit) <= 0) and xs[0] == 0.0 and len(xs) == len(result.probes) + 1


def test_every_probe_shares_the_search_seeds_and_verification_never_does():
    fault, result = run(Bimodal, 3, config=SEARCH_ONLY)
    search = crn_search_seeds(0, result.config)
    probe_calls = fault.calls[: len(result.probes)]
    verify_calls = fault.calls[len(result.probes) :]
    assert all(seeds == search for _, seeds in probe_calls)
    assert [s for s, _ in probe_calls] == [p.severity for p in result.probes]
    verify = {s for _, seeds in verify_calls for s in seeds}
    assert verify and verify.isdisjoint(search)
    per_tier = [set(seeds) for seeds in result.verify_seeds.values()]
    assert sum(map(len, per_tier)) == len(set().union(*per_tier))  # no tier shares a seed


def test_seed_streams_are_disjoint_from_each_other_and_every_other_block():
    """The search's and the verification's seeds are disjoint, and clear of every other block of
    `oodrl.config` (100,000 seeds each: the policy's, the random policy's, protocol 3's), also
    at the largest sizes the blocks allow."""
    largest = TierSearchConfig(
        search_episodes=50_000, verify_batch=2_500, max_verify_batches=5, budget=400_000
    )
    largest.check_seed_blocks(len(LEVELS))
    others = [
        value
        for name, value in vars(seeds_config).items()
        if name.endswith("_SEED_OFFSET") and not name.startswith("CRN_")
    ]
    assert len(others) == 4
    for config in (CrnSearchConfig(), largest):
        for seed in (0, 7, 123_456):
            search = set(crn_search_seeds(seed, config))
            verify = [
                set(crn_verify_seeds(seed, config, b)) for b in range(config.max_verify_batches)
            ]
            every_verify = set().union(*verify)
            assert len(every_verify) == sum(map(len, verify))
            assert search.isdisjoint(every_verify)
            crn = search | every_verify
            assert len(crn_reference_seeds(seed, config)) == len(crn)
            assert min(crn) == seed + 900_000 and max(crn) < seed + 1_000_000
            for offset in others:
                assert crn.isdisjoint(range(seed + offset, seed + offset + 100_000))


@pytest.mark.parametrize(
    ("settings", "key"),
    [
        ({"verify_batch": 10_000, "max_verify_batches": 6}, "tiers.search.verify_batch"),
        ({"max_verify_batches": 3}, "tiers.search.max_verify_batches"),
        ({"max_probes": 30}, "tiers.search.budget"),
    ],
)
def test_sizes_that_overflow_a_seed_block_or_the_budget_are_refused(settings, key):
    """One line naming the params key and what it allows, before anything is measured."""
    config = CrnSearchConfig(**settings)
    fault = Smooth(0, [])
    with pytest.raises(ConfigError) as info:
        search_fault(fault, fault.reference(), seed=0, config=config)
    text = str(info.value)
    assert text.startswith(f"{key}: ") and "Allowed: " in text and "\n" not in text
    assert fault.calls == []


@pytest.mark.parametrize("kind", [Smooth, Bimodal])
def test_the_budget_is_respected_and_stated(kind):
    fault, result = run(kind, 5)
    spent = sum(len(seeds) for _, seeds in fault.calls)
    record = result.as_dict()["episodes"]
    assert spent == record["total"] == result.episodes <= 3_100 == record["budget"]
    assert record["search"] == 100 * len(result.probes) <= 600
    batches = sum(t.batches for t in result.tiers.values())
    assert batches <= 50 and record["verification"] == 50 * batches


def test_a_small_budget_spends_less_and_a_too_small_one_is_refused():
    config = CrnSearchConfig(max_probes=4, budget=650)
    fault, result = run(Smooth, 1, config=config)
    assert result.episodes <= 650
    assert all(t.batches >= 1 for t in result.tiers.values())
    with pytest.raises(ConfigError, match="budget"):
        run(Smooth, 1, config=CrnSearchConfig(budget=700))


def test_same_seed_same_result_and_another_seed_other_episodes():
    a = run(Bimodal, 2, seed=11, config=SEARCH_ONLY)[1].as_dict()
    b = run(Bimodal, 2, seed=11, config=SEARCH_ONLY)[1].as_dict()
    c = run(Bimodal, 2, seed=12, config=SEARCH_ONLY)[1].as_dict()
    assert a == b
    assert a["seeds"] != c["seeds"] and a["probes"] != c["probes"]


def test_verification_goes_to_the_widest_ci():
    """Every tier gets a batch first; the rest go to tiers still above the CI target, the
    widest first: the bimodal fault's severe tier (most crashes) gets the most."""
    _, result = run(Bimodal, 4)
    tiers = result.tiers
    assert all(t.batches >= 1 for t in tiers.values())
    assert tiers["severe"].batches == max(t.batches for t in tiers.values()) > 1
    assert tiers["benign"].verification.episodes == 50 * tiers["benign"].batches


@pytest.mark.parametrize(
    ("ci", "expected"),
    [
        ((0.93, 0.97), True),  # covers the level
        ((0.955, 0.99), True),  # above, but within the tolerance (0.015)
        ((0.97, 0.99), False),  # wholly above level + tolerance
        ((0.90, 0.93), False),  # wholly below level − tolerance
    ],
)
def test_verified_iff_the_ci_meets_the_band(ci, expected):
    estimate = Estimate(0.3, sum(ci) / 2, ci, 100)
    assert ci_meets_level(estimate, LEVELS["mild"], 0.015) is expected


@pytest.mark.parametrize(
    ("ci", "meets_level", "target_met"),
    [
        ((0.935, 0.965), True, True),  # ±0.015 around the level: verified
        ((0.94, 0.979), True, True),  # ±0.0195, reaching up to the band: verified
        ((0.92, 0.98), True, False),  # covers the level, but ±0.03
        ((0.90, 1.00), True, False),  # covers the level, but ±0.05
        ((0.97, 0.99), False, True),  # narrow, wholly above level + tolerance
    ],
)
def test_a_tier_is_verified_only_when_its_ci_meets_the_band_and_the_target(
    ci, meets_level, target_met
):
    """Protocol 5: a CI that meets the level but is wider than `ci_target` (±0.02) is not a
    verification; a narrow one is, if it meets the band."""
    estimate = Estimate(0.3, sum(ci) / 2, ci, 100)
    config = TierSearchConfig()
    assert ci_meets_level(estimate, LEVELS["mild"], config.tolerance) is meets_level
    assert ci_target_met(estimate, config.ci_target) is target_met
    assert tier_verified(estimate, LEVELS["mild"], config) is (meets_level and target_met)
    # The same holds for a stepped tier's band [floor, level].
    assert tier_verified(estimate, LEVELS["mild"], config, floor=0.9) is (
        meets_level and target_met
    )


class Noisy(Smooth):
    """Smooth, with per-episode noise growing with σ (0.6σ of the gap): the severe tier's CI
    needs about 600 episodes to reach ±0.02, the others a few batches at most."""

    def loss(self, severity: float, seed: int) -> float:
        w = np.random.default_rng([self.world, seed, 3]).standard_normal()
        return super().loss(severity, seed) + GAP * 0.6 * severity * w


def test_a_tier_still_wider_than_the_target_at_the_cap_is_not_verified():
    """With 6 batches the widest tier (severe) gets every batch past the first four, and its CI,
    though it meets the level, is still wider than ±0.02: recorded with its CI, unverified."""
    _, result = run(Noisy, 0, config=CrnSearchConfig(max_verify_batches=6))
    tiers = result.tiers
    assert sum(t.batches for t in tiers.values()) == 6  # the cap is spent
    severe = tiers["severe"]
    assert severe.batches == 3
    assert ci_meets_level(severe.verification, severe.level, 0.015)
    assert not ci_target_met(severe.verification, 0.02) and not severe.verified
    record = result.as_dict()["tiers"]["severe"]["verification"]
    assert record["ci_target_met"] is False and record["verified"] is False
    assert record["episodes"] == 150 and record["half_width"] > 0.02


def test_verification_spends_batches_until_every_tier_reaches_the_target():
    """With the default cap the same fault's verification goes on, each batch to the widest CI,
    until every CI is within ±0.02; then it stops, short of the cap, with every tier
    verified."""
    _, result = run(Noisy, 0)
    tiers = result.tiers
    for tier in tiers.values():
        assert ci_target_met(tier.verification, 0.02) and tier.verified
    assert tiers["severe"].batches == max(t.batches for t in tiers.values()) > 3
    assert sum(t.batches for t in tiers.values()) < result.config.max_verify_batches


class Drifted(Smooth):
    """Verification episodes lose `shift` of the gap more than the search's: a tier found on
    the search seeds then misses its level on fresh ones."""

    shift = 0.0

    def loss(self, severity: float, seed: int) -> float:
        fresh = seed >= CRN_VERIFY_SEED_OFFSET
        return super().loss(severity, seed) + (GAP * self.shift if fresh and severity else 0.0)


@pytest.mark.parametrize(("shift", "verified"), [(0.0, True), (0.1, False)])
def test_the_verified_flag_follows_the_fresh_episodes(shift, verified):
    Drifted.shift = shift
    _, result = run(Drifted, 6)
    flags = {name: t.verified for name, t in result.tiers.items()}
    assert set(flags.values()) == {verified}
    record = result.as_dict()["tiers"]["moderate"]["verification"]
    assert record["verified"] is verified and record["episodes"] >= 50


class Shallow(Smooth):
    """R̃ never falls below 0.85: the severe level is unreachable."""

    def true(self, severity: float) -> float:
        return 1.0 - 0.15 * severity


def test_an_unreachable_level_is_probed_at_the_largest_severity_and_not_verified():
    _, result = run(Shallow, 0)
    severe = result.tiers["severe"]
    assert severe.severity is None and severe.resolved and severe.verification is None
    assert 1.0 in [p.severity for p in result.probes]
    assert result.as_dict()["tiers"]["severe"]["severity"] == "unreachable"
    assert result.tiers["moderate"].severity is not None


def test_a_reference_without_the_search_seeds_is_refused():
    config = CrnSearchConfig()
    fault = Smooth(0, crn_search_seeds(0, config))
    with pytest.raises(ContractError, match="clean return"):
        search_fault(fault, fault.reference(), seed=0, config=config)


def test_a_level_not_reached_when_the_probes_run_out_is_not_called_unreachable():
    """One probe, aimed by a (too steep) coarse curve short of σ = 1: the levels the fit has
    not reached are "not reached", with an open bracket, not "unreachable"."""
    coarse = ([0.0, 0.5, 1.0], [1.0, 0.5, 0.0])
    _, result = run(Shallow, 0, config=CrnSearchConfig(max_probes=1), coarse=coarse)
    assert len(result.probes) == 1 and result.probes[0].severity < 1.0
    severe = result.tiers["severe"]
    assert severe.severity is None and not severe.resolved and not severe.unreachable
    record = result.as_dict()["tiers"]["severe"]
    assert record["severity"] == "not reached" and record["search"]["bracket"][1] is None


def test_the_record_holds_plain_values_and_every_probe():
    """The record may be copied into JSON files: plain values only; every probe (σ, R̃ with its
    CI, episodes) and the fit of them are there, and each tier's precision is its verification's
    CI (SPEC §23)."""
    _, result = run(Bimodal, 1, config=SEARCH_ONLY)
    record = result.as_dict()
    assert json.loads(json.dumps(record)) == record  # no tuple, numpy scalar or NaN
    assert record["method"] == "common random numbers"
    assert [p["severity"] for p in record["probes"]] == [p.severity for p in result.probes]
    assert len(record["fit"]) == len(result.probes) + 1 and record["fit"][0]["severity"] == 0.0
    mild = record["tiers"]["mild"]
    assert set(mild) == {"level", "severity", "search", "verification"}
    check = mild["verification"]
    assert check["ci"][0] <= check["normalised"] <= check["ci"][1]
    assert check["episodes"] == 50 * check["batches"]
    assert check["half_width"] == pytest.approx((check["ci"][1] - check["ci"][0]) / 2, abs=1e-6)
    # Batches are numbered over the fault: the first goes to the first tier with a severity.
    first = min(batches[0][0] for batches in record["seeds"]["verification"].values())
    assert first == CRN_VERIFY_SEED_OFFSET


class Steps(World):
    """A stepped fault of 4 steps, R̃ at step k's midpoint (k − ½)/4 from `STEPS`."""

    STEPS = {0.125: 0.97, 0.375: 0.85, 0.625: 0.60, 0.875: 0.30}

    def true(self, severity: float) -> float:
        return self.STEPS[severity]

    def loss(self, severity: float, seed: int) -> float:
        _, z, _ = _latents(self.world, seed)
        return GAP * (1 - self.true(severity)) * (1 + 0.2 * z)


def test_a_stepped_fault_is_verified_on_its_band_without_a_search():
    """Each tier a step lands in (benign at 0.125, moderate at 0.375, severe at 0.625) is
    verified on fresh batches against its band [next level, level]: no probe, no fit."""
    config = CrnSearchConfig()
    fault = Steps(0, crn_reference_seeds(0, config))
    severities = {"benign": 0.125, "mild": None, "moderate": 0.375, "severe": 0.625}
    result = verify_steps(fault, fault.reference(), severities, seed=0, n_boot=N_BOOT)
    assert result.probes == [] and result.search_episodes == 0
    assert {n: t.verified for n, t in result.tiers.items()} == {
        "benign": True,  # R̃ 0.97 in [0.95, 0.99]
        "mild": False,  # no step: not measured
        "moderate": True,  # 0.85 in [0.75, 0.90]
        "severe": True,  # 0.60 in [0.5, 0.75]
    }
    assert result.tiers["mild"].verification is None
    used = {s for _, seeds in fault.calls for s in seeds}
    assert used.isdisjoint(crn_search_seeds(0, config)) and result.episodes == len(used) <= 3_100
    record = result.as_dict()
    assert record["method"] == "steps" and "probes" not in record
    assert record["tiers"]["mild"] == {"level": 0.95, "severity": "unreachable"}
    assert "search" not in record["tiers"]["benign"]
    # A step read as the wrong tier misses its band: R̃ 0.85 is below mild's [0.90, 0.95].
    wrong = verify_steps(fault, fault.reference(), {"mild": 0.375}, seed=0, n_boot=N_BOOT)
    assert wrong.tiers["mild"].verified is False
