"""BaseDetector's parameter declaration and its one name."""

from __future__ import annotations

import numpy as np
import pytest

from oodrl.core.detector import BaseDetector, detector_parameters
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
    """A plugin that writes its own `__init__`, as the README shows."""

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
        "Declared(threshold_rule='max', threshold_percentile=99.0, seed=0, width=4)"
    )
