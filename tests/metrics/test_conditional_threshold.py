"""Thresholds a deployer can trust and the false-alarm rate achieved (SPEC §19).

The null of the simulations: calibration and new stream maxima i.i.d. Uniform(0, 1), so a
threshold x has FAR = P(new max ≥ x) = 1 − x exactly, with no test streams to draw.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from scipy.stats import beta, binomtest
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.config import parse_params
from oodrl.errors import ConfigError
from oodrl.metrics.operating import (
    achieved_false_alarm_rate,
    conditional_rank,
    conditional_threshold,
    conformal_threshold,
    min_alpha_conditional,
    min_calibration_streams_conditional,
    per_stream_threshold,
)
from oodrl.metrics.stamp import params_hash

ALPHA, DELTA = 0.05, 0.1
N, DRAWS = 200, 2000


def _far_exceeds_alpha(n: int, k: int, alpha: float) -> float:
    """P(FAR > α) of the k-th smallest of n continuous maxima: FAR ~ Beta(n + 1 − k, k)."""
    return float(beta.sf(alpha, n + 1 - k, k))


@pytest.mark.parametrize(
    ("n", "alpha", "delta"), [(45, 0.05, 0.1), (200, 0.05, 0.1), (400, 0.01, 0.05), (39, 0.1, 0.2)]
)
def test_the_conditional_rank_is_the_least_order_statistic_the_beta_law_allows(n, alpha, delta):
    k = conditional_rank(n, alpha, delta)
    assert _far_exceeds_alpha(n, k, alpha) <= delta
    assert k == 1 or _far_exceeds_alpha(n, k - 1, alpha) > delta


def test_the_smallest_alpha_each_n_supports():
    # α_min(n) = 1 − δ^(1/n): k = n gives P(FAR > α) = (1 − α)^n ≤ δ.
    expected = {19: 0.114133, 39: 0.057332, 200: 0.011447, 400: 0.005740}
    for n, alpha_min in expected.items():
        assert min_alpha_conditional(n, DELTA) == pytest.approx(alpha_min, abs=1e-6)
    # The fewest streams for α = 0.05 at δ = 0.1: 45 (log 0.1 / log 0.95 = 44.9), exactly.
    assert min_calibration_streams_conditional(ALPHA, DELTA) == 45
    assert conditional_rank(45, ALPHA, DELTA) == 45 and conditional_rank(44, ALPHA, DELTA) is None
    # On the boundary (1 − α)^n = δ exactly (0.5² = 0.25) the rule holds: exact arithmetic.
    assert min_calibration_streams_conditional(0.5, 0.25) == 2 == conditional_rank(2, 0.5, 0.25)


def test_the_conditional_rule_bounds_far_in_all_but_delta_of_the_calibration_draws():
    rng = np.random.default_rng(0)
    maxima = rng.random((DRAWS, N))
    k = conditional_rank(N, ALPHA, DELTA)
    far = 1.0 - np.sort(maxima, axis=1)[:, k - 1]
    # The library's threshold is that order statistic, a float above it.
    for row in range(5):
        threshold = conditional_threshold(maxima[row], ALPHA, DELTA)
        assert threshold == np.nextafter(1.0 - far[row], np.inf)
    # P(FAR > α) ≤ δ; its estimate over 2,000 draws within 3 binomial standard errors
    # (3 · sqrt(δ(1 − δ) / 2000) ≈ 0.020). Here the exact P is 0.062 (k = 195 of 200).
    tolerance = 3 * math.sqrt(DELTA * (1 - DELTA) / DRAWS)
    assert np.mean(far > ALPHA) <= DELTA + tolerance


def test_the_marginal_rule_bounds_the_mean_far_only():
    rng = np.random.default_rng(1)
    maxima = rng.random((DRAWS, N))
    k = math.ceil((N + 1) * (1 - ALPHA))  # 191 of 200
    far = 1.0 - np.sort(maxima, axis=1)[:, k - 1]
    assert conformal_threshold(maxima[0], ALPHA) == np.nextafter(1.0 - far[0], np.inf)
    # E[FAR] = (n + 1 − k)/(n + 1) = 10/201 ≤ α; the mean of 2,000 draws within 4 standard
    # errors (FAR's sd ≈ 0.015, so 4 · 0.015 / sqrt(2000) ≈ 0.0014).
    assert np.mean(far) <= ALPHA + 4 * np.std(far) / math.sqrt(DRAWS)
    # But one draw's FAR exceeds α far more often than δ: why the conditional rule exists.
    assert _far_exceeds_alpha(N, k, ALPHA) > 0.4
    assert np.mean(far > ALPHA) > DELTA + 0.25


def test_ties_never_alarm_at_the_threshold_and_keep_the_guarantee():
    # All maxima equal: the threshold is just above them, so a stream reaching it never alarms.
    tied = np.full(N, 3.0)
    threshold = conditional_threshold(tied, ALPHA, DELTA)
    assert threshold == np.nextafter(3.0, np.inf)
    assert not (tied >= threshold).any()
    # Maxima on 50 integer values (many ties): FAR = P(new > X_(k)) = (49 − X_(k)) / 50 is
    # at most the continuous one, so P(FAR > α) ≤ δ still holds over draws.
    rng = np.random.default_rng(2)
    maxima = rng.integers(0, 50, size=(DRAWS, N)).astype(np.float64)
    thresholds = np.array([conditional_threshold(row, ALPHA, DELTA) for row in maxima[:200]])
    far = (49 - np.floor(thresholds)) / 50
    tolerance = 3 * math.sqrt(DELTA * (1 - DELTA) / len(far))
    assert np.mean(far > ALPHA) <= DELTA + tolerance


def test_too_few_streams_is_one_config_error_naming_the_fewest_and_the_smallest_alpha():
    with pytest.raises(ConfigError, match=r"at least 45 calibration streams.*alpha >= 0\.05734"):
        conditional_threshold(np.arange(39.0), ALPHA, DELTA)
    with pytest.raises(ConfigError, match="at least 45"):
        per_stream_threshold(np.arange(44.0), ALPHA, "episode_max_conditional", DELTA)
    assert per_stream_threshold(np.arange(45.0), ALPHA, "episode_max_conditional") == (
        np.nextafter(44.0, np.inf)
    )
    marginal = conformal_threshold(np.arange(39.0), ALPHA)
    assert per_stream_threshold(np.arange(39.0), ALPHA) == marginal


def test_check_params_refuses_too_few_streams_for_the_conditional_rule(tmp_path, default_params):
    from oodrl.suite.params_check import check_completely

    assert default_params["tiers"]["threshold_rule"] == "episode_max_conditional"
    default_params["tiers"]["n_calibration"] = 39
    with pytest.raises(ConfigError, match=r"tiers\.n_calibration: .* at least 45 .*got 39"):
        check_completely(parse_params(default_params))
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(default_params))
    result = CliRunner().invoke(app, ["check-params", str(bad)])
    assert result.exit_code == 2
    assert result.output.count("\n") == 1 and "tiers.n_calibration" in result.output
    default_params["tiers"]["n_calibration"] = 45
    check_completely(params := parse_params(default_params))
    assert params.tiers.threshold_rule == "episode_max_conditional"
    default_params["tiers"]["delta"] = 0.05  # δ = 0.05 at α = 0.05: n ≥ 59
    with pytest.raises(ConfigError, match="at least 59"):
        check_completely(parse_params(default_params))


def test_the_rule_and_its_delta_are_hashed(default_params):
    """Protocol version 3 hashes every tiers key: a results file says which rule made it."""
    default = parse_params(default_params)
    tiers = default.model_dump(mode="json")["tiers"]
    assert tiers["threshold_rule"] == "episode_max_conditional" and tiers["delta"] == 0.1
    default_params["tiers"].update(threshold_rule="episode_max")
    assert params_hash(parse_params(default_params)) != params_hash(default)


@pytest.mark.parametrize(("alarmed", "n"), [(0, 200), (3, 200), (11, 200), (200, 200), (7, 40)])
def test_the_achieved_false_alarm_rate_and_its_clopper_pearson_interval(alarmed, n):
    alarms = np.zeros((n, 30), bool)
    alarms[:alarmed, 7] = True
    alarms[:alarmed:2, 20] = True  # a second alarm in a stream counts once
    achieved = achieved_false_alarm_rate(alarms)
    exact = binomtest(alarmed, n).proportion_ci(confidence_level=0.95, method="exact")
    assert (achieved.n_alarmed, achieved.n_streams) == (alarmed, n)
    assert achieved.rate == alarmed / n
    assert achieved.ci_low == pytest.approx(exact.low, abs=1e-12)
    assert achieved.ci_high == pytest.approx(exact.high, abs=1e-12)


def test_the_achieved_rate_takes_streams_of_any_length():
    streams = [np.array([False, True]), np.zeros(5, bool), np.array([True])]
    achieved = achieved_false_alarm_rate(streams, confidence=0.9)
    exact = binomtest(2, 3).proportion_ci(confidence_level=0.9, method="exact")
    assert (achieved.n_alarmed, achieved.n_streams) == (2, 3)
    assert (achieved.ci_low, achieved.ci_high) == pytest.approx((exact.low, exact.high))
