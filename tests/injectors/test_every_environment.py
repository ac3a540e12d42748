"""The injector invariants on every registered environment, discrete and continuous actions alike.

Severity 0 reproduces the clean stream exactly, steps before the onset are the clean steps, and
the effect grows with the severity. Each environment is driven by a fixed random linear policy
with seeded action noise (tests/rollout_policies.py), over a few short streams.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from recording import Recording
from rollout_policies import LinearPolicy

from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.trajectory import TrajectorySet
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import collect
from oodrl.errors import ConfigError
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import collect_online, injector_rng, perturb_posthoc

ENV_IDS = ENVIRONMENTS.names()
ONLINE = [name for name in INJECTORS.names() if INJECTORS.get(name).mode == "online"]
POSTHOC = [name for name in INJECTORS.names() if INJECTORS.get(name).mode == "posthoc"]
SEEDS = list(range(8))
T, ONSET = 40, 10
#: Divergence is measured over the first steps after the onset, before chaotic dynamics
#: (HalfCheetah, Hopper) saturate it at the distance between unrelated states.
WINDOW = 10
GRID = [0.1, 0.2, 0.4, 0.6, 0.8]
FIELDS = ("states", "actions", "rewards", "next_states", "dones", "executed_actions")


@cache
def adapter_of(env_id: str) -> EnvironmentAdapter:
    return ENVIRONMENTS.get(env_id)()


@cache
def policy_of(env_id: str) -> LinearPolicy:
    return LinearPolicy(adapter_of(env_id))


@cache
def clean_of(env_id: str) -> TrajectorySet:
    return collect(adapter_of(env_id), policy_of(env_id), SEEDS, T)


def target_params(env_id: str) -> dict:
    """An action-conditioned predicate that holds on many clean steps of the test policy: its
    most frequent discrete action, or action coordinate 0 above its clean median."""
    actions = clean_of(env_id).actions
    if adapter_of(env_id).action_kind == "discrete":
        values, counts = np.unique(actions, return_counts=True)
        return {"target_action": int(values[counts.argmax()])}
    return {"target_dim": 0, "target_threshold": float(np.median(actions[..., 0]))}


def make(name: str, env_id: str):
    params = target_params(env_id) if name == "action_conditioned_dynamics" else {}
    return INJECTORS.get(name).from_params(params)


@cache
def perturbed(name: str, env_id: str, severity: float) -> TrajectorySet:
    injector = make(name, env_id)
    spec = injector.spec(severity, ONSET)
    if injector.mode == "posthoc":
        return perturb_posthoc(injector, clean_of(env_id), spec, seed=0)
    adapter, policy = adapter_of(env_id), policy_of(env_id)
    return collect_online(injector, adapter, policy, SEEDS, T, spec, seed=0, policy_seed=0)


def divergence(name: str, env_id: str, severity: float) -> float:
    distance = np.linalg.norm(
        perturbed(name, env_id, severity).states - clean_of(env_id).states, axis=-1
    )
    return float(distance[:, ONSET : ONSET + WINDOW].mean())


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("name", ONLINE + POSTHOC)
def test_severity_zero_reproduces_the_clean_streams(name, env_id):
    for field in FIELDS:
        np.testing.assert_array_equal(
            getattr(perturbed(name, env_id, 0.0), field), getattr(clean_of(env_id), field)
        )


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("name", ONLINE + POSTHOC)
def test_steps_before_the_onset_are_the_clean_steps(name, env_id):
    clean = clean_of(env_id)
    for severity in (GRID[0], GRID[-1]):
        tset = perturbed(name, env_id, severity)
        for field in FIELDS:
            # A post-hoc change of the observation at the onset is also next_states[onset - 1].
            end = ONSET - 1 if field == "next_states" and name in POSTHOC else ONSET
            np.testing.assert_array_equal(
                getattr(tset, field)[:, :end], getattr(clean, field)[:, :end]
            )
        assert not np.array_equal(tset.states[:, ONSET:], clean.states[:, ONSET:])


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("name", [name for name in ONLINE if name != "live_observation_delay"])
def test_online_effect_grows_with_severity(name, env_id):
    divergences = [divergence(name, env_id, severity) for severity in GRID]
    if name == "live_correlation_break":  # as post hoc: ceil(σ·d) coordinates, in steps
        assert np.all(np.diff(divergences) >= 0) and divergences[-1] > divergences[0], divergences
    else:
        assert np.all(np.diff(divergences) > 0), divergences


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("name", [name for name in POSTHOC if name != "observation_delay"])
def test_posthoc_effect_grows_with_severity(name, env_id):
    # Non-decreasing: correlation_break permutes ceil(σ·d) coordinates, the same number at two
    # severities when d is small (Pendulum: d = 3).
    divergences = [divergence(name, env_id, severity) for severity in GRID]
    assert np.all(np.diff(divergences) >= 0) and divergences[-1] > divergences[0], divergences


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_observation_delay_lag_grows_with_severity(env_id):
    # Distance to the clean stream is not monotone in a delay where the motion is periodic (a
    # gait, a swinging link): a lag of a whole period looks like no lag. What grows is the lag.
    clean, lags = clean_of(env_id).states, []
    for severity in GRID:
        states = perturbed("observation_delay", env_id, severity).states
        lag = next(
            k
            for k in range(1, ONSET + 1)
            if (states[:, ONSET:] == clean[:, ONSET - k : T - k]).all()
        )
        lags.append(lag)
    assert np.all(np.diff(lags) > 0), lags


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_stuck_actuator_holds_the_whole_commanded_action(env_id):
    tset = perturbed("stuck_actuator", env_id, 0.8)
    executed, commanded = tset.executed_actions[:, ONSET:], tset.actions[:, ONSET:]
    held = np.broadcast_to(tset.actions[:, ONSET, None], commanded.shape)
    # A continuous action is held as a vector: all its coordinates come from one source.
    is_held, is_commanded = same_action(executed, held), same_action(executed, commanded)
    assert (is_held | is_commanded).all()
    assert 0.7 < is_held.mean() < 0.95  # held with probability σ = 0.8 (or commanded anyway)


def same_action(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, T) whether step t of stream i has the same action in a and b (whole vectors)."""
    return (a == b).reshape(*a.shape[:2], -1).all(axis=-1)


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("name", ["dynamics_scaling", "action_conditioned_dynamics"])
def test_scaling_faults_scale_the_state_vector_increment(name, env_id):
    injector, adapter = make(name, env_id), adapter_of(env_id)
    spec, factor = injector.spec(0.5, ONSET), injector.full_factor(0.5)
    faults = [Recording(injector.fault(spec, injector_rng(0, name, j))) for j in range(2)]
    collect(adapter, policy_of(env_id), SEEDS[:2], T, labels=spec.labels(T), faults=faults)
    env = adapter.make()
    env.reset(seed=0)
    handle = adapter.handle(env)  # for its `increment` (Acrobot's wrapped angles)
    # Box2D keeps float32 bodies; every other simulator reads back what was written.
    atol = 2e-6 if env_id.startswith("LunarLander") else 0.0
    scaled = 0
    for fault in faults:
        for _, before, own, commanded, written, _ in fault.calls:
            if name == "action_conditioned_dynamics" and not applies(env_id, commanded):
                np.testing.assert_array_equal(written, own)
                continue
            expected = before + factor * handle.increment(before, own)
            handle.write_state(expected)  # as the simulator holds it (Acrobot: within bounds)
            np.testing.assert_allclose(written, handle.read_state(), rtol=0, atol=atol)
            scaled += 1
    env.close()
    assert scaled > 0


def applies(env_id: str, commanded: np.ndarray) -> bool:
    params = target_params(env_id)
    if "target_action" in params:
        return int(commanded) == params["target_action"]
    return bool(commanded[params["target_dim"]] > params["target_threshold"])


@pytest.mark.parametrize("env_id", [e for e in ENV_IDS if e in ("Pendulum-v1", "Hopper-v5")])
@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"target_action": 0}, r"'target_dim'.* \(\S+ has \d-dim continuous actions\)"),
        ({}, r"'target_dim'.*Got None"),
        ({"target_dim": 3, "target_threshold": 0.0}, r"'target_dim'.*range \[0, [13]\)"),
        ({"target_dim": 0, "target_threshold": 5.0}, r"'target_threshold'.*\[-([12]).0, \1.0\)"),
    ],
)
def test_a_predicate_the_action_space_cannot_evaluate_is_refused(env_id, params, message):
    injector = INJECTORS.get("action_conditioned_dynamics").from_params(params)
    with pytest.raises(ConfigError, match=message):
        injector.check_adapter(adapter_of(env_id))
