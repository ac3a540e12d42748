"""`conformal_martingale` (SPEC §20): its p-values, its martingale, Ville's alarm level, and the
false-alarm bound on exchangeable (i.i.d.) streams."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from oodrl.core.detector import ville_threshold
from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.detectors.martingale import conformal_p_values
from oodrl.errors import ConfigError, ContractError
from oodrl.testing import check_streaming, check_threshold, linear_system_trajectories

ALPHA = 0.1


def iid_streams(n: int, T: int, seed: int, shift_from: int | None = None) -> list[Trajectory]:  # noqa: N803
    """Streams whose steps are i.i.d.: states N(0, I₄), uniform actions, episodes of 25 steps;
    from `shift_from` on the states move by 1.5 in every coordinate."""
    streams = []
    for index in range(n):
        rng = np.random.default_rng([seed, index])
        states = rng.standard_normal((T + 1, 4)).astype(np.float32)
        if shift_from is not None:
            states[shift_from:] += 1.5
        dones = np.zeros(T, dtype=bool)
        dones[24::25] = True
        streams.append(
            Trajectory(
                states=states[:-1],
                actions=rng.integers(3, size=T),
                rewards=np.zeros(T, np.float32),
                next_states=states[1:],
                dones=dones,
            )
        )
    return streams


def martingale(**params):
    return DETECTORS.get("conformal_martingale")(alpha=ALPHA, **params)


def test_p_values_follow_their_definition():
    rng = np.random.default_rng(0)
    reference = np.sort(rng.integers(0, 6, 40).astype(float))  # ties on purpose
    scores = rng.integers(0, 7, 30).astype(float)
    uniforms = 1.0 - rng.random(30)
    expected = []
    for t, a in enumerate(scores):
        pool = np.r_[reference, scores[:t]]
        greater, equal = np.sum(pool > a), np.sum(pool == a)
        expected.append((greater + uniforms[t] * (equal + 1)) / (len(pool) + 1))
    np.testing.assert_array_equal(conformal_p_values(reference, scores, uniforms), expected)


def test_p_values_of_exchangeable_scores_are_independent_uniforms():
    rng = np.random.default_rng(1)
    reference = np.sort(rng.standard_normal(300))
    p = conformal_p_values(reference, rng.standard_normal(2000), 1.0 - rng.random(2000))
    assert stats.kstest(p, "uniform").pvalue > 1e-3
    # Independent: no lag-1 correlation beyond noise (sd ≈ 1/√2000 ≈ 0.022).
    assert abs(np.corrcoef(p[:-1], p[1:])[0, 1]) < 0.08


def test_false_alarms_on_iid_streams_stay_within_alpha():
    """Ville: P(sup_t M_t ≥ 1/α) ≤ α on exchangeable steps. 300 i.i.d. streams of 100 steps
    against α = 0.1: the share with any alarm must not exceed α by more than 3 standard errors
    (0.017). (Measured: 0.007; Ville's bound is loose for a mixture.)"""
    detector = martingale().fit(iid_streams(8, 100, seed=0))
    detector.calibrate(iid_streams(2, 100, seed=1))
    outputs = detector.score_many(iid_streams(300, 100, seed=2))
    rate = np.mean([o.alarms.any() for o in outputs])
    assert rate <= ALPHA + 3 * math.sqrt(ALPHA * (1 - ALPHA) / 300)


def test_the_bound_does_not_hold_for_dependent_steps():
    """The documented limitation: clean streams of the linear system (consecutive states
    strongly dependent) are not exchangeable, and far more than α of them alarm (measured
    0.56): the achieved rate is what results report."""
    data = linear_system_trajectories(60, T=100, episode_length=80, seed=0)
    detector = martingale().fit(data[:10]).calibrate(data[10:12])
    rate = np.mean([o.alarms.any() for o in detector.score_many(data[12:])])
    assert rate > 3 * ALPHA


def test_a_sustained_shift_raises_the_alarm():
    detector = martingale().fit(iid_streams(8, 100, seed=0)).calibrate(iid_streams(2, 100, 1))
    outputs = detector.score_many(iid_streams(20, 100, seed=3, shift_from=40))
    first = [int(np.argmax(o.alarms)) if o.alarms.any() else None for o in outputs]
    detected_after_onset = [f for f in first if f is not None and f >= 40]
    assert len(detected_after_onset) >= 18
    assert np.median(detected_after_onset) < 50


def test_the_score_is_the_log_of_the_mixture_of_power_martingales():
    fit = iid_streams(8, 60, seed=0)
    stream = iid_streams(1, 60, seed=4)[0]
    epsilons = [0.2, 0.5, 0.9]
    detector = martingale(epsilons=epsilons).fit(fit)
    base = detector.base_.score(stream).scores
    uniforms = 1.0 - np.random.default_rng(detector.seed).random(60)
    p = conformal_p_values(detector.reference_, base, uniforms)
    products = [np.cumprod(e * p ** (e - 1)) for e in epsilons]
    expected = np.log(np.mean(products, axis=0))
    np.testing.assert_allclose(detector.score(stream).scores, expected, rtol=1e-8, atol=1e-9)


def test_the_threshold_is_villes_whatever_the_calibration_scores():
    detector = martingale().fit(iid_streams(8, 60, seed=0))
    check_threshold(detector, iid_streams(3, 60, seed=5))
    assert detector.threshold_ == ville_threshold(ALPHA)
    assert detector.threshold_ == pytest.approx(math.log(1 / ALPHA), rel=1e-9)
    other = martingale(threshold_rule="percentile").fit(iid_streams(8, 60, seed=0))
    assert other.calibrate(iid_streams(3, 60, seed=5)).threshold_ != detector.threshold_


def test_only_martingales_take_the_ville_rule():
    with pytest.raises(ConfigError, match="threshold_rule='ville'"):
        DETECTORS.get("mahalanobis_distance")(threshold_rule="ville").validate_params()
    martingale().validate_params()


def test_streaming_with_a_look_ahead_base_is_exact():
    data = linear_system_trajectories(8, T=90, episode_length=40, seed=0)
    params = {"base": "lyapunov_divergence", "base_params": {"horizon": 3, "max_reference": 200}}
    detector = martingale(**params).fit(data[:6])
    assert detector.latency == 3
    check_streaming(detector.calibrate(data[6:7]), data[6:])


def test_base_parameters_and_the_split():
    data = linear_system_trajectories(8, T=60, seed=0)
    detector = martingale(base_params={"features": "transition"}, reference_fraction=0.5)
    assert detector.latency == 1
    detector.fit(data)
    # Half of the 8 fit streams (60 steps each) give the reference scores.
    assert len(detector.reference_) == 4 * 60
    assert detector.base_.features == "transition" and detector.base_.seed == detector.seed


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"base": "conformal_martingale"}, "another detector"),
        ({"base": "pyod.models.knn:KNN"}, "not certified machine-independent"),
        ({"base_params": {"ridge": -1.0}}, "'ridge' parameter"),
        ({"epsilons": [0.5, 1.0]}, "'epsilons' parameter"),
    ],
)
def test_bad_parameters(params, message):
    with pytest.raises(ConfigError, match=message):
        martingale(**params).validate_params()


def test_fit_needs_two_trajectories():
    with pytest.raises(ContractError, match="at least 2 trajectories"):
        martingale().fit(iid_streams(1, 30, seed=0))
