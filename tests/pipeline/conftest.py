"""A tiny pipeline (2 detectors × 2 injectors, T=60) built once per session in a throw-away
git + DVC repository; each test works on its own copy (DVC cache included)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from oodrl.io.layout import detector_stage
from oodrl.testing.pipeline import TINY_TIERS, copy_project, repro

DETECTORS = ["mahalanobis_distance", "kde_density"]
INJECTORS = ["observation_delay", "stuck_actuator"]
POLICY_FILES = ("models/policy.pt", "models/policy.json")


def detector_stages(detector: str) -> list[str]:
    """Every stage of one detector's DVC file, as `dvc repro` names them."""
    return [
        detector_stage(detector, "fit"),
        detector_stage(detector, "score_clean"),
        *injector_scoring([detector], *INJECTORS),
    ]


def injector_scoring(detectors: list[str], *injectors: str) -> list[str]:
    """The scoring stages (headline, sweep and tier sets) of `detectors` on `injectors`."""
    return [detector_stage(d, "score", i) for d in detectors for i in injectors]


def injector_stages(injector: str) -> list[str]:
    """The stages of the environment's dvc.yaml that one injector's knob re-runs."""
    return [f"{stage}@{injector}" for stage in ("collect_ood", "collect_sweep", "collect_tiers",
                                                 "impact")]  # fmt: skip


def tiny_params(default: dict) -> dict:
    params = json.loads(json.dumps(default))
    params["env"]["T"] = 60
    params["data"].update(n_id=4, n_ood=3)
    params["anomaly"]["sweep"] = [0.2, 0.6]
    params["benchmark"] = {"detectors": DETECTORS, "injectors": INJECTORS}
    params["metrics"]["n_boot"] = 20
    params["metrics"]["traces_per_anomaly"] = 1
    params["tiers"].update(TINY_TIERS)
    params["executor"]["workers"] = 1
    return params


# Imported by every Python process of the build (PYTHONPATH): records the files of the
# modules it loaded, so test_deps can compare what each stage command imported with its deps.
IMPORT_TRACE = """
import atexit, json, os, sys


def _record():
    files = sorted({getattr(m, "__file__", None) or "" for m in list(sys.modules.values())})
    path = os.path.join(os.environ["OODRL_IMPORT_TRACE"], f"{os.getpid()}.json")
    with open(path, "w") as out:
        json.dump({"argv": sys.argv, "files": [f for f in files if f.endswith(".py")]}, out)


atexit.register(_record)
"""


def python_path(first: Path) -> str:
    """PYTHONPATH with `first` ahead of what the environment already has."""
    return os.pathsep.join(p for p in (str(first), os.environ.get("PYTHONPATH", "")) if p)


@pytest.fixture(scope="session")
def built_repo(tmp_path_factory, repo_root, _default_params) -> Path:
    """The tiny pipeline, built once; `<it>/../import-trace` holds each process's imports."""
    if not (repo_root / "models" / "policy.pt").is_file():
        pytest.skip("models/policy.pt is not committed yet")
    base = tmp_path_factory.mktemp("built")
    trace = base / "import-trace"
    trace.mkdir()
    (trace / "sitecustomize.py").write_text(IMPORT_TRACE)
    repo = copy_project(repo_root, base / "repo", tiny_params(_default_params))
    policy = {name: (repo / name).read_bytes() for name in POLICY_FILES}
    # Cold stage processes: a warm one (oodrl.warm) holds the modules its server preloaded
    # too.
    trace_env = {"PYTHONPATH": python_path(trace), "OODRL_IMPORT_TRACE": str(trace)}
    repro(repo, env={**trace_env, "OODRL_WARM": "0"})
    # train_policy may run (its deps changed since dvc.lock was written) but never retrains.
    assert {name: (repo / name).read_bytes() for name in POLICY_FILES} == policy
    return repo


@pytest.fixture
def repo(built_repo, tmp_path) -> Path:
    copy = tmp_path / "repo"
    shutil.copytree(built_repo, copy, symlinks=True)
    return copy


@pytest.fixture
def plugin_env(repo) -> dict[str, str]:
    """Makes a detector module written in the test (`oodrl_test_plugin`) importable by stages."""
    (repo / "oodrl_test_plugin.py").write_text(PLUGIN_SOURCE)
    return {"PYTHONPATH": python_path(repo)}


PLUGIN_SOURCE = '''
"""Detectors defined by the test suite, reached through a `module:Class` path in params."""

import numpy as np

from oodrl.core import BaseDetector
from oodrl.validation import Interval


class SpeedDetector(BaseDetector):
    """Absolute deviation of the lander's speed from its ID mean, in ID standard deviations."""

    def _fit(self, trajectories):
        speed = np.concatenate([np.hypot(t.states[:, 2], t.states[:, 3]) for t in trajectories])
        self.mean_, self.std_ = float(speed.mean()), float(speed.std()) + 1e-9

    def _score(self, trajectory):
        speed = np.hypot(trajectory.states[:, 2], trajectory.states[:, 3])
        return np.abs(speed - self.mean_) / self.std_


class ExplodingDetector(SpeedDetector):
    """Raises while scoring the trajectory whose seed is `explode_on_seed`."""

    _parameter_constraints = {"explode_on_seed": [Interval(int, 0, None)]}

    def __init__(self, *, explode_on_seed=0, **base):
        super().__init__(**base)
        self.explode_on_seed = explode_on_seed

    def _score(self, trajectory):
        if trajectory.info.get("seed") == self.explode_on_seed:
            raise ValueError("boom")
        return super()._score(trajectory)
'''
