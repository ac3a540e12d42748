"""cusum: the closed form against the recursion, and the detector's residuals and resets."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from oodrl.detectors.cusum import Cusum, cusum
from oodrl.errors import ConfigError
from oodrl.testing import linear_system_trajectories


def recursion(drift, restarts):
    g, out = 0.0, []
    for value, restart in zip(drift, restarts, strict=True):
        g = max(0.0, (0.0 if restart else g) + value)
        out.append(g)
    return np.array(out)


def test_by_hand():
    drift = np.array([1.0, -3.0, 2.0, 2.0, -1.0])
    no_restart = np.array([True, False, False, False, False])
    np.testing.assert_array_equal(cusum(drift, no_restart), [1, 0, 2, 4, 3])
    restart_at_3 = np.array([True, False, False, True, False])
    np.testing.assert_array_equal(cusum(drift, restart_at_3), [1, 0, 2, 2, 1])


@given(
    arrays(np.float64, st.integers(1, 60), elements=st.floats(-10, 10)),
    st.lists(st.integers(0, 59), max_size=5),
)
def test_closed_form_equals_recursion(drift, restart_steps):
    restarts = np.zeros(len(drift), dtype=bool)
    restarts[0] = True
    restarts[[s for s in restart_steps if s < len(drift)]] = True
    np.testing.assert_allclose(cusum(drift, restarts), recursion(drift, restarts), atol=1e-9)


def test_detector_applies_the_recursion_to_its_residual():
    fit = linear_system_trajectories(4, seed=0)
    trajectory = linear_system_trajectories(5, seed=0)[4]
    assert trajectory.dones.any()
    for reset_on_done in (False, True):
        detector = Cusum(slack=0.3, reset_on_done=reset_on_done).fit(fit)
        e = detector._residuals([trajectory])
        drift = e - detector.residual_mean_ - detector.slack_
        restarts = np.zeros(trajectory.T, dtype=bool)
        restarts[0] = True
        if reset_on_done:
            restarts[1:] = trajectory.dones[:-1]
        np.testing.assert_allclose(
            detector.score(trajectory).scores, recursion(drift, restarts), atol=1e-9
        )


def test_residual_is_about_one_in_distribution_and_the_slack_is_in_its_sd():
    fit = linear_system_trajectories(6, seed=0)
    detector = Cusum(slack=2.0).fit(fit)
    e = detector._residuals(fit)
    assert abs(detector.residual_mean_ - 1.0) < 1e-6
    assert detector.slack_ == 2.0 * e.std()


def test_state_residual_is_the_mean_squared_standardised_state():
    fit = linear_system_trajectories(6, seed=0)
    trajectory = linear_system_trajectories(7, seed=0)[6]
    detector = Cusum(residual="state", slack=0.3).fit(fit)
    states = np.concatenate([t.states for t in fit]).astype(np.float64)
    z = (trajectory.states - states.mean(axis=0)) / states.std(axis=0)
    e = detector._residuals([trajectory])
    np.testing.assert_allclose(e, (z**2).mean(axis=1), rtol=1e-12)
    assert abs(detector.residual_mean_ - 1.0) < 1e-9
    drift = e - detector.residual_mean_ - detector.slack_
    restarts = np.r_[True, np.zeros(trajectory.T - 1, bool)]
    np.testing.assert_allclose(
        detector.score(trajectory).scores, recursion(drift, restarts), atol=1e-9
    )


def test_the_residual_decides_what_accumulates():
    # Every observed increment doubled, the states themselves left as they were: a dynamics
    # fault without displaced states. The transition residual accumulates it into alarms at
    # every step; the state distance, which never reads s_{t+1}, cannot see it.
    fit = linear_system_trajectories(6, seed=0)
    clean = linear_system_trajectories(7, seed=0)[6]
    faster = type(clean)(
        states=clean.states,
        actions=clean.actions,
        rewards=clean.rewards,
        next_states=clean.states + 2.0 * (clean.next_states - clean.states),
        dones=clean.dones,
        info=clean.info,
    )
    for residual, responds in (("transition", True), ("state", False)):
        detector = Cusum(residual=residual).fit(fit).calibrate(fit)
        alarms = detector.score(faster).alarms.mean() - detector.score(clean).alarms.mean()
        assert bool(alarms > 0.5) is responds, (residual, alarms)


def test_residual_is_validated():
    with pytest.raises(ConfigError, match="'residual' parameter of Cusum must be one of"):
        Cusum(residual="reward").fit(linear_system_trajectories(2, seed=0))
