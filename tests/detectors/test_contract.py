"""Every registered detector passes the oodrl.testing contract checks (ids = detector name)."""

from __future__ import annotations

import copy
import subprocess
import sys
from functools import cache

import pytest

from oodrl.core.detector import BaseDetector
from oodrl.detectors import DETECTORS
from oodrl.errors import ConfigError
from oodrl.testing import (
    check_detector,
    check_global_random_state,
    check_not_fitted,
    check_parameters,
    check_pickle_roundtrip,
    check_reproducible,
    check_score_is_pure,
    check_scores,
    check_state_dim,
    check_threshold,
    check_torch_free_import,
    linear_system_trajectories,
)

NAMES = DETECTORS.names()

#: Small models and reference sets so the whole file runs in seconds.
SMALL: dict[str, dict] = {
    "pedm": {"n_members": 2, "n_samples": 3, "hidden_sizes": [16, 16], "epochs": 2},
    "autoencoder": {"hidden_sizes": [16], "latent_dim": 2, "epochs": 2},
    "ensemble_disagreement": {"n_members": 2, "hidden_sizes": [16, 16], "epochs": 2},
    "kde_density": {"max_reference": 200},
    "lyapunov_divergence": {"max_reference": 300},
    "time_series_features": {"window": 16},
}

DATA = linear_system_trajectories(10, T=120, episode_length=80, seed=0)
FIT, CALIBRATION, EVALUATION = DATA[:6], DATA[6:8], DATA[8:]


def make(name: str) -> BaseDetector:
    return DETECTORS.get(name)(**SMALL.get(name, {}))


@cache
def _fitted(name: str) -> BaseDetector:
    return make(name).fit(FIT)


@pytest.fixture
def fitted(request) -> BaseDetector:
    """A fitted detector of the test's name; a copy, so a test may calibrate it."""
    return copy.deepcopy(_fitted(request.param))


def by_name(test):
    return pytest.mark.parametrize("fitted", NAMES, ids=NAMES, indirect=True)(test)


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_registered_name_is_the_class_name(name):
    assert DETECTORS.get(name).name == name


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_parameters(name):
    check_parameters(make(name))
    check_parameters(DETECTORS.get(name)())


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_invalid_threshold_rule_is_a_config_error_at_fit(name):
    detector = DETECTORS.get(name)(threshold_rule="median")
    with pytest.raises(ConfigError, match="'threshold_rule' parameter of"):
        detector.fit(FIT)


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_building_does_not_import_torch(name):
    check_torch_free_import(make(name))


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_not_fitted(name):
    check_not_fitted(make(name), EVALUATION[0])


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_reproducible(name):
    check_reproducible(lambda: make(name), FIT, EVALUATION)


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_global_random_state_untouched(name):
    check_global_random_state(lambda: make(name), FIT, EVALUATION)


@by_name
def test_scores(fitted):
    check_scores(fitted, EVALUATION)


@by_name
def test_score_is_pure(fitted):
    check_score_is_pure(fitted, EVALUATION)


@by_name
def test_wrong_state_dim(fitted):
    check_state_dim(fitted, EVALUATION[0])


@by_name
def test_threshold(fitted):
    check_threshold(fitted, CALIBRATION)


@by_name
def test_pickle_roundtrip(fitted):
    check_pickle_roundtrip(fitted, EVALUATION)


def test_check_detector_runs_every_check():
    check_detector(lambda: make("mahalanobis_distance"), FIT, CALIBRATION, EVALUATION)


def test_package_import_is_light():
    code = (
        "import sys, oodrl.detectors; "
        "heavy = [m for m in ('torch', 'numpy', 'scipy', 'sklearn') if m in sys.modules]; "
        "sys.exit(str(heavy) if heavy else 0)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_pedm_threshold_defaults_to_max():
    assert DETECTORS.get("pedm")().threshold_rule == "max"
