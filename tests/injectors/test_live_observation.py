"""The live observation faults on a real simulator (LunarLander, gymnasium's heuristic pilot)."""

import math

import numpy as np
import pytest
from rollout_policies import HeuristicPolicy

from oodrl.envs.collect import collect, episode_seed
from oodrl.envs.lunar_lander import LunarLanderAdapter
from oodrl.errors import ConfigError
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import collect_online, injector_rng
from oodrl.injectors.live_observation import LIVE_COUNTERPARTS, reference_statistics

LIVE = sorted(LIVE_COUNTERPARTS.values())
SEEDS = list(range(20000, 20004))
T, ONSET = 300, 100
FIELDS = ("states", "actions", "rewards", "next_states", "dones", "executed_actions")
ADAPTER, POLICY = LunarLanderAdapter(), HeuristicPolicy()


@pytest.fixture(scope="module")
def clean():
    return collect(ADAPTER, POLICY, SEEDS, T)


def run(injector, severity, seeds=SEEDS, horizon=T, onset=ONSET):
    spec = injector.spec(severity, onset)
    return collect_online(injector, ADAPTER, POLICY, seeds, horizon, spec, 0, policy_seed=0)


@pytest.mark.parametrize("name", LIVE)
def test_steps_before_the_onset_are_the_clean_twins_bit_for_bit(name, clean):
    faulty = run(INJECTORS.get(name)(), 0.8)
    assert faulty.attrs["mode"] == "online"
    for field in FIELDS:
        # The fault acts from the onset step: the first reported observation it corrupts is the
        # one that step emits, next_states[ONSET]; everything before is the clean twin's.
        np.testing.assert_array_equal(
            getattr(faulty, field)[:, :ONSET], getattr(clean, field)[:, :ONSET]
        )
    assert not np.array_equal(faulty.next_states[:, ONSET:], clean.next_states[:, ONSET:])


@pytest.mark.parametrize("name", LIVE)
def test_the_policy_acts_on_what_the_sensor_reports(name):
    faulty = run(INJECTORS.get(name)(), 0.6)
    # The recorded states are the reported ones: the policy's actions follow from them, and
    # each reported observation is the next step's state (no episode ends between them).
    for j in range(len(SEEDS)):
        np.testing.assert_array_equal(faulty.actions[j], POLICY.act(faulty.states[j]))
    continuing = ~faulty.dones[:, :-1]
    np.testing.assert_array_equal(
        faulty.next_states[:, :-1][continuing], faulty.states[:, 1:][continuing]
    )


def test_the_first_observation_after_a_reset_is_reported_through_the_fault_too():
    stats = {"mean": [0.1] * 8, "scale": [0.5] * 8}
    severity = 0.5
    injector = INJECTORS.get("live_regime_switch")(**stats)
    faulty = run(injector, severity, onset=20)
    widening = math.sqrt(1 + 2 * severity) - 1
    env = ADAPTER.make()
    resets = 0
    for j, t in zip(*np.nonzero(faulty.dones[:, 20:-1]), strict=True):
        t += 20
        episode = faulty.episode_index[j, t + 1]
        true = env.reset(seed=episode_seed(SEEDS[j], int(episode)))[0].astype(np.float64)
        expected = true + (widening * (true - 0.1) + 2 * severity * 0.5)
        np.testing.assert_allclose(faulty.states[j, t + 1], expected.astype(np.float32))
        resets += 1
    env.close()
    assert resets > 0  # the streams hold episode ends after the onset


def true_observations() -> np.ndarray:
    """A clean LunarLander observation sequence (one stream, within its first episode)."""
    tset = collect(ADAPTER, POLICY, [SEEDS[0]], 80)
    return tset.states[0].astype(np.float64)


def reports(name: str, severity: float, observations: np.ndarray, **params) -> np.ndarray:
    """What a fresh fault reports for a sequence of true observations (open loop)."""
    injector = INJECTORS.get(name)(**params)
    fault = injector.fault(injector.spec(severity, 0), injector_rng(0, name, 0))
    return np.stack([fault.report(x) for x in observations])


@pytest.mark.parametrize("name", LIVE)
def test_every_live_fault_is_causal(name):
    """A report depends on the true observations so far only: two sequences that agree up to a
    step get the same reports up to it, whatever follows."""
    observations = true_observations()
    changed = observations.copy()
    changed[40:] += 5.0
    first, second = reports(name, 0.7, observations), reports(name, 0.7, changed)
    np.testing.assert_array_equal(first[:40], second[:40])
    assert not np.array_equal(first[40:], second[40:])


@pytest.mark.parametrize("name", LIVE)
def test_open_loop_corruption_grows_with_severity(name):
    observations = true_observations()
    grid = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    corruption = [np.abs(reports(name, s, observations) - observations).mean() for s in grid]
    assert corruption[0] == 0.0
    if name == "live_observation_delay":
        corruption = corruption[:3]  # the lag grows; the gap to a lagged value need not
    assert np.all(np.diff(corruption) >= 0) and corruption[-1] > corruption[1], corruption


def test_correlation_break_reports_earlier_values_of_the_chosen_coordinates_only():
    observations = true_observations()
    reported = reports("live_correlation_break", 0.5, observations)
    changed = np.flatnonzero((reported != observations).any(axis=0))
    assert 0 < changed.size <= math.ceil(0.5 * 8)
    for t in range(len(observations)):
        for i in changed:
            assert reported[t, i] in observations[: t + 1, i]


def test_observation_delay_lags_k_steps_after_its_line_fills():
    observations = true_observations()
    reported = reports("live_observation_delay", 0.3, observations, max_delay=10)
    k = 3
    np.testing.assert_array_equal(reported[k:], observations[:-k])
    np.testing.assert_array_equal(reported[:k], np.repeat(observations[:1], k, axis=0))


def test_noise_uses_the_given_scale_and_reference_statistics_are_the_clean_moments(clean):
    stats = reference_statistics(clean.states)
    np.testing.assert_allclose(
        stats["scale"], clean.states.reshape(-1, 8).astype(np.float64).std(axis=0)
    )
    observations = true_observations()
    scale = [0.0] * 7 + [1.0]
    noise = reports("live_gaussian_state_noise", 0.5, observations, scale=scale) - observations
    assert np.all(noise[:, :7] == 0) and abs(noise[:, 7].std() - 0.5) < 0.1


@pytest.mark.parametrize("name", ["live_gaussian_state_noise", "live_regime_switch"])
def test_statistics_of_the_wrong_length_are_refused(name):
    injector = INJECTORS.get(name).from_params({"scale": [1.0, 1.0]})
    with pytest.raises(ConfigError, match="'scale' parameter .* one entry per observation"):
        injector.check_adapter(ADAPTER)
