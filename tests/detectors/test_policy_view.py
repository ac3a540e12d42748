"""The policy view and its detectors (SPEC §20): `q_margin`, `q_entropy`, `q_energy`,
`max_softmax` read what the agent's own policy computed on the observation it saw."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from scipy.special import logsumexp, softmax
from scipy.stats import entropy
from test_contract import POLICIES, SPLITS
from test_sanity import CLEAN, FIT, ONSET, matched_auroc

from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.detectors.policy_view import DEFAULT_POLICY, TemperedValues, fitted_temperature
from oodrl.envs.collect import collect
from oodrl.envs.lunar_lander import LunarLanderAdapter
from oodrl.errors import ConfigError
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import injector_rng
from oodrl.policies.load import load_policy
from oodrl.suite.environments import policy_path
from oodrl.suite.pipeline import POLICY
from oodrl.testing import linear_system_trajectories

ROOT = Path(__file__).resolve().parents[2]
#: The committed LunarLander-v3 policy: a NoisyNet DQN.
LUNAR_LANDER = ROOT / "models" / "policy.pt"
#: A committed SAC actor (tanh_actor): no value head.
PENDULUM = policy_path("Pendulum-v1", ROOT)
VIEW = ["q_margin", "q_entropy", "q_energy", "max_softmax"]
FIT_DISCRETE, _, EVALUATION = SPLITS["discrete"]


@cache
def fitted(name: str, **params) -> object:
    return DETECTORS.get(name)(policy=POLICIES["discrete"], **params).fit(FIT_DISCRETE)


def test_the_default_policy_is_the_pipelines():
    assert DEFAULT_POLICY == POLICY


# -- what the agent saw ---------------------------------------------------------------------------
class _SpyingSensor:
    """A live sensor fault that also keeps every true observation it is handed, in order."""

    def __init__(self, fault) -> None:
        self.fault, self.true = fault, []

    def before_step(self, t, commanded, sim):
        return self.fault.before_step(t, commanded, sim)

    def after_step(self, t, observation, commanded, sim):
        self.true.append(np.array(observation))
        return self.fault.after_step(t, observation, commanded, sim)

    def after_reset(self, t, observation, sim):
        self.true.append(np.array(observation))
        return self.fault.after_reset(t, observation, sim)


def true_states(recorded: Trajectory, spy: _SpyingSensor, onset: int) -> np.ndarray:
    """The simulator's observations behind `recorded.states`: the recorded ones up to the onset
    (the sensor acts from the observation step `onset` emits), then the spy's, the first
    observation after a reset taking the place of the terminal one."""
    states = recorded.states.copy()
    true = iter(spy.true)
    for t in range(onset, recorded.T):
        observation = next(true)
        if recorded.dones[t]:
            observation = next(true)
        if t + 1 < recorded.T:
            states[t + 1] = observation
    return states


@pytest.fixture(scope="module")
def live_noise():
    """Two LunarLander streams under a live sensor noise (σ = 1, sd 0.5 on every coordinate)
    from step 40, with the true observations behind them; the committed policy acts greedily."""
    T, onset, seeds = 150, 40, [30_000, 30_001]  # noqa: N806
    adapter, policy = LunarLanderAdapter(), load_policy(LUNAR_LANDER)
    injector = INJECTORS.get("live_gaussian_state_noise")(mean=[0.0] * 8, scale=[0.5] * 8)
    spec = injector.spec(1.0, onset)
    spies = [
        _SpyingSensor(injector.fault(spec, injector_rng(0, injector.injector_name, j)))
        for j in range(len(seeds))
    ]
    faulty = collect(adapter, policy, seeds, T, labels=spec.labels(T), faults=spies)
    streams = faulty.trajectories()
    return streams, [true_states(s, spy, onset) for s, spy in zip(streams, spies, strict=True)]


def test_the_view_is_the_policy_on_the_observation_the_agent_saw(live_noise):
    streams, truths = live_noise
    policy = load_policy(LUNAR_LANDER)
    detector = DETECTORS.get("q_margin")(policy=str(LUNAR_LANDER)).fit(streams)
    for stream, true in zip(streams, truths, strict=True):
        view = detector.policy_view([stream])
        # The first corrupted observation is the one step 40 emits: states[41].
        assert (stream.states[41:] != true[41:]).all()
        # The view is the policy's values of the reported observation, on which it acted...
        np.testing.assert_array_equal(view, policy.outputs(stream.states))
        np.testing.assert_array_equal(view.argmax(axis=1), stream.actions)
        # ...not of the simulator's state, which it never saw.
        of_the_truth = policy.outputs(true)
        np.testing.assert_array_equal(view[:41], of_the_truth[:41])
        assert (view[41:] != of_the_truth[41:]).any(axis=1).all()
        assert (of_the_truth[41:].argmax(axis=1) != stream.actions[41:]).any()
        expected = -np.diff(np.sort(view.astype(np.float64), axis=1)[:, -2:], axis=1)[:, 0]
        np.testing.assert_allclose(
            detector.score(stream).scores, expected / detector.temperature_, rtol=1e-12
        )


def lunar_lander_streams(seeds: list[int], T: int) -> list[Trajectory]:  # noqa: N803
    """Clean streams of the committed LunarLander policy."""
    adapter, policy = LunarLanderAdapter(), load_policy(LUNAR_LANDER)
    return collect(adapter, policy, seeds, T).trajectories()


@cache
def fitted_lunar_lander(name: str):
    return DETECTORS.get(name)(policy=str(LUNAR_LANDER)).fit(lunar_lander_streams([40_000], 60))


def test_a_noisy_policy_is_read_as_its_mean_network():
    detector = fitted_lunar_lander("q_energy")
    assert load_policy(LUNAR_LANDER).kind == "noisy_dqn"
    assert all(layer.weight_sigma is None for layer in detector.policy_.layers)
    assert detector.policy_.mode == "greedy"
    assert len(pickle.dumps(detector)) < 0.6 * LUNAR_LANDER.stat().st_size


def test_a_fitted_detector_scores_without_torch_or_the_policy_file():
    detector = fitted_lunar_lander("max_softmax")
    (trajectory,) = lunar_lander_streams([40_001], 30)
    code = (
        "import pickle, sys; detector, trajectory = pickle.load(sys.stdin.buffer); "
        "scores = detector.score(trajectory).scores; "
        "sys.exit('torch' in sys.modules or len(scores) != trajectory.T)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], input=pickle.dumps((detector, trajectory)), cwd="/"
    )
    assert result.returncode == 0


# -- the scores -----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", VIEW)
def test_scores_are_their_definitions_on_the_tempered_values(name):
    detector = fitted(name)
    q = detector.policy_view(EVALUATION).astype(np.float64)
    z = q / detector.temperature_
    expected = {
        "q_margin": -np.diff(np.sort(z, axis=1)[:, -2:], axis=1)[:, 0],
        "q_entropy": entropy(softmax(z, axis=1), axis=1),
        "q_energy": -detector.temperature_ * logsumexp(z, axis=1),
        "max_softmax": -softmax(z, axis=1).max(axis=1),
    }[name]
    scores = np.concatenate([o.scores for o in detector.score_many(EVALUATION)])
    np.testing.assert_allclose(scores, expected, rtol=1e-8, atol=1e-12)


def test_the_fitted_temperature_gives_the_target_mean_entropy():
    q = fitted("q_entropy").policy_view(FIT_DISCRETE)
    for target in (0.2, 0.5, 0.9):
        temperature = fitted_temperature(q, target)
        mean = entropy(softmax(q.astype(np.float64) / temperature, axis=1), axis=1).mean()
        assert mean == pytest.approx(target * np.log(q.shape[1]), rel=1e-9)
    assert fitted("q_entropy").temperature_ == fitted_temperature(q, 0.5)
    assert fitted_temperature(np.ones((5, 3)), 0.5) == 1.0  # every value equal: T is moot


def test_a_fixed_temperature_is_used_as_given():
    assert fitted("q_energy", temperature=2.5).temperature_ == 2.5


def test_far_worse_actions_weigh_nothing_and_keep_their_margin():
    tempered = TemperedValues.of(np.array([[1e4, -1e4, 0.0]], np.float32), 1.0)
    assert tempered.partition[0] == 1.0 and tempered.log_partition[0] == 0.0
    assert abs(tempered.entropy()[0]) < 1e-200
    np.testing.assert_array_equal(tempered.shifted, [[0.0, -2e4, -1e4]])  # not floored


def dead_sensor(trajectory: Trajectory, onset: int) -> Trajectory:
    """Every observation coordinate reads 0 from the onset (a dead sensor)."""
    states = trajectory.states.copy()
    states[onset:] = 0.0
    return trajectory.replace(states=states)


def devalued(trajectory: Trajectory, onset: int, detector) -> Trajectory:
    """Observations moved, from the onset, along the direction that lowers every action's value
    by the same amount (the linear system's policy has values P s): the softmax is unchanged,
    only the value level drops, by 3 standard deviations of the clean best value."""
    weight = detector.policy_.layers[0].weight.astype(np.float64)
    direction = np.linalg.pinv(weight) @ -np.ones(len(weight))
    drop = 3.0 * detector.policy_view(FIT).max(axis=1).std()
    states = trajectory.states.copy()
    states[onset:] += (drop * direction).astype(np.float32)
    return trajectory.replace(states=states)


@pytest.mark.parametrize("name", VIEW)
def test_each_detector_flags_its_blatant_anomaly(name):
    # Away from the origin a linear policy grows more confident, so test_sanity's regime switch
    # is no anomaly of the view (matched AUROC 0.1–0.3). A dead sensor puts the policy where
    # every action is worth the same: the least confident view. The energy reads the value
    # level, which a dead sensor leaves in the clean range: its anomaly is devalued states.
    detector = DETECTORS.get(name)(policy=POLICIES["discrete"]).fit(FIT)
    if name == "q_energy":
        perturbed = [devalued(t, ONSET, detector) for t in CLEAN]
    else:
        perturbed = [dead_sensor(t, ONSET) for t in CLEAN]
    assert matched_auroc(detector, CLEAN, perturbed) > 0.95


# -- what the view cannot read --------------------------------------------------------------------
@pytest.mark.parametrize("name", VIEW)
def test_a_sac_actor_is_refused_in_one_line_with_the_reason(name):
    actor = load_policy(PENDULUM)
    assert actor.kind == "tanh_actor"
    assert "tanh_actor" in DETECTORS.get(name).policy_support(actor)
    pendulum_like = linear_system_trajectories(2, T=20, state_dim=3, action_dim=1)
    with pytest.raises(ConfigError) as refusal:
        DETECTORS.get(name)(policy=str(PENDULUM)).fit(pendulum_like)
    message = str(refusal.value)
    assert "\n" not in message
    assert message.startswith(f"{name} cannot use {PENDULUM}: ")
    assert "discrete action head" in message and "tanh_actor" in message


def test_a_discrete_policy_is_supported():
    assert DETECTORS.get("q_margin").policy_support(load_policy(LUNAR_LANDER)) is None


def test_a_missing_policy_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="'policy' parameter of q_entropy: cannot read"):
        DETECTORS.get("q_entropy")(policy=str(tmp_path / "none.pt")).fit(FIT_DISCRETE)


def test_a_policy_of_another_dimension_is_a_config_error():
    expected = "observation dimension 8; the fit trajectories have dimension 4"
    with pytest.raises(ConfigError, match=expected):
        DETECTORS.get("q_margin")(policy=str(LUNAR_LANDER)).fit(FIT_DISCRETE)


def test_a_callable_policy_is_refused(tmp_path):
    pointer = tmp_path / "policy.json"
    spec = {"callable": "x:act", "state_dim": 4, "action_kind": "discrete", "action_size": 3}
    pointer.write_text(json.dumps({"format": "oodrl-callable", **spec}))
    with pytest.raises(ConfigError, match="is a callable policy: convert it"):
        DETECTORS.get("max_softmax")(policy=str(pointer)).fit(FIT_DISCRETE)
