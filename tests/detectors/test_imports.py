"""Torch loads only when a neural detector fits (each DVC stage is a fresh process).

Scoring runs the fitted networks in numpy, so the ~30 scoring stages of the neural detectors
never pay torch's import time (~1.5 s each).
"""

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


#: Small neural detectors so that fitting takes a fraction of a second.
SMALL = {"hidden_sizes": [8], "epochs": 1, "device": "cpu"}
NEURAL = [n for n in NAMES if DETECTORS.get(n).uses_torch]


def small(name: str):
    return DETECTORS.get(name)(**(SMALL if name in NEURAL else {}))


@pytest.mark.parametrize("name", NEURAL, ids=NEURAL)
def test_fitting_a_neural_detector_imports_torch(name):
    # `uses_torch` tells the truth: the fitting stage pays for torch, and only it.
    code = (
        "import pickle, sys; detector = pickle.load(sys.stdin.buffer); "
        "assert 'torch' not in sys.modules; "
        "from oodrl.testing import linear_system_trajectories; "
        "detector.fit(linear_system_trajectories(2, T=40)); "
        "sys.exit('torch' not in sys.modules)"
    )
    result = run_fresh(code, pickle.dumps(small(name)))
    assert result.returncode == 0, f"fitting {name} did not import torch. {result.stderr.decode()}"


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_loading_and_scoring_a_fitted_detector_does_not_import_torch(name):
    data = linear_system_trajectories(3, T=40)
    detector = small(name).fit(data[:2])
    code = (
        "import pickle, sys; detector, trajectory = pickle.load(sys.stdin.buffer); "
        "assert detector.score(trajectory).scores.shape == (trajectory.T,); "
        "sys.exit('torch' in sys.modules)"
    )
    result = run_fresh(code, pickle.dumps((detector, data[2])))
    assert result.returncode == 0, f"scoring {name} imported torch. {result.stderr.decode()}"
