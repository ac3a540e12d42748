"""`deedee` (SPEC §20): a hand-worked example of the running mean, the time-aligned training
summaries, the per-step median bandwidth and both similarities; resets and streams."""

from __future__ import annotations

import math

import numpy as np
import pytest

from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.detectors.deedee import episode_steps, running_means
from oodrl.testing import check_streaming, linear_system_trajectories


def stream(values: list[float], dones: list[int] = ()) -> Trajectory:
    """A 1-d stream with these states (the next state: the following value, or the last one
    repeated); `dones` marks the steps that end an episode."""
    states = np.array(values, dtype=np.float32)[:, None]
    ends = np.zeros(len(values), dtype=bool)
    ends[list(dones)] = True
    return Trajectory(
        states=states,
        actions=np.zeros(len(values), dtype=np.int64),
        rewards=np.zeros(len(values), dtype=np.float32),
        next_states=np.r_[states[1:], states[-1:]],
        dones=ends,
    )


#: Two training episodes of 4 steps: A = 0, 2, 4, 6 (running means 0, 1, 2, 3) and B = 2, 2,
#: 2, 2 (running means 2, 2, 2, 2).
FIT = [stream([0, 2, 4, 6], dones=[3]), stream([2, 2, 2, 2], dones=[3])]
#: One episode 1, 3, 5, 7, 9: running means 1, 2, 3, 4, 5.
SCORED = stream([1, 3, 5, 7, 9])


def test_hand_worked_scores():
    """The fit states have mean 2.5 and standard deviation s = √2.75; distances and bandwidths
    are both in units of s, which cancel in D/h². Per episode step τ (training summaries A_τ,
    B_τ; h_τ = |A_τ − B_τ|, the median of the one pair):

        τ = 0: m = 1, A = 0, B = 2, h = 2: both at distance 1: 1 − e^{−1/8}     = 0.1175
        τ = 1: m = 2, A = 1, B = 2, h = 1: B at distance 0:    1 − 1            = 0
        τ = 2: m = 3, A = 2, B = 2, h = 0 (floored to 1e-12): distance 1:  1 − 0 = 1
        τ = 3: m = 4, A = 3, B = 2, h = 1: nearest at 1:       1 − e^{−1/2}     = 0.3935
        τ = 4: past both episodes, which keep their last means (τ = 3): nearest at 2:
                                                               1 − e^{−2}       = 0.8647

    `similarity: mean` averages the kernel instead: at τ = 3, 1 − (e^{−1/2} + e^{−2})/2 =
    0.6291; at τ = 0 both kernels are e^{−1/8}, as with max.
    """
    expected = [1 - math.exp(-1 / 8), 0.0, 1.0, 1 - math.exp(-1 / 2), 1 - math.exp(-2)]
    detector = DETECTORS.get("deedee")().fit(FIT)
    np.testing.assert_allclose(detector.score(SCORED).scores, expected, rtol=1e-9, atol=1e-12)
    mean = DETECTORS.get("deedee")(similarity="mean").fit(FIT).score(SCORED).scores
    assert mean[0] == pytest.approx(expected[0], rel=1e-9)
    assert mean[3] == pytest.approx(1 - (math.exp(-1 / 2) + math.exp(-2)) / 2, rel=1e-9)


def test_median_bandwidths_per_episode_step():
    detector = DETECTORS.get("deedee")().fit(FIT)
    s = math.sqrt(2.75)
    np.testing.assert_allclose(detector.bandwidths_, [2 / s, 1 / s, 1e-12, 1 / s], rtol=1e-7)


def test_a_fixed_bandwidth_in_standardised_units():
    detector = DETECTORS.get("deedee")(bandwidth=1.0).fit(FIT)
    # τ = 0: distance 1/s to both, s² = 2.75: 1 − exp(−(1/2.75)/2).
    assert detector.score(SCORED).scores[0] == pytest.approx(1 - math.exp(-1 / 5.5), rel=1e-9)


def test_the_running_mean_restarts_with_each_episode():
    detector = DETECTORS.get("deedee")().fit(FIT)
    twice = detector.score(stream([1, 3, 5, 1, 3], dones=[2])).scores
    once = detector.score(SCORED).scores
    np.testing.assert_array_equal(twice[:3], once[:3])
    np.testing.assert_array_equal(twice[3:], once[:2])


def test_episode_steps_and_running_means():
    dones = np.array([0, 0, 1, 0, 1, 1, 0], dtype=bool)
    steps = episode_steps(dones)
    assert steps.tolist() == [0, 1, 2, 0, 1, 0, 0]
    x = np.arange(7.0)[:, None]
    assert running_means(x, steps)[:, 0].tolist() == [0, 0.5, 1, 3, 3.5, 5, 6]


@pytest.mark.parametrize(
    "params",
    [{"similarity": "mean"}, {"bandwidth": 0.5, "features": "state_action"}],
    ids=["mean", "fixed_bandwidth"],
)
def test_other_parameters_stream_exactly(params):
    data = linear_system_trajectories(8, T=100, action_dim=2, seed=3)
    detector = DETECTORS.get("deedee")(**params).fit(data[:6])
    check_streaming(detector.calibrate(data[6:7]), data[6:])
