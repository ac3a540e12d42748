"""Fitted neural detectors are the same bytes whatever SIMD kernels the libraries pick (SPEC §14).

Each case fits and scores every neural detector in a fresh interpreter under one kernel
selection (the variables are read when numpy loads, hence subprocesses) and reports digests of
the pickled weights and of the scores; all selections must agree with the default.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

#: Kernel selections: numpy's SIMD dispatch (exp, log, casts, reductions) without AVX-512 or
#: without AVX2 either, and OpenBLAS's matrix kernels for two CPU generations and two threads.
SELECTIONS: dict[str, dict[str, str]] = {
    "no-avx512": {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"},
    "no-avx2": {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"},
    "openblas-haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "openblas-skylakex": {"OPENBLAS_CORETYPE": "SkylakeX"},
    "openblas-2-threads": {"OPENBLAS_NUM_THREADS": "2"},
}

#: Fits and scores every neural detector, and one of the policy view, on tiny data; prints
#: {name: [learned state, scores]} digests (the view learns its temperature).
SCRIPT = """
import hashlib, json, pickle, tempfile
import numpy as np
from oodrl.detectors import DETECTORS
from oodrl.testing import linear_system_policy, linear_system_trajectories

policy = str(linear_system_policy(tempfile.mkdtemp() + "/policy.pt"))

SMALL = {
    "pedm": {"n_members": 3, "n_samples": 4, "hidden_sizes": [16, 16], "epochs": 2,
             "batch_size": 64},
    "autoencoder": {"hidden_sizes": [16], "latent_dim": 2, "epochs": 2, "batch_size": 64},
    "ensemble_disagreement": {"n_members": 3, "hidden_sizes": [16, 16], "epochs": 2,
                              "batch_size": 64},
    "fqe_td": {"policy": policy, "n_members": 3, "hidden_sizes": [16], "iterations": 3,
               "batch_size": 64},
    "q_entropy": {"policy": policy},
    "riqn": {"hidden_size": 8, "n_cos": 4, "n_quantiles": 2, "epochs": 2, "chunk_length": 40},
}
fit = linear_system_trajectories(3, T=120, seed=0)
scored = linear_system_trajectories(2, T=90, seed=1)
digests = {}
for name, params in SMALL.items():
    detector = DETECTORS.get(name)(**params).fit(fit)
    scores = np.concatenate([o.scores for o in detector.score_many(scored)])
    digests[name] = [
        hashlib.sha256(pickle.dumps(getattr(detector, "weights_", None)
                                    or detector.temperature_)).hexdigest(),
        hashlib.sha256(scores.tobytes()).hexdigest(),
    ]
print(json.dumps(digests))
"""


def digests(selection: dict[str, str]) -> dict[str, list[str]]:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", **selection}
    for variable in ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE"):
        if variable not in selection:
            env.pop(variable, None)
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


@pytest.fixture(scope="module")
def default_digests() -> dict[str, list[str]]:
    return digests({})


def cpu_flags() -> set[str]:
    """The CPU's feature flags (Linux); empty where /proc/cpuinfo is not there."""
    try:
        text = open("/proc/cpuinfo").read()  # noqa: SIM115 - a one-shot read
    except OSError:
        return set()
    return {flag for line in text.splitlines() if line.startswith("flags") for flag in
            line.split(":", 1)[1].split()}  # fmt: skip


#: Selections this CPU cannot execute: OpenBLAS's SkylakeX kernels are AVX-512 code, and forcing
#: them on a CPU without AVX-512 dies of an illegal instruction (SIGILL), not of a wrong result.
NEEDS = {"openblas-skylakex": "avx512f"}


@pytest.mark.parametrize("selection", list(SELECTIONS), ids=list(SELECTIONS))
def test_fits_and_scores_are_identical_under_every_kernel(selection, default_digests):
    needed = NEEDS.get(selection)
    if needed and needed not in cpu_flags():
        pytest.skip(f"{selection}: this CPU lacks {needed}, so its kernels cannot run here")
    neural = {"pedm", "autoencoder", "ensemble_disagreement", "fqe_td", "riqn"}
    assert set(default_digests) == {*neural, "q_entropy"}
    assert digests(SELECTIONS[selection]) == default_digests
