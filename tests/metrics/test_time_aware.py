"""The time-aware per-stream rule (SPEC §24): a per-step standardiser from the fit streams only,
then the constant rule's order statistic on the standardised calibration maxima.

The clean law of the simulations: T = 100 steps of independent N(0, σ_t²) scores, σ_t = 1 in the
quiet phase (steps 0–49) and 10 in the loud phase (50–99). Because the law is known, a threshold's
false-alarm rate is exact: a stream alarms iff some x_t ≥ loc_t + thr · scale_t, so
FAR = 1 − Π_t Φ((loc_t + thr · scale_t) / σ_t), with no test streams to draw.
"""

from __future__ import annotations

import inspect
import math

import numpy as np
import pytest
from scipy.stats import binom, norm

from oodrl.errors import ContractError
from oodrl.metrics.operating import conditional_rank, conditional_threshold
from oodrl.metrics.time_aware import (
    ALPHAS,
    IQR_PER_SD,
    MIN_WINDOW_VALUES,
    alpha_curve,
    first_alarm_steps,
    fit_step_standardiser,
    rule_operating_point,
    stream_detections,
    stream_maxima,
    time_aware_threshold,
)

T, QUIET = 100, 50
SD = np.r_[np.ones(QUIET), np.full(T - QUIET, 10.0)]
N_FIT, N_CAL = 100, 200  # 100 fit streams: interior windows of 3 steps (300 values)
ALPHA, DELTA = 0.05, 0.1


def _clean(rng: np.random.Generator, *shape: int) -> np.ndarray:
    return rng.standard_normal((*shape, T)) * SD


def _reference(id_scores: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The standardiser's definition, one step at a time (slow and plain)."""
    length = max(s.size for s in id_scores)
    at = [np.array([s[t] for s in id_scores if s.size > t]) for t in range(length)]
    held = np.concatenate([[0], np.cumsum([a.size for a in at])])
    windows = []
    for t in range(length):
        h = 0
        while held[min(t + h + 1, length)] - held[max(t - h, 0)] < MIN_WINDOW_VALUES:
            h += 1
        windows.append((max(t - h, 0), min(t + h + 1, length)))
    pooled = [np.concatenate(at[a:b]) for a, b in windows]
    location = np.array([np.quantile(v, 0.5) for v in pooled])
    raw = np.array([np.subtract(*np.quantile(v, [0.75, 0.25])) / IQR_PER_SD for v in pooled])
    everything = np.concatenate(id_scores)
    floor = 0.1 * (np.subtract(*np.quantile(everything, [0.75, 0.25])) / IQR_PER_SD)
    return location, np.maximum([raw[a:b].max() for a, b in windows], floor)


def test_the_standardiser_follows_its_definition_on_streams_of_many_lengths():
    rng = np.random.default_rng(1)
    fit = [rng.standard_cauchy(int(n)) for n in rng.integers(5, 101, size=12)]
    fit.append(rng.standard_cauchy(400))  # late steps: one long stream, windows ~300 wide
    standardiser = fit_step_standardiser(fit)
    location, scale = _reference(fit)
    np.testing.assert_array_equal(standardiser.location, location)
    np.testing.assert_array_equal(standardiser.scale, scale)
    assert standardiser.half_width[-1] == 299  # steps 100..399 hold one value each


def test_windows_quartiles_and_the_steps_beyond_the_fit():
    # 100 streams of the values 0..9: interior windows {t−1, t, t+1} × 100, median t, IQR 2.
    standardiser = fit_step_standardiser([np.arange(10.0)] * 100)
    assert standardiser.half_width.tolist() == [2, 1, 1, 1, 1, 1, 1, 1, 1, 2]
    assert standardiser.location[1:9].tolist() == list(range(1, 9))
    assert standardiser.location[[0, 9]].tolist() == [1, 8]  # cut windows {0, 1, 2}, {7, 8, 9}
    np.testing.assert_allclose(standardiser.scale, 2 / IQR_PER_SD)
    # Steps beyond the longest fit stream keep the last step's location and scale.
    z = standardiser.standardise(np.full(13, 8.0))
    np.testing.assert_array_equal(z[9:], 0.0)
    np.testing.assert_allclose(z[:3], (8 - np.array([1, 1, 2])) * IQR_PER_SD / 2)


def test_a_window_that_dips_takes_its_largest_scale_and_a_constant_step_the_floor():
    rng = np.random.default_rng(2)
    # Windows of 3 steps: step 50's window (49–51) holds one quiet step, whose pooled IQR
    # (≈ 0.47 × the loud sd for that mixture) would make the first loud step's scale too small.
    fit = _clean(rng, N_FIT)
    dipped = np.subtract(*np.quantile(fit[:, QUIET - 1 : QUIET + 2], [0.75, 0.25])) / IQR_PER_SD
    assert dipped < 6
    # The largest in the window: a loud window's (50–52: 10 within sampling error).
    assert fit_step_standardiser(list(fit)).scale[QUIET] > 7
    fit = rng.standard_normal((300, 8))  # 300 streams: every window is its own step
    fit[:, 3] = 0.0  # a step where the detector is constant: scale 0 without the floor
    standardiser = fit_step_standardiser(list(fit))
    pooled = np.subtract(*np.quantile(fit, [0.75, 0.25])) / IQR_PER_SD
    assert standardiser.scale[3] == pytest.approx(0.1 * pooled)
    assert standardiser.scale[[0, 1, 2, 4]].min() > 0.9
    # All constant: no scale anywhere, standardising only shifts.
    assert fit_step_standardiser([np.full(10, 2.0)] * 30).scale.tolist() == [1.0] * 10
    with pytest.raises(ContractError, match="at least 300"):
        fit_step_standardiser([np.zeros(10)] * 29)


def test_the_standardiser_reads_the_fit_streams_only():
    # The API: fit streams are its one input.
    assert list(inspect.signature(fit_step_standardiser).parameters) == ["id_scores"]
    rng = np.random.default_rng(3)
    fit, calibration, audit = _clean(rng, N_FIT), _clean(rng, N_CAL), _clean(rng, 100)
    faulty = _clean(rng, 50)
    standardiser = fit_step_standardiser(list(fit))
    before = standardiser.location.tobytes(), standardiser.scale.tobytes()
    thresholds = []
    for scale in (1.0, 3.0):  # perturbed calibration and audit streams
        thresholds.append(time_aware_threshold(standardiser, calibration * scale, ALPHA))
        alpha_curve(calibration * scale, faulty, audit * scale, 20, standardiser=standardiser)
        assert (standardiser.location.tobytes(), standardiser.scale.tobytes()) == before
    assert thresholds[0] != thresholds[1]  # they do reach the threshold
    assert not standardiser.scale.flags.writeable
    # The same fit streams give the same bytes; other fit streams other statistics.
    again = fit_step_standardiser(list(fit))
    assert (again.location.tobytes(), again.scale.tobytes()) == before
    changed = fit.copy()
    changed[:, :QUIET] += 1.0
    other = fit_step_standardiser(list(changed))
    assert not np.array_equal(other.location, standardiser.location)
    assert not np.array_equal(fit_step_standardiser(list(fit * 2)).scale, standardiser.scale)


def _exact_far(location: np.ndarray, scale: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """Per draw (rows), P(a fresh clean stream alarms) at its standardiser and threshold."""
    bound = (location + threshold[:, None] * scale) / SD
    return -np.expm1(norm.logcdf(bound).sum(axis=1))


def test_the_false_alarm_promise_holds_under_a_time_varying_clean_law():
    """500 draws of (fit, calibration), each thresholded by both per-stream rules.

    Marginal: the threshold is the ⌈201 · 0.95⌉ = 191st of 200 maxima, so FAR ~ Beta(10, 191)
    given the fit (the calibration maxima of z stay i.i.d.): E[FAR] = 10/201 and
    sd(FAR) = √(10 · 191 / (201² · 202)) = 0.0153, so the mean over 500 draws is within
    4 · 0.0153 / √500 = 0.0027 of 10/201 but for a 4-sd event.
    Conditional: P(FAR > α) = P(Binomial(200, α) ≤ 200 − k) = p ≤ δ exactly; the count of
    500 draws with FAR > α is Binomial(500, p), checked within 3.5 of its sd (√(500 p (1 − p))).
    Fresh streams: 100 a draw through `first_alarm_steps` (50 000 in all): their alarm share is
    within 4 binomial sd (√(0.05 · 0.95 / 50 000) ≈ 0.001) of the mean exact FAR.
    """
    rng = np.random.default_rng(4)
    draws, n_fresh = 500, 100
    location, scale = np.empty((draws, T)), np.empty((draws, T))
    marginal, conditional, fresh_alarms = np.empty(draws), np.empty(draws), 0
    for i in range(draws):
        standardiser = fit_step_standardiser(list(_clean(rng, N_FIT)))
        calibration = _clean(rng, N_CAL)
        location[i], scale[i] = standardiser.location, standardiser.scale
        marginal[i] = time_aware_threshold(standardiser, calibration, ALPHA, DELTA, "episode_max")
        conditional[i] = time_aware_threshold(standardiser, calibration, ALPHA, DELTA)
        first = first_alarm_steps(_clean(rng, n_fresh), marginal[i], standardiser=standardiser)
        fresh_alarms += sum(step is not None for step in first)
    far = _exact_far(location, scale, marginal)
    sd = math.sqrt(10 * 191 / (201**2 * 202))
    assert abs(far.mean() - 10 / 201) <= 4 * sd / math.sqrt(draws)
    assert abs(fresh_alarms / (draws * n_fresh) - far.mean()) <= 4 * math.sqrt(
        ALPHA * (1 - ALPHA) / (draws * n_fresh)
    )
    k = conditional_rank(N_CAL, ALPHA, DELTA)
    p = binom.cdf(N_CAL - k, N_CAL, ALPHA)
    assert p <= DELTA
    exceed = int(np.sum(_exact_far(location, scale, conditional) > ALPHA))
    assert abs(exceed - draws * p) <= 3.5 * math.sqrt(draws * p * (1 - p))


def test_a_quiet_phase_fault_is_caught_by_the_time_aware_rule_only():
    # +3 (3 quiet-phase sd) on steps 20–49: standardised, each faulty step exceeds the
    # threshold (~3.3) with probability ~0.4, so nearly every stream alarms within K = 20;
    # the constant threshold (~33, set by the loud phase's maxima) is out of the quiet's reach.
    rng = np.random.default_rng(5)
    standardiser = fit_step_standardiser(list(_clean(rng, N_FIT)))
    calibration, audit, faulty = _clean(rng, N_CAL), _clean(rng, 200), _clean(rng, 500)
    onset, k = 20, 20
    faulty[:, onset:QUIET] += 3.0
    rates = {}
    for rule, fitted in (("constant", None), ("time_aware", standardiser)):
        if fitted is None:
            threshold = conditional_threshold(stream_maxima(calibration), ALPHA)
        else:
            threshold = time_aware_threshold(fitted, calibration, ALPHA)
        detections = stream_detections(faulty, threshold, onset, k, standardiser=fitted)
        point = rule_operating_point(faulty, audit, threshold, onset, fitted, alpha=ALPHA, k=k)
        assert point.detected == detections.sum()
        rates[rule] = detections.mean()
    assert rates["time_aware"] >= 0.95
    assert rates["constant"] <= 0.02


def test_the_alpha_curve_reports_unsupported_alphas_and_monotone_thresholds():
    rng = np.random.default_rng(6)
    standardiser = fit_step_standardiser(list(_clean(rng, N_FIT)))
    calibration, audit, faulty = _clean(rng, N_CAL), _clean(rng, 200), _clean(rng, 100)
    faulty[:, 20:QUIET] += 3.0
    for fitted in (None, standardiser):
        curve = alpha_curve(calibration, faulty, audit, 20, standardiser=fitted, k=20)
        assert [r["alpha"] for r in curve] == list(ALPHAS)
        assert {r["rule"] for r in curve} == {"time_aware" if fitted else "constant"}
        # 200 streams at δ = 0.1 support α ≥ 1 − 0.1^(1/200) = 0.0114: not 0.01.
        unsupported = curve[0]
        assert not unsupported["supported"] and "threshold" not in unsupported
        assert "needs at least 230 calibration streams" in unsupported["reason"]
        supported = curve[1:]
        assert all(r["supported"] for r in supported)
        thresholds = [r["threshold"] for r in supported]
        assert thresholds == sorted(thresholds, reverse=True) and len(set(thresholds)) == 4
        for r in supported:
            assert r["detection_rate_ci"][0] <= r["detection_rate"] <= r["detection_rate_ci"][1]
            low, high = r["clean_false_alarm_ci"]
            assert low <= r["clean_false_alarm_rate"] <= high and r["n_clean"] == 200
            assert r["early_false_alarm_rate"] == r["early_false_alarms"] / 100
            assert set(r["delay"]) == {"median", "p90", "mean", "n_detected"}
            if r["delay"]["n_detected"] >= 5:
                assert r["delay"]["median"] <= r["delay"]["p90"]
            else:
                assert r["delay"]["median"] is r["delay"]["mean"] is None
        if fitted is not None:
            at = next(r for r in curve if r["alpha"] == 0.05)
            assert at["threshold"] == time_aware_threshold(standardiser, calibration, 0.05)
            assert at["detection_rate"] >= 0.9
    # Fewer streams lose more α; the marginal rule supports α ≥ 1/(n + 1) and is never used
    # in the conditional one's place.
    curve = alpha_curve(calibration[:50], faulty, audit, 20, standardiser=standardiser)
    assert [r["supported"] for r in curve] == [False, False, True, True, True]
    marginal = alpha_curve(
        calibration[:50], faulty, audit, 20, standardiser=standardiser, threshold_rule="episode_max"
    )
    assert [r["supported"] for r in marginal] == [False, True, True, True, True]
    assert "needs at least 99 held-out trajectories" in marginal[0]["reason"]
    # Deterministic: the same inputs, the same records.
    assert curve == alpha_curve(calibration[:50], faulty, audit, 20, standardiser=standardiser)


def test_first_alarm_steps_side_by_side():
    # Half the fit values 0, half 1.349: median 0.6745, IQR / 1.349 = 1, so z = s − 0.6745.
    standardiser = fit_step_standardiser([np.zeros(4), np.full(4, IQR_PER_SD)] * 150)
    np.testing.assert_allclose(standardiser.location, IQR_PER_SD / 2)
    np.testing.assert_allclose(standardiser.scale, 1.0)
    scores = np.array([[0.0, 0.0, 3.5, 0.0], [0.0, 0.0, 0.0, 0.0], [2.6, 0.0, 0.0, 0.0]])
    assert first_alarm_steps(scores, 2.5) == [2, None, 0]
    assert first_alarm_steps(scores, 2.5, latency=2) == [None, None, 2]
    assert first_alarm_steps(scores, 2.5, standardiser=standardiser) == [2, None, None]
    assert first_alarm_steps(scores, 2.5, latency=1, standardiser=standardiser) == [3, None, None]
