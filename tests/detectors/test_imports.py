"""No built-in detector imports torch (each DVC stage is a fresh process; torch costs ~1.5 s).

The neural detectors train and score their networks in numpy (`oodrl.detectors.mlp`). Those that
read the agent's policy (`uses_torch`) import torch to read its checkpoint when they fit, and
score without it.
"""

from __future__ import annotations

import pickle
import subprocess
import sys

import pytest
from test_contract import POLICIES

from oodrl.detectors import DETECTORS
from oodrl.detectors.neural import NeuralDetector
from oodrl.testing import linear_system_trajectories
from oodrl.validation import constructor_params

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
SMALL = {"hidden_sizes": [8], "epochs": 1}
NEURAL = [n for n in NAMES if issubclass(DETECTORS.get(n), NeuralDetector)]
#: Those whose fitting does not read a policy checkpoint.
TORCH_FREE_FIT = [n for n in NEURAL if not DETECTORS.get(n).uses_torch]


def small(name: str):
    params = dict(SMALL if name in NEURAL else {})
    if "policy" in constructor_params(DETECTORS.get(name)):
        params["policy"] = POLICIES["discrete"]  # the policy of the data
    return DETECTORS.get(name)(**params)


def test_the_neural_detectors_are_found():
    assert set(TORCH_FREE_FIT) >= {"pedm", "autoencoder", "ensemble_disagreement"}


@pytest.mark.parametrize("name", TORCH_FREE_FIT, ids=TORCH_FREE_FIT)
def test_fitting_a_neural_detector_does_not_import_torch(name):
    code = (
        "import pickle, sys; detector = pickle.load(sys.stdin.buffer); "
        "from oodrl.testing import linear_system_trajectories; "
        "detector.fit(linear_system_trajectories(2, T=40)); "
        "sys.exit('torch' in sys.modules)"
    )
    result = run_fresh(code, pickle.dumps(small(name)))
    assert result.returncode == 0, f"fitting {name} imported torch. {result.stderr.decode()}"


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
