"""Torch loads only when a neural detector fits or scores (each DVC stage is a fresh process)."""

from __future__ import annotations

import pickle
import subprocess
import sys

import pytest

from oodrl.detectors import DETECTORS
from oodrl.testing import linear_system_trajectories

NAMES = DETECTORS.names()


def run_fresh(code: str, stdin: bytes = b"") -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], input=stdin, capture_output=True)


def test_building_every_detector_imports_neither_torch_nor_scipy():
    # What every stage does when it validates params.yaml.
    code = (
        "import sys; from oodrl.detectors import DETECTORS; "
        "[DETECTORS.get(n).from_params({}) for n in DETECTORS.names()]; "
        "assert 'torch' not in sys.modules; assert 'scipy' not in sys.modules"
    )
    result = run_fresh(code)
    assert result.returncode == 0, result.stderr.decode()


@pytest.mark.parametrize("name", [n for n in NAMES if DETECTORS.get(n).uses_torch])
def test_loading_a_fitted_neural_detector_does_not_import_torch(name):
    small = {"hidden_sizes": [8], "epochs": 1, "device": "cpu"}
    detector = DETECTORS.get(name)(**small).fit(linear_system_trajectories(2, T=40))
    code = "import pickle, sys; pickle.load(sys.stdin.buffer); sys.exit('torch' in sys.modules)"
    result = run_fresh(code, pickle.dumps(detector))
    assert result.returncode == 0, f"unpickling {name} imported torch. {result.stderr.decode()}"
