import numpy as np
import pytest

from oodrl.core.detector import episode_max_threshold
from oodrl.errors import ConfigError
from oodrl.metrics.operating import (
    clopper_pearson,
    conformal_threshold,
    delay_text,
    first_raise,
    min_alpha,
    min_calibration_streams,
    operating_point,
)

T, ONSET = 10, 4


def hand_worked_scores() -> np.ndarray:
    """Five faulty streams, threshold 1, onset 4 (alarm steps in brackets):
    s0 [5]; s1 [2, 6]; s2 [8]; s3 none; s4 [3]."""
    scores = np.zeros((5, T))
    for row, steps in enumerate([[5], [2, 6], [8], [], [3]]):
        scores[row, steps] = 2.0
    return scores


def test_detection_rate_at_k_matches_the_hand_worked_example():
    clean = np.zeros((4, T))
    clean[0, 7] = 1.0  # one clean stream touches the threshold: an alarm (score >= threshold)
    # Latency 0: first raises 5, 2, 8, none, 3. Detected within K = 2: s0 only; s1 and s4 raise
    # their first alarm before the onset (false alarms, although s1 alarms again at 6).
    point = operating_point(hand_worked_scores(), clean, 1.0, ONSET, k=2, curve_ks=[0, 1, 2, 4, 5])
    record = point.as_dict()
    assert record["detection_rate"] == pytest.approx(1 / 5)
    assert record["early_false_alarm_rate"] == pytest.approx(2 / 5)
    # Delays only from the streams detected within K (SPEC §19): s2's raise at 8 is no delay.
    assert point.delays == (1,)
    # One detected stream: its count is kept, its median not shown (fewer than 5).
    assert record["delay"] == {"median": None, "p90": None, "n_detected": 1}
    assert record["detection_curve"] == {0: 0.0, 1: 0.2, 2: 0.2, 4: 0.4, 5: 0.4}
    assert record["clean_false_alarm_rate"] == pytest.approx(1 / 4)
    # Latency 1 (the score of t needs s_{t+1}): raises 6, 3, 9, none, 4. s4's alarm at step 3 is
    # raised at the onset: a detection with delay 0; s1's first raise (3) is still early.
    late = operating_point(hand_worked_scores(), clean, 1.0, ONSET, k=2, latency=1)
    assert late.detection_rate == pytest.approx(2 / 5)
    assert late.early_false_alarms == 1
    assert late.delays == (2, 0)


def test_a_cell_with_fewer_than_5_detections_prints_no_delay():
    """SPEC §19: delays only from streams detected within K, with their count, not shown
    below 5. Streams first alarm at 4 + j (j = 0..5); K = 3 detects four of them."""
    scores = np.zeros((6, T))
    for j in range(6):
        scores[j, ONSET + j] = 2.0
    few = operating_point(scores, scores[:0], 1.0, ONSET, k=3).as_dict()["delay"]
    assert few == {"median": None, "p90": None, "n_detected": 4}
    assert delay_text(few) == "— (n = 4)"
    enough = operating_point(scores, scores[:0], 1.0, ONSET, k=4).as_dict()["delay"]
    assert enough == {"median": 2.0, "p90": 3.6, "n_detected": 5}
    assert delay_text(enough) == "2 (n = 5)"


def test_an_alarm_raised_beyond_the_stream_is_no_alarm():
    alarms = np.zeros((2, T), bool)
    alarms[0, T - 1] = True
    assert first_raise(alarms, latency=0).tolist() == [T - 1, T]
    assert first_raise(alarms, latency=3).tolist() == [T, T]


def test_conformal_threshold_is_the_episode_max_rule_and_refuses_too_few_streams():
    maxima = np.arange(19.0)
    assert conformal_threshold(maxima, 0.05) == episode_max_threshold(maxima, 0.05)
    assert min_calibration_streams(0.05) == 19 and min_calibration_streams(0.1) == 9
    assert min_alpha(19) == pytest.approx(0.05) and min_alpha(6) == pytest.approx(1 / 7)
    with pytest.raises(ConfigError, match="at least 19 held-out"):
        conformal_threshold(maxima[:18], 0.05)


@pytest.mark.parametrize("n_calibration", [19, 25])
def test_the_per_stream_rule_keeps_alpha_over_calibration_draws(n_calibration):
    """Under a known null (iid N(0, 1) scores) the clean false-alarm rate, averaged over many
    calibration draws, is at most α and at least α − 1/(n + 1) (the conformal bounds)."""
    alpha, draws, n_test, horizon = 0.05, 2000, 40, 30
    rng = np.random.default_rng(0)
    rates = np.empty(draws)
    for i in range(draws):
        calibration = rng.standard_normal((n_calibration, horizon)).max(axis=1)
        threshold = conformal_threshold(calibration, alpha)
        clean = rng.standard_normal((n_test, horizon))
        point = operating_point(clean, clean, threshold, onset=0, alpha=alpha)
        rates[i] = point.clean_false_alarms / point.n_clean
    # Standard error of the mean: about 0.048 / sqrt(2000) ≈ 0.001 per calibration draw.
    assert rates.mean() <= alpha + 0.005
    assert rates.mean() >= alpha - 1 / (n_calibration + 1) - 0.005


def test_clopper_pearson_against_known_values():
    low, high = clopper_pearson(0, 20)
    assert low == 0.0 and high == pytest.approx(0.168433, abs=1e-5)
    low, high = clopper_pearson(5, 10)
    assert (low, high) == (pytest.approx(0.187086, abs=1e-5), pytest.approx(0.812914, abs=1e-5))
