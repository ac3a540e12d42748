"""kde_density against an exact log-density (scipy cdist + logsumexp over every kernel).

Tolerance: |error| <= 1e-7 · max(1, |log p̂|) nats — the log-density is certified to 24 significant
bits (relative 6e-8) so that it is the same on every machine (SPEC §14) — including points
hundreds to thousands of bandwidths from every kernel centre, where tree-based approximations
(scikit-learn's KernelDensity) were measured several nats off.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist
from scipy.special import logsumexp
from scipy.stats import gaussian_kde

from oodrl.core.trajectory import Trajectory
from oodrl.detectors.kde import KdeDensity, bandwidth_of, gaussian_kde_logpdf

RTOL = 1e-7


def exact_logpdf(x: np.ndarray, reference: np.ndarray, bandwidth: float) -> np.ndarray:
    n, d = reference.shape
    exponents = -cdist(x, reference, "sqeuclidean") / (2 * bandwidth**2)
    return logsumexp(exponents, axis=1) - np.log(n) - 0.5 * d * np.log(2 * np.pi * bandwidth**2)


def assert_close(actual: np.ndarray, expected: np.ndarray) -> None:
    np.testing.assert_array_less(np.abs(actual - expected), RTOL * np.maximum(1, np.abs(expected)))


@pytest.mark.parametrize("bandwidth", [0.05, 0.4, 3.0])
def test_logpdf_matches_exact_including_far_outliers(bandwidth):
    rng = np.random.default_rng(0)
    reference = rng.standard_normal((700, 5))
    inliers = rng.standard_normal((300, 5))
    outliers = rng.standard_normal((40, 5)) * np.logspace(1, 3, 40)[:, None]
    x = np.vstack([inliers, outliers])  # > 128 rows: several blocks
    assert_close(
        gaussian_kde_logpdf(x, reference, bandwidth), exact_logpdf(x, reference, bandwidth)
    )


def test_one_dimensional_single_kernel_is_a_normal_logpdf():
    x = np.array([[0.0], [1.0], [-250.0]])
    expected = -0.5 * np.log(2 * np.pi * 0.25) - x[:, 0] ** 2 / (2 * 0.25)
    assert_close(gaussian_kde_logpdf(x, np.zeros((1, 1)), 0.5), expected)


@pytest.mark.parametrize("rule", ["scott", "silverman"])
def test_bandwidth_rules_match_scipy_factors(rule):
    data = np.random.default_rng(1).standard_normal((3, 200))
    kde = gaussian_kde(data, bw_method=rule)
    assert bandwidth_of(rule, 200, 3) == pytest.approx(kde.factor, rel=1e-12)


def _trajectory(states: np.ndarray) -> Trajectory:
    T = len(states)
    return Trajectory(
        states=states.astype(np.float32),
        actions=np.zeros(T, dtype=np.int64),
        rewards=np.zeros(T, dtype=np.float32),
        next_states=states.astype(np.float32),
        dones=np.zeros(T, dtype=bool),
    )


def test_detector_scores_are_exact_negative_log_density_of_standardised_states():
    rng = np.random.default_rng(2)
    fit = _trajectory(rng.standard_normal((600, 3)) * [1.0, 5.0, 0.1] + [0.0, 2.0, -1.0])
    scored = _trajectory(np.vstack([rng.standard_normal((50, 3)), [[40.0, -300.0, 9.0]]]))
    detector = KdeDensity(max_reference=250, bandwidth=0.3, seed=3).fit([fit])
    states = fit.states.astype(np.float64)
    mean, std = states.mean(axis=0), states.std(axis=0)
    reference = (
        states[np.sort(np.random.default_rng(3).choice(600, 250, replace=False))] - mean
    ) / std
    x = (scored.states.astype(np.float64) - mean) / std
    assert_close(detector.score(scored).scores, -exact_logpdf(x, reference, 0.3))


def test_epsilon_is_added_to_the_density():
    rng = np.random.default_rng(4)
    fit = _trajectory(rng.standard_normal((200, 2)))
    scored = _trajectory(np.array([[0.0, 0.0], [30.0, 30.0]]))
    plain = KdeDensity().fit([fit]).score(scored).scores
    capped = KdeDensity(epsilon=1e-6).fit([fit]).score(scored).scores
    np.testing.assert_allclose(capped, -np.log(np.exp(-plain) + 1e-6), rtol=1e-9)
    assert capped[1] == pytest.approx(-np.log(1e-6))


def test_fast_path_equals_the_exact_path_on_every_row(monkeypatch):
    # The BLAS exponents and numpy's exp/log are certified against the index-order exponents
    # summed in decimal: forcing that exact path on every row must change no bit.
    from oodrl import numerics

    rng = np.random.default_rng(5)
    reference = rng.standard_normal((300, 4))
    x = np.vstack(
        [
            rng.standard_normal((200, 4)),
            rng.standard_normal((30, 4)) * np.logspace(0.5, 3, 30)[:, None],
        ]
    )
    fast = gaussian_kde_logpdf(x, reference, 0.3)
    certify = numerics.certify

    def everywhere_exact(values, bound, exact, bits=numerics.CERTIFIED_BITS):
        return certify(values, np.full_like(values, np.inf), exact, bits)

    monkeypatch.setattr(numerics, "certify", everywhere_exact)
    np.testing.assert_array_equal(fast, gaussian_kde_logpdf(x, reference, 0.3))
