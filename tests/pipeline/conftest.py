"""The tiny pipeline (tests/tiny_pipeline.py: 2 detectors × 2 injectors, T=60), built once per
session (`built_repo`, tests/conftest.py); each test works on its own copy (DVC cache included)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from tiny_pipeline import DETECTORS, INJECTORS, POLICY_FILES, python_path, tiny_params

from oodrl.io.layout import detector_stage

# The tests here import these from conftest.
__all__ = ["DETECTORS", "INJECTORS", "POLICY_FILES", "python_path", "tiny_params"]


def detector_stages(detector: str) -> list[str]:
    """Every stage of one detector's DVC file, as `dvc repro` names them."""
    return [detector_stage(detector, "fit"), detector_stage(detector, "score_clean"),
            *fault_scoring([detector])]  # fmt: skip


def fault_scoring(detectors: list[str]) -> list[str]:
    """What an injector's knob re-runs of each of `detectors`: its scoring of every injector's
    headline set and of their sweeps and tier streams, and its cells."""
    return [detector_stage(d, stage) for d in detectors
            for stage in ("score", "score_variants", "cells")]  # fmt: skip


def injector_stages(injector: str) -> list[str]:
    """The stages of the environment's dvc.yaml that one injector's knob re-runs."""
    return [f"{stage}@{injector}" for stage in ("collect_ood", "collect_sweep", "collect_tiers",
                                                 "impact")]  # fmt: skip


def _immutable(relative: Path) -> bool:
    """Files no test here writes and nothing rewrites in place, linked rather than copied:
    git's objects (a new object is a new file), and the environment pipelines' reports, models
    and locks (only their own `dvc repro` writes those; `oodrl pipeline write` rewrites their
    dvc.yaml files, which are copied). 2,400 of the 3,600 files and 209 of the 217 MB: a copy
    takes seconds instead of 12 s on a loaded machine, for some thirty copies a run."""
    parts = relative.parts
    return parts[:2] == (".git", "objects") or (
        parts[0] == "pipeline" and ({"reports", "models"} & set(parts) or parts[-1] == "dvc.lock")
    )


@pytest.fixture
def repo(built_repo, tmp_path) -> Path:
    def copy_file(source: str, target: str) -> None:
        if _immutable(Path(source).relative_to(built_repo)):
            os.link(source, target)
        else:
            shutil.copy2(source, target)

    copy = tmp_path / "repo"
    shutil.copytree(built_repo, copy, symlinks=True, copy_function=copy_file)
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
