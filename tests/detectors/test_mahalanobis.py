"""mahalanobis_distance on a hand-worked example."""

import numpy as np
import pytest

from oodrl.core.trajectory import Trajectory
from oodrl.detectors.mahalanobis import MahalanobisDistance


def _trajectory(states, actions=None) -> Trajectory:
    states = np.asarray(states, dtype=np.float32)
    T = len(states)
    return Trajectory(
        states=states,
        actions=np.zeros(T, dtype=np.int64) if actions is None else np.asarray(actions),
        rewards=np.zeros(T, dtype=np.float32),
        next_states=states,
        dones=np.zeros(T, dtype=bool),
    )


@pytest.mark.parametrize("ridge", [1e-3, 0.5])
def test_hand_worked_example(ridge):
    # Mean 0, covariance diag(0.5, 2): the standardised covariance is I, so the precision is
    # I / (1 + λ). The point (1, 2) standardises to (√2, √2): z = 4 / (1 + λ).
    fit = _trajectory([[1, 0], [-1, 0], [0, 2], [0, -2]])
    detector = MahalanobisDistance(ridge=ridge).fit([fit])
    scores = detector.score(_trajectory([[1, 2], [0, 0]])).scores
    np.testing.assert_allclose(scores, [4 / (1 + ridge), 0.0], atol=1e-12)


def test_matches_the_formula_with_the_ridge_on_standardised_features():
    rng = np.random.default_rng(0)
    states = rng.standard_normal((500, 3)) @ [[2, 0, 0], [1, 1, 0], [0, 0.3, 0.1]]
    fit = _trajectory(states)
    detector = MahalanobisDistance(ridge=0.1).fit([fit])
    x = fit.states.astype(np.float64)
    mean, std = x.mean(axis=0), x.std(axis=0)
    covariance = np.cov(x, rowvar=False, bias=True)
    # (x − μ)ᵀ(Σ + λI)⁻¹(x − μ) on standardised x equals (x − μ)ᵀ(Σ_raw + λ·D²)⁻¹(x − μ).
    precision = np.linalg.inv(covariance + 0.1 * np.diag(std**2))
    expected = np.einsum("ij,jk,ik->i", x - mean, precision, x - mean)
    np.testing.assert_allclose(detector.score(fit).scores, expected, rtol=1e-10)


def test_state_action_features_survive_collinear_one_hot_columns():
    rng = np.random.default_rng(1)
    actions = rng.integers(0, 3, 300)
    fit = _trajectory(rng.standard_normal((300, 2)), actions)
    detector = MahalanobisDistance(features="state_action").fit([fit])
    unseen_action = _trajectory(np.zeros((1, 2)), [7])
    assert detector.score(unseen_action).scores[0] > detector.score(fit).scores.max()
