"""time_series_features: descriptors against a per-window reference, early steps, short input."""

import numpy as np
import pytest

from oodrl.detectors.time_series import TimeSeriesFeatures, window_descriptors
from oodrl.errors import ContractError
from oodrl.testing import linear_system_trajectories


def reference_descriptors(window: np.ndarray) -> np.ndarray:
    """The seven descriptors of one (L,) window, written plainly."""
    L = len(window)
    centred = window - window.mean()
    power = np.abs(np.fft.rfft(centred))[1:] ** 2
    frequencies = np.fft.rfftfreq(L)[1:]
    return np.array(
        [
            window.mean(),
            window.std(),
            np.polyfit(np.arange(L), window, 1)[0],
            np.sum(centred[:-1] * centred[1:]) / np.sum(centred**2),
            window.max() - window.min(),
            np.mean(np.abs(np.diff(window))),
            np.sum(frequencies * power) / np.sum(power),
        ]
    )


@pytest.mark.parametrize("length", [5, 8])
def test_descriptors_match_a_plain_per_window_computation(length):
    series = np.random.default_rng(0).standard_normal((20, 3))
    descriptors = window_descriptors(series, length)
    assert descriptors.shape == (20 - length + 1, 7 * 3)
    for row in range(descriptors.shape[0]):
        for coordinate in range(3):
            expected = reference_descriptors(series[row : row + length, coordinate])
            np.testing.assert_allclose(descriptors[row, coordinate::3], expected, atol=1e-12)


def test_constant_windows_have_zero_autocorrelation_and_spectrum():
    descriptors = window_descriptors(np.ones((6, 1)), 4)
    assert np.isfinite(descriptors).all()
    np.testing.assert_array_equal(descriptors[:, 3], 0.0)
    np.testing.assert_array_equal(descriptors[:, 6], 0.0)


@pytest.mark.parametrize("distance", ["mahalanobis", "robust_z"])
def test_early_steps_take_the_first_full_window_score(distance):
    data = linear_system_trajectories(5, seed=0)
    detector = TimeSeriesFeatures(window=10, distance=distance).fit(data[:4])
    scores = detector.score(data[4]).scores
    np.testing.assert_array_equal(scores[:9], scores[9])


def test_trajectories_shorter_than_the_window_are_refused():
    data = linear_system_trajectories(2, T=20, seed=0)
    with pytest.raises(ContractError, match="window=32"):
        TimeSeriesFeatures().fit(data)
    detector = TimeSeriesFeatures(window=8).fit(data)
    short = linear_system_trajectories(1, T=5, seed=0)[0]
    with pytest.raises(ContractError, match="window=8"):
        detector.score(short)
