"""Shared feature extraction: action encodings, feature sets, standardisation."""

import numpy as np
import pytest

from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    ActionEncoding,
    Standardizer,
    seeded_subsample,
    trajectory_features,
)
from oodrl.detectors.mahalanobis import MahalanobisDistance
from oodrl.errors import ContractError


def _trajectory(actions, T=4) -> Trajectory:
    states = np.arange(2 * T, dtype=np.float32).reshape(T, 2)
    return Trajectory(
        states=states,
        actions=np.asarray(actions),
        rewards=np.zeros(T, dtype=np.float32),
        next_states=states + 1,
        dones=np.zeros(T, dtype=bool),
    )


def test_discrete_actions_are_one_hot_and_unseen_ones_all_zero():
    encoding = ActionEncoding.fit([_trajectory([0, 2, 1, 2])])
    assert encoding == ActionEncoding(3, 3)
    np.testing.assert_array_equal(
        encoding.encode(np.array([2, 0, 5, -1])),
        [[0, 0, 1], [1, 0, 0], [0, 0, 0], [0, 0, 0]],
    )


def test_continuous_actions_pass_through_and_shapes_are_checked():
    actions = np.linspace(-1, 1, 12, dtype=np.float32).reshape(4, 3)
    encoding = ActionEncoding.fit([_trajectory(actions)])
    assert encoding == ActionEncoding(None, 3)
    np.testing.assert_array_equal(encoding.encode(actions), actions)
    with pytest.raises(ContractError):
        encoding.encode(np.zeros(4, dtype=np.int64))
    detector = MahalanobisDistance(features="transition").fit([_trajectory(actions)])
    assert detector.score(_trajectory(actions)).scores.shape == (4,)


@pytest.mark.parametrize(
    ("feature_set", "width"), [("state", 2), ("state_action", 5), ("transition", 7)]
)
def test_feature_sets(feature_set, width):
    trajectory = _trajectory([0, 1, 2, 0])
    features = trajectory_features(trajectory, feature_set, ActionEncoding(3, 3))
    assert features.shape == (4, width)
    assert features.dtype == np.float64
    if feature_set == "transition":
        np.testing.assert_array_equal(features[:, -2:], 1.0)  # s' − s


def test_standardizer_keeps_constant_columns_finite():
    x = np.column_stack([np.arange(5.0), np.full(5, 3.0)])
    standardizer = Standardizer.fit(x)
    np.testing.assert_array_equal(standardizer.scale[1], 1.0)
    z = standardizer.transform(x)
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(z[:, 0].std(), 1.0)


def test_seeded_subsample():
    np.testing.assert_array_equal(seeded_subsample(5, 10, seed=0), np.arange(5))
    picked = seeded_subsample(100, 10, seed=0)
    assert len(np.unique(picked)) == 10 and np.all(np.diff(picked) > 0)
    np.testing.assert_array_equal(picked, seeded_subsample(100, 10, seed=0))
