"""Every registered detector passes the oodrl.testing contract checks (ids = detector name),
on discrete-action and on continuous-action data."""

from __future__ import annotations

import copy
import subprocess
import sys
import tempfile
from functools import cache
from pathlib import Path

import numpy as np
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
    check_scores_use_the_data,
    check_state_dim,
    check_threshold,
    check_torch_free_import,
    linear_system_policy,
    linear_system_trajectories,
)
from oodrl.validation import constructor_params

NAMES = DETECTORS.names()

#: Small models and reference sets so the whole file runs in seconds.
SMALL: dict[str, dict] = {
    "pedm": {"n_members": 2, "n_samples": 3, "hidden_sizes": [16, 16], "epochs": 2},
    "autoencoder": {"hidden_sizes": [16], "latent_dim": 2, "epochs": 2},
    "ensemble_disagreement": {"n_members": 2, "hidden_sizes": [16, 16], "epochs": 2},
    "kde_density": {"max_reference": 200},
    "lyapunov_divergence": {"max_reference": 300},
    "time_series_features": {"window": 16},
    "riqn": {"hidden_size": 8, "n_cos": 4, "n_quantiles": 2, "epochs": 1, "chunk_length": 40},
    "fqe_td": {"n_members": 2, "hidden_sizes": [16], "iterations": 3},
}

DATA = linear_system_trajectories(10, T=120, episode_length=80, seed=0)
FIT, CALIBRATION, EVALUATION = DATA[:6], DATA[6:8], DATA[8:]

#: (fit, calibration, evaluation) trajectories by action kind.
SPLITS = {
    "discrete": (FIT, CALIBRATION, EVALUATION),
    "continuous": (lambda d: (d[:6], d[6:8], d[8:]))(
        linear_system_trajectories(10, T=120, action_dim=2, seed=0)
    ),
}
ACTIONS = list(SPLITS)

#: The policy that made each kind's data (`linear_system_policy`), for detectors that read the
#: agent's policy (a `policy` parameter): files of this module's lifetime.
_POLICY_DIR = tempfile.TemporaryDirectory(prefix="oodrl-contract-policies-")
POLICIES = {
    actions: str(linear_system_policy(Path(_POLICY_DIR.name) / f"{actions}.pt", **kind))
    for actions, kind in {"discrete": {}, "continuous": {"action_dim": 2}}.items()
}


@cache
def refusal(name: str, actions: str) -> str | None:
    """Why a detector refuses the policy of one action kind's data (None: it reads it)."""
    support = getattr(DETECTORS.get(name), "policy_support", None)
    if support is None:
        return None
    from oodrl.policies.load import load_policy

    return support(load_policy(POLICIES[actions]))


def make(name: str, actions: str = "discrete") -> BaseDetector:
    """A small detector for one action kind's data; a test skips where the detector refuses it."""
    reason = refusal(name, actions)
    if reason is not None:
        pytest.skip(f"{name} refuses the {actions} data's policy: {reason}")
    params = dict(SMALL.get(name, {}))
    if "policy" in constructor_params(DETECTORS.get(name)):
        params["policy"] = POLICIES[actions]
    return DETECTORS.get(name)(**params)


@cache
def _fitted(name: str, actions: str) -> BaseDetector:
    return make(name, actions).fit(SPLITS[actions][0])


def by_name_and_actions(test):
    """Run `test(name, actions)` for every registered detector and both action kinds."""
    test = pytest.mark.parametrize("actions", ACTIONS, ids=ACTIONS)(test)
    return pytest.mark.parametrize("name", NAMES, ids=NAMES)(test)


def fitted(name: str, actions: str) -> BaseDetector:
    """A fitted detector; a copy, so a test may calibrate it."""
    return copy.deepcopy(_fitted(name, actions))


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


@pytest.mark.parametrize(
    "check",
    [check_reproducible, check_global_random_state, check_scores_use_the_data],
    ids=lambda check: check.__name__,
)
@by_name_and_actions
def test_fresh_fits(name, actions, check):
    fit, _, evaluation = SPLITS[actions]
    check(lambda: make(name, actions), fit, evaluation)


@pytest.mark.parametrize(
    "check", [check_score_is_pure, check_pickle_roundtrip], ids=lambda check: check.__name__
)
@by_name_and_actions
def test_fitted(name, actions, check):
    check(fitted(name, actions), SPLITS[actions][2])


@by_name_and_actions
def test_wrong_state_dim(name, actions):
    check_state_dim(fitted(name, actions), SPLITS[actions][2][0])


@by_name_and_actions
def test_threshold(name, actions):
    check_threshold(fitted(name, actions), SPLITS[actions][1])


@pytest.mark.parametrize("actions", ACTIONS, ids=ACTIONS)
def test_check_detector_runs_every_check(actions):
    check_detector(lambda: make("mahalanobis_distance"), *SPLITS[actions])


def test_continuous_data_has_float32_action_vectors_that_move_the_system():
    discrete, continuous = SPLITS["discrete"][0], SPLITS["continuous"][0]
    assert all(t.actions.shape == (t.T,) and t.actions.dtype == np.int64 for t in discrete)
    assert all(t.actions.shape == (t.T, 2) and t.actions.dtype == np.float32 for t in continuous)
    actions = np.concatenate([t.actions for t in continuous])
    assert np.abs(actions).max() <= 1 and actions.std(axis=0).min() > 0.1
    # The actions move the system: s' depends on a beyond A s (a least-squares fit on (s, a)
    # explains the increments better than one on s alone).
    s = np.concatenate([t.states for t in continuous]).astype(np.float64)
    nxt = np.concatenate([t.next_states for t in continuous]).astype(np.float64)
    keep = ~np.concatenate([t.dones for t in continuous])
    s, a, nxt = s[keep], actions[keep].astype(np.float64), nxt[keep]
    residual_without = np.linalg.lstsq(s, nxt, rcond=None)[1].sum()
    residual_with = np.linalg.lstsq(np.hstack([s, a]), nxt, rcond=None)[1].sum()
    assert residual_with < 0.7 * residual_without


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


class _Constant(BaseDetector):
    """Scores every step alike: a broken detector the contract must reject."""

    def _fit(self, trajectories):
        pass

    def _score(self, trajectory):
        return np.ones(trajectory.T)


class _IgnoresFit(_Constant):
    """Scores the step's state norm whatever it was fitted on: also rejected."""

    def _score(self, trajectory):
        return np.linalg.norm(trajectory.states, axis=1)


@pytest.mark.parametrize(
    ("broken", "message"),
    [(_Constant, "ignore the steps"), (_IgnoresFit, "ignore the fit set")],
    ids=["constant", "ignores_fit"],
)
def test_scores_use_the_data_rejects_broken_detectors(broken, message):
    with pytest.raises(AssertionError, match=message):
        check_scores_use_the_data(broken, FIT, EVALUATION)
