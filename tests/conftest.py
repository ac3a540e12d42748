"""Shared fixtures: the repository root, the default params as a dict, small clean sets."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def _default_params() -> dict:
    return yaml.safe_load((REPO_ROOT / "params.yaml").read_text())


@pytest.fixture
def default_params(_default_params) -> dict:
    """A fresh deep copy of params.yaml that a test may edit."""
    return copy.deepcopy(_default_params)


@pytest.fixture(scope="session")
def heuristic_clean():
    """Eight clean LunarLander streams of T=300 from gymnasium's heuristic controller."""
    from rollout_policies import HeuristicPolicy

    from oodrl.envs.collect import collect
    from oodrl.envs.lunar_lander import LunarLanderAdapter

    return collect(LunarLanderAdapter(), HeuristicPolicy(), range(100, 108), 300)
