"""BaseDetector's parameter declaration and its one name."""

from __future__ import annotations

import numpy as np
import pytest

from oodrl.core.detector import BaseDetector, detector_parameters, episode_max_threshold
from oodrl.errors import ConfigError
from oodrl.validation import Interval


class Unnamed(BaseDetector):
    def _fit(self, trajectories):
        pass

    def _score(self, trajectory):
        return np.zeros(trajectory.T)


class Named(Unnamed):
    name = "named"


class SubclassOfNamed(Named):
    pass


@detector_parameters
class Declared(Unnamed):
    _parameter_constraints = {"width": [Interval(int, 1, None)]}

    width: int = 3
    threshold_rule: str = "max"


class PluginStyle(Unnamed):
    """A plugin that writes its own `__init__`, as docs/how-to/add-detector.md shows."""

    _parameter_constraints = {"width": [Interval(int, 1, None)]}

    def __init__(self, *, width: int = 3, **base) -> None:
        super().__init__(**base)
        self.width = width


def test_a_class_without_a_name_is_named_after_itself():
    assert (Unnamed.name, Named.name, SubclassOfNamed.name) == (
        "Unnamed",
        "named",
        "SubclassOfNamed",
    )
    assert Named().name == "named"


@pytest.mark.parametrize("cls", [Declared, PluginStyle], ids=["fields", "own_init"])
def test_parameters_are_keyword_arguments_stored_under_their_names(cls):
    detector = cls(width=5, seed=2)
    expected_rule = "max" if cls is Declared else "percentile"
    assert detector.get_params() == {
        "width": 5,
        "threshold_rule": expected_rule,
        "threshold_percentile": 99.0,
        "alpha": 0.05,
        "seed": 2,
    }
    assert cls.from_params(detector.get_params()).get_params() == detector.get_params()
    with pytest.raises(TypeError):
        cls(5)  # keyword-only, as in scikit-learn
    with pytest.raises(ConfigError, match="has no parameter 'depth'.*width"):
        cls.from_params({"depth": 1})
    with pytest.raises(ConfigError, match=f"'width' parameter of {cls.__name__} must be"):
        cls.from_params({"width": 0})


def test_detectors_compare_by_identity_and_hash():
    # Two equal-parameter detectors may be fitted on different data: not interchangeable.
    one, two = Declared(), Declared()
    assert one != two and len({one, two}) == 2


def test_repr_lists_the_parameters():
    assert repr(Declared(width=4)) == (
        "Declared(threshold_rule='max', threshold_percentile=99.0, alpha=0.05, seed=0, width=4)"
    )


def test_episode_max_is_the_conformal_rank_of_the_trajectory_maxima():
    maxima = np.random.default_rng(0).permutation(np.arange(1.0, 20.0))
    # n = 19, alpha = 0.1: the ceil(20 * 0.9) = 18th smallest, and alarms only above it.
    threshold = episode_max_threshold(maxima, 0.1)
    assert threshold == np.nextafter(18.0, np.inf)
    assert episode_max_threshold(maxima, 0.05) == np.nextafter(19.0, np.inf)
    with pytest.raises(ConfigError, match="at least 19 held-out trajectories; got 18"):
        episode_max_threshold(maxima[:18], 0.05)


def test_episode_max_bounds_the_clean_false_alarm_probability():
    # Exchangeable clean trajectories: a new one's maximum exceeds the threshold with
    # probability at most alpha (exactly 1 - 18/20 = 0.1 here, for continuous maxima).
    rng = np.random.default_rng(1)
    calibration = rng.standard_normal((4000, 19, 50)).max(axis=2)
    new = rng.standard_normal((4000, 50)).max(axis=1)
    thresholds = np.array([episode_max_threshold(m, 0.1) for m in calibration])
    assert abs((new >= thresholds).mean() - 0.1) < 0.015


def test_calibrate_by_episode_max_reads_each_trajectory_maximum():
    detector = _StateSum(threshold_rule="episode_max", alpha=0.5)
    trajectories = [_constant_trajectory(value) for value in (3.0, 1.0, 2.0)]
    detector.fit(trajectories).calibrate(trajectories)
    # n = 3, alpha = 0.5: the ceil(4 * 0.5) = 2nd smallest maximum.
    assert detector.threshold_ == np.nextafter(2.0, np.inf)


class _StateSum(Unnamed):
    def _score(self, trajectory):
        return trajectory.states.sum(axis=1).astype(np.float64)


def _constant_trajectory(value: float):
    from oodrl.core.trajectory import Trajectory

    states = np.full((4, 1), value, dtype=np.float32)
    states[0] = 0.0
    return Trajectory(states, np.zeros(4, int), np.zeros(4), states, np.zeros(4, bool))
