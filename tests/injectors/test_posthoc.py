import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from rollout_policies import HeuristicPolicy

from oodrl.core.spec import AnomalySpec
from oodrl.core.trajectory import Trajectory
from oodrl.envs.collect import collect
from oodrl.envs.lunar_lander import LunarLanderAdapter
from oodrl.errors import ContractError
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import perturb_posthoc

POSTHOC = [name for name in INJECTORS.names() if INJECTORS.get(name).mode == "posthoc"]
GRID = [0.1, 0.2, 0.4, 0.6, 0.8]
T, ONSET = 400, 133


@pytest.fixture(scope="module")
def clean():
    """Six clean LunarLander streams long enough to hold episode resets after the onset."""
    tset = collect(LunarLanderAdapter(), HeuristicPolicy(), range(10000, 10006), T)
    assert tset.dones[:, ONSET:].any()
    return tset


def make(name: str, **params):
    return INJECTORS.get(name).from_params(params)


def stream_of(states: np.ndarray, next_states: np.ndarray) -> np.ndarray:
    """The observation stream (T + 1, d) of one trajectory, or (N, T + 1, d) of a set."""
    return np.concatenate([states, next_states[..., -1:, :]], axis=-2)


def post_onset_distance(name: str, clean, severity: float) -> float:
    injector = make(name)
    perturbed = perturb_posthoc(injector, clean, injector.spec(severity, ONSET), seed=3)
    return float(np.linalg.norm(perturbed.states - clean.states, axis=-1)[:, ONSET:].mean())


@st.composite
def trajectories(draw):
    """A random trajectory with episode resets, an onset >= 1, an optional offset, and
    discrete or continuous actions (which no post-hoc injector may touch)."""
    length = draw(st.integers(4, 50))
    action_dim = draw(st.none() | st.integers(1, 3))
    d = draw(st.integers(1, 8))
    onset = draw(st.integers(1, length - 1))
    offset = draw(st.none() | st.integers(onset + 1, length))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    stream = rng.normal(size=(length + 1, d)).astype(np.float32)
    dones = rng.random(length) < 0.15
    next_states = stream[1:].copy()
    next_states[dones] = rng.normal(size=(int(dones.sum()), d))
    trajectory = Trajectory(
        states=stream[:-1],
        actions=(
            rng.integers(0, 4, length)
            if action_dim is None
            else rng.uniform(-1, 1, (length, action_dim)).astype(np.float32)
        ),
        rewards=rng.normal(size=length).astype(np.float32),
        next_states=next_states,
        dones=dones,
    )
    return trajectory, onset, offset


severities = st.floats(0.0, 1.0)


@pytest.mark.parametrize("name", POSTHOC)
@settings(max_examples=40, deadline=None)
@given(case=trajectories(), severity=severities, seed=st.integers(0, 2**16))
def test_only_labelled_steps_change_and_streams_stay_consistent(name, case, severity, seed):
    trajectory, onset, offset = case
    injector = make(name)
    spec = injector.spec(severity, onset, offset)
    perturbed, labels = injector.inject(trajectory, spec, np.random.default_rng(seed))

    np.testing.assert_array_equal(labels, spec.labels(trajectory.T))
    np.testing.assert_array_equal(perturbed.states[~labels], trajectory.states[~labels])
    for field in ("actions", "rewards", "dones"):
        np.testing.assert_array_equal(getattr(perturbed, field), getattr(trajectory, field))
    continuing = ~perturbed.dones[:-1]
    np.testing.assert_array_equal(
        perturbed.next_states[:-1][continuing], perturbed.states[1:][continuing]
    )
    np.testing.assert_array_equal(
        perturbed.next_states[perturbed.dones], trajectory.next_states[trajectory.dones]
    )
    again, _ = injector.inject(trajectory, spec, np.random.default_rng(seed))
    np.testing.assert_array_equal(again.states, perturbed.states)
    np.testing.assert_array_equal(again.next_states, perturbed.next_states)


@pytest.mark.parametrize("name", POSTHOC)
@settings(max_examples=25, deadline=None)
@given(case=trajectories(), seed=st.integers(0, 2**16))
def test_severity_zero_reproduces_the_clean_trajectory(name, case, seed):
    trajectory, onset, offset = case
    injector = make(name)
    perturbed, _ = injector.inject(
        trajectory, injector.spec(0.0, onset, offset), np.random.default_rng(seed)
    )
    np.testing.assert_array_equal(perturbed.states, trajectory.states)
    np.testing.assert_array_equal(perturbed.next_states, trajectory.next_states)


@pytest.mark.parametrize("name", POSTHOC)
def test_perturbation_grows_with_severity(name, clean):
    distances = [post_onset_distance(name, clean, severity) for severity in GRID]
    assert np.all(np.diff(distances) > 0), distances


@pytest.mark.parametrize("name", POSTHOC)
def test_perturb_posthoc_keeps_everything_but_the_observations(name, clean):
    injector = make(name)
    spec = injector.spec(0.5, ONSET)
    perturbed = perturb_posthoc(injector, clean, spec, seed=7)

    assert perturbed.attrs["spec"] == spec.to_dict() and perturbed.attrs["mode"] == "posthoc"
    np.testing.assert_array_equal(perturbed.labels, np.tile(spec.labels(T), (len(clean), 1)))
    for field in ("actions", "rewards", "dones", "executed_actions", "episode_index", "seeds"):
        np.testing.assert_array_equal(getattr(perturbed, field), getattr(clean, field))
    np.testing.assert_array_equal(perturbed.states[:, :ONSET], clean.states[:, :ONSET])
    continuing = ~perturbed.dones[:, :-1]
    np.testing.assert_array_equal(
        perturbed.next_states[:, :-1][continuing], perturbed.states[:, 1:][continuing]
    )
    again = perturb_posthoc(injector, clean, spec, seed=7)
    np.testing.assert_array_equal(again.states, perturbed.states)
    np.testing.assert_array_equal(again.next_states, perturbed.next_states)


def test_perturb_posthoc_refuses_a_spec_of_another_injector(clean):
    spec = AnomalySpec("regime_switch", 0.5, ONSET, mode="posthoc")
    with pytest.raises(ContractError, match="does not describe"):
        perturb_posthoc(make("gaussian_state_noise"), clean, spec, seed=0)


@pytest.mark.parametrize("severity", [0.2, 0.7])
def test_gaussian_noise_has_sd_severity_times_the_clean_sd(clean, severity):
    injector = make("gaussian_state_noise")
    perturbed = perturb_posthoc(injector, clean, injector.spec(severity, ONSET), seed=1)
    clean_stream = stream_of(clean.states, clean.next_states).astype(np.float64)
    sd = clean_stream.std(axis=1, keepdims=True)
    noise = stream_of(perturbed.states, perturbed.next_states) - clean_stream
    standardised = (noise / np.where(sd > 0, severity * sd, 1.0))[:, ONSET:]
    for i in range(clean.states.shape[-1]):
        has_spread = sd[:, 0, i] > 0
        values = standardised[has_spread, :, i].ravel()
        assert abs(values.std() - 1.0) < 0.1 and abs(values.mean()) < 0.1


@pytest.mark.parametrize("severity", [0.25, 0.9])
def test_dropout_zeroes_coordinates_at_rate_0_8_severity(clean, severity):
    injector = make("state_feature_dropout")
    perturbed = perturb_posthoc(injector, clean, injector.spec(severity, ONSET), seed=2)
    before, after = clean.states[:, ONSET:], perturbed.states[:, ONSET:]
    nonzero = before != 0
    dropped = after == 0
    np.testing.assert_array_equal(after[~dropped], before[~dropped])
    assert abs(dropped[nonzero].mean() - 0.8 * severity) < 0.03


@pytest.mark.parametrize("name", ["correlation_break"])
@settings(max_examples=40, deadline=None)
@given(case=trajectories(), severity=severities, seed=st.integers(0, 2**16))
def test_correlation_break_permutes_chosen_coordinates_within_the_window(
    name, case, severity, seed
):
    trajectory, onset, offset = case
    assume(not trajectory.dones[-1])  # else the stream's last row is a terminal row, kept as is
    injector = make(name)
    spec = injector.spec(severity, onset, offset)
    perturbed, labels = injector.inject(trajectory, spec, np.random.default_rng(seed))
    rows = np.flatnonzero(np.append(labels, labels[-1]))
    before = stream_of(trajectory.states, trajectory.next_states)[rows]
    after = stream_of(perturbed.states, perturbed.next_states)[rows]
    np.testing.assert_array_equal(np.sort(after, axis=0), np.sort(before, axis=0))
    changed = np.any(after != before, axis=0)
    assert changed.sum() <= math.ceil(severity * trajectory.state_dim)


def test_correlation_break_permutes_ceil_severity_times_d_coordinates(clean):
    injector = make("correlation_break")
    window = clean.states[:, ONSET:]
    constant = np.all(window == window[:, :1], axis=1).sum(axis=1)  # a permutation can't move
    for severity in GRID:
        perturbed = perturb_posthoc(injector, clean, injector.spec(severity, ONSET), seed=4)
        changed = np.any(perturbed.states[:, ONSET:] != window, axis=1).sum(axis=1)
        k = math.ceil(severity * clean.states.shape[-1])
        assert np.all(changed <= k) and np.all(changed >= k - constant), (severity, changed)


@settings(max_examples=40, deadline=None)
@given(case=trajectories(), severity=severities)
def test_regime_switch_moves_the_mean_and_scales_the_variance(case, severity):
    trajectory, onset, offset = case
    assume(not trajectory.dones[-1])  # else the stream's last row is a terminal row, kept as is
    injector = make("regime_switch")
    spec = injector.spec(severity, onset, offset)
    perturbed, labels = injector.inject(trajectory, spec, np.random.default_rng(0))
    stream_labels = np.append(labels, labels[-1])
    before = stream_of(trajectory.states, trajectory.next_states).astype(np.float64)
    after = stream_of(perturbed.states, perturbed.next_states).astype(np.float64)
    sd_pre = before[:onset].std(axis=0)
    window_before, window_after = before[stream_labels], after[stream_labels]
    np.testing.assert_allclose(
        window_after.mean(axis=0) - window_before.mean(axis=0), 2 * severity * sd_pre, atol=1e-5
    )
    np.testing.assert_allclose(
        window_after.var(axis=0),
        (1 + 2 * severity) * window_before.var(axis=0),
        rtol=1e-4,
        atol=1e-6,
    )


def test_regime_switch_is_deterministic(clean):
    injector = make("regime_switch")
    spec = injector.spec(0.5, ONSET)
    np.testing.assert_array_equal(
        perturb_posthoc(injector, clean, spec, seed=0).states,
        perturb_posthoc(injector, clean, spec, seed=1).states,
    )


@pytest.mark.parametrize(("severity", "max_delay"), [(0.05, 10), (0.5, 10), (0.8, 10), (1.0, 3)])
def test_delay_is_the_clean_stream_shifted_across_resets(clean, severity, max_delay):
    injector = make("observation_delay", max_delay=max_delay)
    perturbed = perturb_posthoc(injector, clean, injector.spec(severity, ONSET), seed=0)
    k = math.ceil(severity * max_delay)
    clean_stream = stream_of(clean.states, clean.next_states)
    np.testing.assert_array_equal(perturbed.states[:, ONSET:], clean_stream[:, ONSET - k : T - k])
    np.testing.assert_array_equal(perturbed.next_states[:, -1], clean_stream[:, T - k])
    # After a reset the delay line still serves the previous episode's last observations.
    episode, step = np.argwhere(clean.dones[:, ONSET:-1])[0]
    after_reset = ONSET + step + 1
    np.testing.assert_array_equal(
        perturbed.states[episode, after_reset], clean.states[episode, after_reset - k]
    )
    assert clean.episode_index[episode, after_reset - k] < clean.episode_index[episode, after_reset]


def test_delay_before_the_first_step_holds_the_first_observation():
    rng = np.random.default_rng(0)
    stream = rng.normal(size=(9, 2)).astype(np.float32)
    trajectory = Trajectory(
        states=stream[:-1],
        actions=np.zeros(8, np.int64),
        rewards=np.zeros(8, np.float32),
        next_states=stream[1:],
        dones=np.zeros(8, bool),
    )
    injector = make("observation_delay", max_delay=5)
    perturbed, _ = injector.inject(trajectory, injector.spec(1.0, 2), rng)
    np.testing.assert_array_equal(perturbed.states[2:6], np.repeat(stream[:1], 4, axis=0))
    np.testing.assert_array_equal(perturbed.states[6:], stream[1:3])


def test_regime_switch_needs_steps_before_the_onset():
    trajectory = Trajectory(
        states=np.ones((5, 2), np.float32),
        actions=np.zeros(5, np.int64),
        rewards=np.zeros(5, np.float32),
        next_states=np.ones((5, 2), np.float32),
        dones=np.zeros(5, bool),
    )
    injector = make("regime_switch")
    with pytest.raises(ContractError, match="onset >= 1"):
        injector.inject(trajectory, injector.spec(0.5, 0), np.random.default_rng(0))
