"""cusum_tv: cusum's W_t against a clean per-age curve b fitted on the held-out half of the fit
streams. The contract, the curve's parts (pooled quantiles, isotonic fit, ages), the split, and
on synthetic streams whose residual grows with time: W's quantiles grow, cusum_tv's stay ≈ 1."""

import numpy as np
import pytest

from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.detectors.cusum import Cusum
from oodrl.detectors.cusum_tv import (
    CusumTV,
    ages,
    model_and_curve_halves,
    nondecreasing,
    pooled_quantiles,
)
from oodrl.errors import ConfigError, ContractError
from oodrl.testing import check_detector, check_streaming, linear_system_trajectories

#: The data of the registered detectors' contract tests (tests/detectors/test_contract.py).
DATA = linear_system_trajectories(10, T=120, episode_length=80, seed=0)
CONTINUOUS = linear_system_trajectories(10, T=120, action_dim=2, seed=0)


def drifting(n, *, seed, T=300, offset=0.0, onset=None):  # noqa: N803
    """Clean streams whose transition noise grows along the stream (its sd 0.09 → 0.13): the
    residual's level drifts with time, as on Acrobot. `offset` is added to the first
    coordinate's increment from `onset` on: a mean shift of the dynamics."""
    sigma = 0.1 * (0.9 + 0.4 * np.arange(T) / T)
    streams = []
    for index in range(n):
        rng = np.random.default_rng([seed, index])
        states = rng.standard_normal((T, 2))
        increments = sigma[:, None] * rng.standard_normal((T, 2))
        if onset is not None:
            increments[onset:, 0] += offset
        streams.append(
            Trajectory(
                states=states.astype(np.float32),
                actions=rng.integers(0, 2, T),
                rewards=np.zeros(T, np.float32),
                next_states=(states + increments).astype(np.float32),
                dones=np.zeros(T, bool),
            )
        )
    return streams


def third_quantiles(scores, q=0.9):
    """The q-quantile of the (n, T) scores of each third of the steps."""
    return [float(np.quantile(part, q)) for part in np.array_split(scores, 3, axis=1)]


@pytest.mark.parametrize("residual", ["transition", "state"])
@pytest.mark.parametrize("data", [DATA, CONTINUOUS], ids=["discrete", "continuous"])
def test_contract(data, residual):
    check_detector(lambda: CusumTV(residual=residual), data[:6], data[6:8], data[8:])


def test_contract_with_resets():
    check_detector(lambda: CusumTV(reset_on_done=True), DATA[:6], DATA[6:8], DATA[8:])


# -- the curve's parts -----------------------------------------------------------------------------
def test_ages_count_from_the_last_restart():
    restarts = np.array([True, False, False, True, False, True, True, False])
    np.testing.assert_array_equal(ages(restarts), [0, 1, 2, 0, 1, 0, 0, 1])


def test_nondecreasing_pools_a_dip_into_its_neighbours():
    # 3 > 1 violates: pooled to 2, then (2, 2) against 2 stands; 5 after it stays.
    np.testing.assert_array_equal(nondecreasing(np.array([3.0, 1.0, 2.0, 5.0])), [2, 2, 2, 5])


def test_pooled_quantiles_by_hand():
    # Ages 0, 1, 2 hold 2, 2 and 1 values.
    values = np.array([1.0, 5.0, 2.0, 6.0, 9.0])
    value_ages = np.array([0, 0, 1, 1, 2])
    # Each age alone holds enough: the ⌈0.5·m⌉-th smallest of its own values.
    np.testing.assert_array_equal(pooled_quantiles(values, value_ages, 0.5, 1), [1, 2, 9])
    # 3 values: age 0 pools ages 0..1 (4 values; the window is clipped at 0), age 1 pools
    # 0..2, age 2 pools 1..2 (3 values).
    np.testing.assert_array_equal(pooled_quantiles(values, value_ages, 0.5, 3), [2, 5, 6])
    np.testing.assert_array_equal(pooled_quantiles(values, value_ages, 0.9, 3), [6, 9, 9])
    # More than there are: every age pools everything.
    np.testing.assert_array_equal(pooled_quantiles(values, value_ages, 0.5, 99), [5, 5, 5])


# -- the split -------------------------------------------------------------------------------------
def test_the_model_sees_the_even_half_and_the_curve_the_odd_half():
    assert model_and_curve_halves(5) == ([0, 2, 4], [1, 3])
    fit = drifting(12, seed=3, T=100)
    detector = CusumTV(slack=0.25, min_pool=10).fit(fit)
    model_half, curve_half = [fit[i] for i in range(0, 12, 2)], [fit[i] for i in range(1, 12, 2)]
    # The residual model, ν and k are cusum's own fit on the even-indexed streams.
    alone = Cusum(slack=0.25).fit(model_half)
    np.testing.assert_array_equal(
        detector.residual_model_.model.coefficients, alone.residual_model_.model.coefficients
    )
    assert (detector.residual_mean_, detector.slack_) == (alone.residual_mean_, alone.slack_)
    # b is the floored isotonic pooled quantile of W on the odd-indexed streams.
    statistic = np.concatenate([o.scores for o in alone.score_many(curve_half)])
    step_ages = np.tile(np.arange(100), len(curve_half))
    floor = float(alone._residuals(curve_half).std())
    expected = np.maximum(nondecreasing(pooled_quantiles(statistic, step_ages, 0.9, 10)), floor)
    np.testing.assert_array_equal(detector.curve_, expected)
    assert detector.floor_ == floor


def test_a_changed_stream_moves_only_its_halfs_part():
    fit = drifting(8, seed=4, T=100)
    detector = CusumTV(min_pool=8).fit(fit)

    def with_tail_noise(index):
        """Stream `index` with its last 30 increments tripled."""
        stream = fit[index]
        increments = stream.next_states - stream.states
        increments[70:] *= 3
        changed = list(fit)
        changed[index] = stream.replace(next_states=stream.states + increments)
        return CusumTV(min_pool=8).fit(changed)

    model_changed = with_tail_noise(2)  # even: the residual model's half
    assert model_changed.residual_mean_ != detector.residual_mean_
    curve_changed = with_tail_noise(3)  # odd: the curve's half
    assert curve_changed.residual_mean_ == detector.residual_mean_
    np.testing.assert_array_equal(
        curve_changed.residual_model_.model.coefficients,
        detector.residual_model_.model.coefficients,
    )
    assert not np.array_equal(curve_changed.curve_, detector.curve_)
    assert np.all(curve_changed.curve_[80:] > detector.curve_[80:])


def test_fit_needs_two_trajectories_and_valid_params():
    with pytest.raises(ContractError, match="at least 2 trajectories"):
        CusumTV().fit(DATA[:1])
    with pytest.raises(ConfigError, match="'quantile' parameter of CusumTV"):
        CusumTV(quantile=1.0).fit(DATA[:4])
    with pytest.raises(ConfigError, match="'min_pool' parameter of CusumTV"):
        CusumTV(min_pool=0).fit(DATA[:4])


# -- the scores ------------------------------------------------------------------------------------
def test_score_is_w_over_the_curve_at_the_age_and_the_last_value_beyond():
    detector = CusumTV(reset_on_done=True).fit(DATA[:6])
    longer = linear_system_trajectories(1, T=400, episode_length=300, seed=5)[0]
    step_ages = ages(detector._restarts(longer))
    assert step_ages.max() >= len(detector.curve_)  # some steps are older than any fit step
    statistic = Cusum._score_many(detector, [longer])[0]
    expected = statistic / detector.curve_[np.minimum(step_ages, len(detector.curve_) - 1)]
    np.testing.assert_array_equal(detector.score(longer).scores, expected)
    check_streaming(detector.calibrate(DATA[6:8]), [longer])


def test_w_grows_with_time_on_clean_streams_and_cusum_tv_stays_near_one():
    # Slack 0.25: W is not 0 at most early steps (where the floor of b would set the scores).
    detector = CusumTV(slack=0.25).fit(drifting(200, seed=10))
    clean = drifting(100, seed=11)
    statistic = np.stack(Cusum._score_many(detector, clean))
    w = third_quantiles(statistic)
    z = third_quantiles(np.stack([o.scores for o in detector.score_many(clean)]))
    assert w[1] > 2 * w[0] and w[2] > 2 * w[1], w
    assert all(0.75 < q < 1.25 for q in z), z
    assert max(z) / min(z) < 1.5 < w[2] / w[0], (z, w)


def test_an_early_mean_shift_is_detected_sooner_than_by_a_constant_threshold():
    fit, calibration = drifting(200, seed=10), drifting(40, seed=11)
    shifted = drifting(40, seed=12, offset=0.2, onset=30)
    delays = {}
    for detector in (CusumTV(slack=0.25), Cusum(slack=0.25)):
        detector.fit(fit).calibrate(calibration)
        alarms = np.stack([o.alarms for o in detector.score_many(shifted)])
        assert alarms[:, :30].mean() < 0.05, detector.name
        after = alarms[:, 30:]
        assert after.any(axis=1).all(), detector.name
        delays[detector.name] = float(np.median(after.argmax(axis=1)))
        if detector.name == "cusum_tv":
            assert after[:, :30].mean() > 0.8
            clean = detector.score_many(drifting(40, seed=13))
            assert np.mean([o.alarms.mean() for o in clean]) < 0.05
    assert delays["cusum_tv"] <= 5 and delays["cusum"] > 3 * delays["cusum_tv"], delays


def test_params_name_it_by_its_path():
    assert DETECTORS.get("oodrl.detectors.cusum_tv:CusumTV") is CusumTV
    assert CusumTV.name == "cusum_tv" and CusumTV().latency == 1
    assert CusumTV(residual="state").latency == 0
