"""Impact calibration on a toy environment whose impact is known in closed form."""

import json

import gymnasium as gym
import numpy as np
import pytest

from oodrl.config import TierSearchConfig
from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.errors import ContractError
from oodrl.injectors.online import DynamicsScaling
from oodrl.io import yamlio
from oodrl.protocol.impact import (
    AT_MOST,
    BEYOND_RANGE,
    LEVELS,
    UNREACHABLE,
    Returns,
    impact_record,
    impact_text,
    minimum_detectable_impact,
)
from oodrl.protocol.tier_search import calibrate_impact
from oodrl.report.impact import impact_table, plot_impact_curves
from oodrl.testing.pipeline import TINY_TIERS

ENV_ID, LENGTH, DRIFT, COST = "OodrlToyDrift-v0", 10, 0.1, 0.3
GRID = [0.2, 0.4, 0.6, 0.8, 1.0]
#: The tier search on 8 common episodes and batches of 8 (π is deterministic here: every
#: episode is the same, so more would measure nothing more).
#: π being deterministic, R̃'s CI is the random policy's mean's, which no verification batch
#: narrows: 100 random-policy episodes put the severe tier's within the ±0.02 a tier needs to be
#: verified (16 would leave it at ±0.03).
SEARCH = TierSearchConfig(search_episodes=8, verify_batch=8, random_episodes=100)
#: Coarse-curve episodes.
EPISODES = 16
INJECTORS = {"strong": DynamicsScaling(gain=1.5), "weak": DynamicsScaling(gain=0.5)}


class ToyDrift(gym.Env):
    """x starts at 0 and drifts by 0.1 a step; reward = action − 0.3·x after the step's drift.

    Under dynamics_scaling (factor c = 1 + gain·σ on every increment, from the first step) the
    reward is computed before the fault rescales the step, so x before step t is 0.1·c·t and
    an always-1 policy's return over 10 steps is exactly 10 − 0.3·(4.5·c + 1).
    """

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = 0.0
        return np.array([self.x], np.float32), {}

    def step(self, action):
        self.x += DRIFT
        return np.array([self.x], np.float32), float(action) - COST * self.x, False, False, {}


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=ToyDrift, max_episode_steps=LENGTH)


class ToyHandle(SimulatorHandle):
    state_names = ("x",)

    def __init__(self, env):
        self.env = env

    def read_state(self):
        return np.array([self.env.x])

    def write_state(self, state):
        self.env.x = float(state[0])
        return np.array([self.env.x], np.float32)


class ToyAdapter(EnvironmentAdapter):
    env_id = ENV_ID

    def handle(self, env):
        return ToyHandle(env.unwrapped)


class AlwaysOne:
    state_dim, action_kind, action_size, sha256, mode = 1, "discrete", 2, "always-one", "greedy"

    def act(self, observations, rngs=None):
        return np.ones(len(observations), np.int64)


def closed_form_return(gain: float, severity: float) -> float:
    return LENGTH - COST * (4.5 * (1 + gain * severity) + 1)


def _calibrate(**kwargs):
    return calibrate_impact(
        ToyAdapter(), AlwaysOne(), INJECTORS, GRID, EPISODES, n_boot=200, search=SEARCH, **kwargs
    )


@pytest.fixture(scope="module")
def document():
    return _calibrate()


def test_the_impact_curve_is_the_closed_form(document):
    clean, random = document["clean_return"], document["random_return"]
    assert clean == pytest.approx(closed_form_return(1.5, 0.0), abs=1e-5)
    assert 2.0 < random < 5.0  # ≈ 5 − 1.65: the random policy pushes 1 half the time
    for fault, gain in (("strong", 1.5), ("weak", 0.5)):
        for point in document["faults"][fault]["curve"]:
            expected = closed_form_return(gain, point["severity"])
            assert point["mean_return"] == pytest.approx(expected, abs=1e-5)
            normalised = (expected - random) / (clean - random)
            assert point["normalised"] == pytest.approx(normalised, abs=1e-5)
            # Every π episode is the same, so only the random policy's mean varies.
            assert point["ci"][0] <= point["normalised"] <= point["ci"][1]


def test_tiers_are_measured_where_they_are_read_and_verified(document):
    """Every probe of the search measures R̃ (exact here: π is deterministic and R̃ linear in
    σ) where it reports it; each tier is read on the fit of the probes where R̃ is its level,
    and the verification re-measures it there on fresh episodes, with its CI."""
    clean, random = document["clean_return"], document["random_return"]
    for fault, gain in (("strong", 1.5), ("weak", 0.5)):
        record = document["faults"][fault]

        def closed_form(severity, gain=gain):
            # R̃(σ) = 1 − 0.3·4.5·gain·σ / (R_clean − R_rand): linear in σ.
            return 1 - COST * 4.5 * gain * severity / (clean - random)

        search = record["tier_search"]
        assert search["method"] == "common random numbers"
        assert 1 <= len(search["probes"]) <= SEARCH.max_probes
        for probe in search["probes"]:
            assert probe["normalised"] == pytest.approx(closed_form(probe["severity"]), abs=1e-5)
            assert probe["episodes"] == SEARCH.search_episodes
        assert search["episodes"]["total"] <= SEARCH.budget
        reached = []
        for name, level in LEVELS.items():
            crossing = (1 - level) * (clean - random) / (COST * 4.5 * gain)
            tier = record["tiers"][name]
            if crossing > GRID[-1]:
                assert tier["severity"] == UNREACHABLE and "verification" not in tier
                assert GRID[-1] in [p["severity"] for p in search["probes"]]
                continue
            assert closed_form(tier["severity"]) == pytest.approx(level, abs=1e-5)
            check = tier["verification"]
            assert check["normalised"] == pytest.approx(closed_form(tier["severity"]), abs=1e-5)
            assert check["ci"][0] <= check["normalised"] <= check["ci"][1]
            assert check["episodes"] == SEARCH.verify_batch * check["batches"]
            assert check["verified"] is True
            reached.append(tier["severity"])
        assert reached == sorted(reached)
    assert document["faults"]["weak"]["tiers"]["severe"]["severity"] == UNREACHABLE
    assert document["faults"]["strong"]["tiers"]["severe"]["severity"] != UNREACHABLE


def test_the_document_is_deterministic_and_renders(document, tmp_path):
    assert yamlio.dump(_calibrate()) == yamlio.dump(document)
    blocks = SEARCH.max_verify_batches * SEARCH.verify_batch  # every batch a fault may spend
    assert document["seeds"] == {
        "policy": [500000, 500000 + EPISODES - 1],
        "random": [600000, 600000 + SEARCH.random_episodes - 1],
        "search": [900000, 900000 + SEARCH.search_episodes - 1],
        "verification": [950000, 950000 + blocks - 1],
    }
    assert document["search"] == {**SEARCH.model_dump(), "max_severity": GRID[-1]}
    table = impact_table(document)
    assert "| weak" in table and UNREACHABLE in table and f"n = {SEARCH.verify_batch}" in table
    assert plot_impact_curves(document, tmp_path / "impact.png").stat().st_size > 0


def test_the_document_holds_plain_values_only(document):
    """Impact records are copied into JSON files (tier results, the leaderboard): no tuple,
    numpy scalar or NaN anywhere."""
    assert json.loads(json.dumps(document, allow_nan=False)) == document


def test_a_reference_without_the_search_seeds_is_refused():
    """A reference measured for other tier-search params lacks seeds this search reads."""
    from oodrl.protocol.impact import episode_limit
    from oodrl.protocol.tier_search import measure_reference

    adapter = ToyAdapter()
    other = TierSearchConfig(search_episodes=8, verify_batch=4)
    reference = measure_reference(
        adapter, AlwaysOne(), 16, other, seed=0, horizon=episode_limit(adapter)
    )
    with pytest.raises(ContractError, match="impact_reference"):
        _calibrate(reference=reference)


def test_a_noisy_non_monotone_curve_is_fitted_monotone_before_reading_tiers():
    n = 4
    returns = Returns(
        clean=np.full(n, 10.0),
        # R̃ = 0.90, 0.94 (a noisy rise), 0.70: pooled to 0.92, 0.92, 0.70.
        faulty={0.2: np.full(n, 9.0), 0.4: np.full(n, 9.4), 0.6: np.full(n, 7.0)},
        random=np.zeros(n),
    )
    record = impact_record(returns, n_boot=50)
    assert [p["normalised"] for p in record["curve"]] == [0.9, 0.94, 0.7]
    assert [p["monotone"] for p in record["curve"]] == pytest.approx([0.92, 0.92, 0.7])
    tiers = {name: t["severity"] for name, t in record["tiers"].items()}
    # mild: between (0, 1) and (0.2, 0.92); moderate: between (0.4, 0.92) and (0.6, 0.70), not
    # at 0.2 where the raw estimate dips to 0.90.
    assert tiers["mild"] == pytest.approx(0.125)
    assert tiers["moderate"] == pytest.approx(0.4 + 0.02 / 0.22 * 0.2, abs=1e-6)
    assert tiers["severe"] == pytest.approx(0.4 + 0.17 / 0.22 * 0.2, abs=1e-6)
    assert record["return_above_clean"] == []


def test_a_fault_that_raises_the_return_is_flagged_and_its_tiers_unreachable():
    rng = np.random.default_rng(0)
    clean = 10 + rng.standard_normal(30)
    returns = Returns(clean, {0.5: clean + 2.0, 1.0: clean + 3.0}, rng.standard_normal(30))
    record = impact_record(returns, n_boot=200)
    assert record["return_above_clean"] == [0.5, 1.0]
    assert {t["severity"] for t in record["tiers"].values()} == {UNREACHABLE}


def test_a_policy_no_better_than_random_is_refused():
    returns = Returns(np.zeros(3), {0.5: np.zeros(3)}, np.ones(3))
    with pytest.raises(ContractError, match="not above the random"):
        impact_record(returns)


def test_minimum_detectable_impact_interpolates_on_the_impact_curve():
    impact_xs, impact_curve = [0.0, 0.5, 1.0], [1.0, 0.9, 0.7]
    # The metric reaches 0.9 at σ = 0.3, where R̃ = 1 − 0.1·0.6 = 0.94: a 6% return loss.
    loss = minimum_detectable_impact(impact_xs, impact_curve, [0.1, 0.2, 0.4], [0.5, 0.8, 1.0])
    assert loss == pytest.approx(0.06)
    assert minimum_detectable_impact(impact_xs, impact_curve, [0.1, 0.4], [0.5, 0.85]) == (
        BEYOND_RANGE
    )
    # Reached only above the impact grid's range: beyond range, not extrapolated.
    assert minimum_detectable_impact([0.0, 0.2], [1.0, 0.9], [0.1, 0.4], [0.5, 0.95]) == (
        BEYOND_RANGE
    )


def test_an_mdi_at_the_first_tier_prints_as_a_bound():
    """SPEC §19: reached already at the first measured tier, the loss there only bounds the
    minimum detectable impact: `{at_most: 0.05}`, printed "≤ 5.0%" (a loss of ≤ 0.05)."""
    xs, ys = [0.0, 0.2, 0.35, 0.7], [1.0, 0.95, 0.9, 0.75]  # mild, moderate, severe
    tiers = [0.2, 0.35, 0.7]
    bound = minimum_detectable_impact(xs, ys, tiers, [0.93, 0.97, 1.0])
    assert bound == {AT_MOST: 0.05}
    assert impact_text(bound) == "≤ 5.0%"
    # Reached at the second tier: a value, interpolated as before.
    assert minimum_detectable_impact(xs, ys, tiers, [0.5, 0.9, 1.0]) == pytest.approx(0.1)
    assert impact_text(0.1) == "10.0%" and impact_text(BEYOND_RANGE) == BEYOND_RANGE
    # A stepped fault reaching it at its first measured severity: its step's loss, a bound.
    stepped = minimum_detectable_impact(
        [0.0, *STEPPED], [1.0, *STEPPED.values()], [0.1, 0.4], [0.95, 0.99], steps=4
    )
    assert stepped == {AT_MOST: pytest.approx(0.03)}


def test_the_impact_commands_write_deterministic_outputs_and_refuse_a_bad_grid(
    tmp_path, repo_root, monkeypatch
):
    """impact-reference measures π's clean returns on every seed the impact stage reads (the
    coarse curve's, the tier search's, every verification batch's); impact reuses them."""
    from typer.testing import CliRunner

    from oodrl.cli import app
    from oodrl.config import parse_params
    from oodrl.protocol.tier_search import reference_seeds
    from oodrl.stages.impact import read_reference

    monkeypatch.chdir(tmp_path)
    params = yamlio.load((repo_root / "params.yaml").read_text())
    params["tiers"].update({**TINY_TIERS, "episodes": 3})  # a two-probe search on a few episodes
    (tmp_path / "params.yaml").write_text(yamlio.dump(params))
    policy = str(repo_root / "models" / "policy.pt")
    result = CliRunner().invoke(
        app, ["impact-reference", "--policy", policy, "--out", "reference.yaml"]
    )
    assert result.exit_code == 0, result.output
    reference = read_reference(tmp_path / "reference.yaml")
    tiers = parse_params(params, components=False).tiers
    assert reference["clean"]["seeds"] == sorted(reference_seeds(0, 3, tiers.search))
    assert len(reference["clean"]["seeds"]) == 3 + 2 + 4 * 2 and len(reference["random"]) == 2

    def impact(name: str, *extra: str):
        return CliRunner().invoke(
            app,
            ["impact", "gaussian_state_noise", "--policy", policy, "--out", f"{name}.yaml",
             "--reference", "reference.yaml", "--episodes", "3", *extra],
        )  # fmt: skip

    for name in ("first", "second"):
        result = impact(name, "--grid", "0.5,1.0")
        assert result.exit_code == 0, result.output
    first = (tmp_path / "first.yaml").read_text()
    assert first == (tmp_path / "second.yaml").read_text()
    document = yamlio.load(first)
    # The post-hoc observation fault was calibrated live, with running statistics (no --id).
    assert document["faults"]["gaussian_state_noise"]["mode"] == "online"
    assert document["seeds"]["policy"] == [500000, 500002]
    search = document["faults"]["gaussian_state_noise"]["tier_search"]
    tiny = TINY_TIERS["search"]
    assert 1 <= len(search["probes"]) <= tiny["max_probes"]
    assert search["episodes"]["search"] == len(search["probes"]) * tiny["search_episodes"]
    assert search["episodes"]["verification"] <= tiny["max_verify_batches"] * tiny["verify_batch"]
    assert "gaussian_state_noise" in impact_table(document)
    bad = impact("bad", "--grid", "0.5,0.2")
    assert bad.exit_code == 2 and "--grid must be increasing" in bad.output
    assert not (tmp_path / "bad.yaml").exists()


def test_minimum_detectable_impacts_from_a_sweep_document(document):
    from oodrl.protocol.impact import minimum_detectable_impacts, sweep_metric

    summary = lambda value: {"matched_auroc": {"mean": value}}  # noqa: E731
    sweep = {
        "sweep": {
            "strong": {0.2: {"a": summary(0.8), "b": summary(0.5)},
                       0.4: {"a": summary(1.0), "b": summary(0.6)}},
            "not_calibrated": {0.2: {"a": summary(1.0)}},
        }
    }  # fmt: skip
    table = minimum_detectable_impacts(document, sweep_metric(sweep))
    # Detector a reaches 0.9 at σ = 0.3, on the linear closed-form curve of "strong".
    clean, random = document["clean_return"], document["random_return"]
    expected_loss = COST * 4.5 * 1.5 * 0.3 / (clean - random)
    assert table["a"]["strong"] == pytest.approx(expected_loss, abs=1e-5)
    assert table["b"]["strong"] == BEYOND_RANGE
    assert "not_calibrated" not in table["a"]


# -- stepped faults ------------------------------------------------------------------------------
#: A stepped fault of 4 steps: R̃ at each step's midpoint (k − ½)/4.
STEPPED = {0.125: 0.97, 0.375: 0.85, 0.625: 0.60, 0.875: 0.30}


def _returns(normalised: dict[float, float]) -> Returns:
    """Returns whose normalised means are `normalised` exactly (clean 10, random 0)."""
    faulty = {s: np.full(8, 10.0 * r) for s, r in normalised.items()}
    return Returns(np.full(8, 10.0), faulty, np.zeros(8))


def test_a_stepped_fault_takes_each_tier_at_a_step_that_lands_in_its_band():
    stepped = impact_record(_returns(STEPPED), n_boot=50, stepped=True)["tiers"]
    # benign: the first step (R̃ 0.97) lands in [0.95, 0.99]. mild: the first step at or below
    # 0.95 (R̃ 0.85) is already below 0.90, where moderate begins: no step costs 5-10% of the
    # return. moderate and severe land in their bands.
    assert {name: t["severity"] for name, t in stepped.items()} == {
        "benign": 0.125,
        "mild": UNREACHABLE,
        "moderate": 0.375,
        "severe": 0.625,
    }
    # Read as a continuous curve, mild would be a σ between the first two steps' midpoints,
    # which gives the fault of the second step, at R̃ 0.85, not 0.95.
    continuous = impact_record(_returns(STEPPED), n_boot=50)["tiers"]
    assert 0.125 < continuous["mild"]["severity"] < 0.375


def test_a_stepped_severe_tier_past_half_the_return_is_unreachable():
    tiers = impact_record(_returns({0.25: 0.92, 0.75: 0.40}), n_boot=50, stepped=True)["tiers"]
    assert tiers["mild"]["severity"] == 0.25
    assert tiers["moderate"]["severity"] == tiers["severe"]["severity"] == UNREACHABLE


def test_live_stepped_faults_declare_their_steps_and_each_midpoint_is_its_step():
    from oodrl.injectors.live_observation import (
        LiveCorrelationBreak,
        LiveGaussianStateNoise,
        LiveObservationDelay,
    )
    from oodrl.protocol.impact import severity_steps, step_severities

    delay = LiveObservationDelay(max_delay=10)
    assert severity_steps(delay, ToyAdapter()) == 10
    assert [delay.delay(s) for s in step_severities(10)] == list(range(1, 11))
    assert severity_steps(LiveCorrelationBreak(), ToyAdapter()) == ToyAdapter().state_dim
    assert severity_steps(LiveGaussianStateNoise(), ToyAdapter()) is None
    assert severity_steps(DynamicsScaling(), ToyAdapter()) is None


def test_a_stepped_fault_is_measured_once_per_step():
    from oodrl.injectors.live_observation import LiveObservationDelay

    injectors = {"delay": LiveObservationDelay(max_delay=3)}
    document = calibrate_impact(
        ToyAdapter(), AlwaysOne(), injectors, GRID, 4, n_boot=20, search=SEARCH
    )
    record = document["faults"]["delay"]
    assert record["severity_steps"] == 3
    assert [p["severity"] for p in record["curve"]] == pytest.approx([1 / 6, 0.5, 5 / 6])
    # The always-1 policy never reads its observation: a delayed sensor costs it nothing.
    assert all(t["severity"] == UNREACHABLE for t in record["tiers"].values())
    # Its tiers are steps: nothing searched, nothing to verify.
    assert record["tier_search"]["method"] == "steps" and "probes" not in record["tier_search"]
    assert record["tier_search"]["episodes"]["total"] == 0


def test_minimum_detectable_impact_of_a_stepped_fault_is_its_steps_impact():
    xs, ys = [0.0, *STEPPED], [1.0, *STEPPED.values()]
    # AUROC reaches 0.9 first at σ = 0.2, which is step ⌈0.2·4⌉ = 1: a loss of 1 − 0.97.
    loss = minimum_detectable_impact(xs, ys, [0.1, 0.2, 0.4], [0.5, 0.95, 0.99], steps=4)
    assert loss == pytest.approx(0.03)
    assert minimum_detectable_impact(xs, ys, [0.1], [0.5], steps=4) == BEYOND_RANGE
