import pickle

import numpy as np
import pytest
from recording import Recording
from rollout_policies import HeuristicPolicy

from oodrl.core.injector import Fault
from oodrl.envs.collect import BLOCK_SIZE, collect
from oodrl.envs.lunar_lander import LunarLanderAdapter
from oodrl.errors import ConfigError
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import collect_online, collect_online_sets, injector_rng

ONLINE = [name for name in INJECTORS.names() if INJECTORS.get(name).mode == "online"]
DYNAMICS = ["dynamics_scaling", "action_conditioned_dynamics", "gradual_drift"]
GRID = [0.1, 0.2, 0.4, 0.6, 0.8]
SEEDS = list(range(10000, 10004))
T, ONSET = 300, 100
FIELDS = ("states", "actions", "rewards", "next_states", "dones", "executed_actions")

ADAPTER, POLICY = LunarLanderAdapter(), HeuristicPolicy()


@pytest.fixture(scope="module")
def clean():
    return collect(ADAPTER, POLICY, SEEDS, T)


#: The action-conditioned predicate on LunarLander: the main engine (SPEC §4).
TARGETS = {"action_conditioned_dynamics": {"target_action": 2}}


def make(name: str, **params):
    return INJECTORS.get(name).from_params({**TARGETS.get(name, {}), **params})


def run(injector, severity: float, seeds=SEEDS, horizon: int = T, onset: int = ONSET, seed=0):
    spec = injector.spec(severity, onset)
    return collect_online(injector, ADAPTER, POLICY, seeds, horizon, spec, seed, policy_seed=0)


@pytest.mark.parametrize("name", ONLINE)
def test_severity_zero_reproduces_the_clean_streams(name, clean):
    perturbed = run(make(name), 0.0)
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(perturbed, field), getattr(clean, field))


@pytest.mark.parametrize("severity", [0.3, 1.0])
@pytest.mark.parametrize("name", ONLINE)
def test_steps_before_the_onset_are_the_clean_steps(name, severity, clean):
    perturbed = run(make(name), severity)
    for field in FIELDS:
        np.testing.assert_array_equal(
            getattr(perturbed, field)[:, :ONSET], getattr(clean, field)[:, :ONSET]
        )
    assert not np.array_equal(perturbed.states, clean.states)
    assert perturbed.attrs["spec"]["severity"] == severity and perturbed.attrs["mode"] == "online"
    assert perturbed.labels[:, ONSET:].all() and not perturbed.labels[:, :ONSET].any()


# Live sensor faults saturate over this window (a dropped coordinate reads 0 whatever σ): their
# growth is tested over a short window in test_every_environment.py and open loop in
# test_live_observation.py.
@pytest.mark.parametrize("name", [name for name in ONLINE if not name.startswith("live_")])
def test_divergence_grows_with_severity(name):
    # A short horizon with no episode end: the streams stay comparable step by step.
    seeds, horizon, onset = list(range(4)), 120, 40
    reference = collect(ADAPTER, POLICY, seeds, horizon)
    divergences = []
    for severity in GRID:
        perturbed = run(make(name), severity, seeds, horizon, onset)
        distance = np.linalg.norm(perturbed.states - reference.states, axis=-1)
        divergences.append(distance[:, onset:].mean())
    assert np.all(np.diff(divergences) > 0), divergences


@pytest.mark.parametrize("name", ONLINE)
def test_same_parameters_give_identical_streams(name):
    injector = make(name)
    first, second = run(injector, 0.5, horizon=150), run(injector, 0.5, horizon=150)
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(first, field), getattr(second, field))
    fault = injector.fault(injector.spec(0.5, ONSET), injector_rng(0, name, 0))
    assert isinstance(pickle.loads(pickle.dumps(fault)), Fault)  # faults go to worker processes


def test_stuck_actuator_at_full_severity_always_executes_the_held_action(clean):
    perturbed = run(make("stuck_actuator"), 1.0)
    held = perturbed.actions[:, ONSET]
    assert np.all(perturbed.executed_actions[:, ONSET:] == held[:, None])
    for j in range(len(SEEDS)):  # `actions` records what the policy commanded
        np.testing.assert_array_equal(perturbed.actions[j], POLICY.act(perturbed.states[j]))
    assert np.any(perturbed.actions[:, ONSET:] != held[:, None])


def test_stuck_actuator_holds_with_probability_severity():
    perturbed = run(make("stuck_actuator"), 0.5)
    commanded, executed = perturbed.actions[:, ONSET:], perturbed.executed_actions[:, ONSET:]
    held = np.broadcast_to(perturbed.actions[:, ONSET, None], commanded.shape)
    assert np.all((executed == commanded) | (executed == held))
    informative = commanded != held  # steps where holding makes a difference
    assert abs((executed == held)[informative].mean() - 0.5) < 0.1


def expected_factor(name: str, severity: float, t: int, commanded: int) -> float:
    full = 1.0 + 1.5 * severity
    if name == "action_conditioned_dynamics":
        return full if commanded == 2 else 1.0
    if name == "gradual_drift":
        return 1.0 + (full - 1.0) * min(1.0, (t - ONSET) / 200)
    return full


@pytest.mark.parametrize("severity", [0.5, 1.0])
@pytest.mark.parametrize("name", DYNAMICS)
def test_written_increments_are_the_simulators_increments_times_the_factor(name, severity):
    injector = make(name)
    spec = injector.spec(severity, ONSET)
    faults = [Recording(injector.fault(spec, injector_rng(0, name, j))) for j in range(len(SEEDS))]
    tset = collect(ADAPTER, POLICY, SEEDS, T, labels=spec.labels(T), faults=faults)
    assert tset.dones[:, ONSET:-1].any()  # the checks below cover steps right after a reset
    for j, fault in enumerate(faults):
        assert [call[0] for call in fault.calls] == list(range(ONSET, T))
        for t, before, own, commanded, written, returned in fault.calls:
            # The state the policy acted on: after a reset, the reset observation's.
            np.testing.assert_array_equal(before, tset.states[j, t, :6])
            np.testing.assert_array_equal(returned, tset.next_states[j, t])
            factor = expected_factor(name, severity, t, int(commanded))
            # Box2D keeps float32 bodies: the written state reads back to float32 rounding.
            np.testing.assert_allclose(written - before, factor * (own - before), atol=2e-6)
            np.testing.assert_array_equal(returned[:6], written.astype(np.float32))
            if factor == 1.0:
                np.testing.assert_array_equal(written, own)


def test_action_conditioned_dynamics_checks_the_target_action_against_the_environment():
    injector = make("action_conditioned_dynamics", target_action=4)
    with pytest.raises(ConfigError, match=r"target_action.*\[0, 4\)"):
        run(injector, 0.5)
    for params in ({}, {"target_dim": 0, "target_threshold": 0.0}):
        injector = INJECTORS.get("action_conditioned_dynamics").from_params(params)
        with pytest.raises(ConfigError, match=r"'target_action'.*LunarLander-v3 has 4 discrete"):
            run(injector, 0.5)


@pytest.mark.parametrize(
    "name", ["dynamics_scaling", "action_conditioned_dynamics", "gradual_drift"]
)
def test_gain_sets_the_full_severity_factor(name):
    from oodrl.injectors import INJECTORS

    default, lowered = INJECTORS.get(name)(), INJECTORS.get(name)(gain=0.3)
    assert default.full_factor(1.0) == 2.5  # SPEC §4: 1 + 1.5σ
    assert lowered.full_factor(1.0) == 1.3 and lowered.full_factor(0.0) == 1.0
    with pytest.raises(ConfigError, match="'gain' parameter"):
        INJECTORS.get(name)(gain=0.0).validate_params()


def test_sweep_collection_reports_progress_per_job_of_streams():
    """The online-collection progress bar's total is seeds × specs; it must reach it, one call
    per job of streams (the streams of every spec dealt to jobs of at most BLOCK_SIZE)."""
    injector = make("dynamics_scaling")
    specs = [injector.spec(severity, 5) for severity in (0.2, 0.8)]
    seeds = list(range(10000, 10000 + BLOCK_SIZE + 3))  # a full block and a partial one
    done: list[int] = []
    sets = collect_online_sets(
        injector, ADAPTER, POLICY, seeds, 12, specs, seed=0, policy_seed=0, progress=done.append
    )
    assert len(sets) == len(specs)
    assert sum(done) == len(seeds) * len(specs) and max(done) <= BLOCK_SIZE
