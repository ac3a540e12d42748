"""`ecod` (oodrl.detectors.ecod) against PyOD's ECOD scoring one row per call.

Tolerance: rtol 1e-9 (atol 1e-12 for scores near 0). The −log table holds `numerics.log`
values, rounded to 32 significant bits (a relative 2⁻³² ≈ 2.3e-10 per column) so that they are
the same on every machine; PyOD's own logs and linspace ECDF values round in the last bits.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
from pyod.models.ecod import ECOD as PyodECOD

from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.detectors.ecod import ECOD
from oodrl.testing import check_detector, check_streaming, linear_system_trajectories
from oodrl.testing.kernels import kernel_selections

RTOL, ATOL = 1e-9, 1e-12


def trajectory(states: np.ndarray) -> Trajectory:
    """A trajectory with these states (float32, as every trajectory holds them)."""
    states = np.asarray(states, dtype=np.float32)
    steps = len(states)
    return Trajectory(
        states=states,
        actions=np.zeros(steps, np.int64),
        rewards=np.zeros(steps, np.float32),
        next_states=states,
        dones=np.zeros(steps, bool),
    )


def pyod_one_row_at_a_time(fit: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """PyOD's ECOD fitted on `fit`, each row scored in a call of its own."""
    with warnings.catch_warnings():  # scipy warns of constant columns (skewness NaN → 0)
        warnings.simplefilter("ignore", RuntimeWarning)
        model = PyodECOD().fit(fit.astype(np.float32).astype(np.float64))
        rows = rows.astype(np.float32).astype(np.float64)
        return np.array([model.decision_function(row[None])[0] for row in rows])


def levels(rng, values: list[float], counts: list[int]) -> np.ndarray:
    """`counts[k]` copies of `values[k]`, shuffled: symmetric levels have zero skewness, and one
    value added can restore or break the symmetry."""
    return rng.permutation(np.repeat(values, counts))


def data_sets():
    rng = np.random.default_rng(0)
    n, m = 500, 250
    yield "gaussian_d5", rng.standard_normal((n, 5)), 1.5 * rng.standard_normal((m, 5))
    skewed = [rng.exponential(size=n), -rng.lognormal(size=n), rng.gamma(2, size=n)]
    wider = [rng.exponential(2, m), -rng.lognormal(0.5, 1, m), rng.gamma(2, 1.5, m)]
    yield "skewed_d3", np.column_stack(skewed), np.column_stack(wider)
    # Ties everywhere: binary and small-integer columns, a constant one, symmetric levels (rows
    # between them break the symmetry) and levels one −1 short of symmetric (a row at −1
    # restores it), values between the levels.
    n = 499
    ties = np.column_stack([rng.integers(0, 2, n), rng.integers(-2, 3, n), np.full(n, 0.5),
                            levels(rng, [-1, 0, 1], [166, 167, 166]),
                            levels(rng, [-3, -1, 1, 3], [125, 124, 125, 125])])  # fmt: skip
    rows = np.column_stack([rng.integers(0, 2, m), rng.integers(-3, 4, m) * 0.5,
                            rng.choice([0.0, 0.5, 1.0], m), rng.choice([-1, -0.5, 0, 0.5, 1], m),
                            rng.choice([-3.0, -2.0, -1.0, 0.0, 1.0, 3.0], m)])  # fmt: skip
    yield "ties_d5", ties, rows
    yield "one_column", rng.standard_t(3, (n, 1)), 3 * rng.standard_normal((m, 1))
    yield "one_fit_row", rng.standard_normal((1, 3)), rng.standard_normal((20, 3))


@pytest.mark.parametrize("name, fit, rows", list(data_sets()), ids=[c[0] for c in data_sets()])
def test_scores_agree_with_pyod_scoring_each_row_alone(name, fit, rows):
    detector = ECOD().fit([trajectory(fit)])
    ours = detector.score(trajectory(rows)).scores
    np.testing.assert_allclose(ours, pyod_one_row_at_a_time(fit, rows), rtol=RTOL, atol=ATOL)


def test_zero_skewness_is_decided_for_the_fit_rows_and_the_scored_row():
    """Balanced levels have zero skewness; a row between them breaks the symmetry (O = max of
    the tails), and a row on the level the fit set lacks one of restores it (O = their sum).
    Taking the fit set's skewness would get both wrong; PyOD and ecod agree on both."""
    rng = np.random.default_rng(1)
    symmetric = levels(rng, [-3, -1, 1, 3], [100, 100, 100, 100])
    short_of_a_minus_one = levels(rng, [-3, -1, 1, 3], [100, 99, 100, 100])
    cases = [(symmetric, 0.5, False), (symmetric, 0.0, True),
             (short_of_a_minus_one, -1.0, True), (short_of_a_minus_one, 1.0, False)]  # fmt: skip
    for fit, row, zero in cases:
        detector = ECOD().fit([trajectory(fit[:, None])])
        x = np.array([[row]])
        rows, _ = detector._zero_skewness(x, np.ones((1, 1), bool))
        assert rows.size == zero
        ours = detector.score(trajectory(x)).scores
        np.testing.assert_allclose(ours, pyod_one_row_at_a_time(fit[:, None], x), rtol=RTOL)


def test_matches_the_pyod_wrapper_on_raw_states():
    """The same score as the `pyod_ecod` wrapper (one PyOD call per row) on the state view
    unstandardised, with oodrl's own trajectories."""
    data = linear_system_trajectories(8, T=60, episode_length=40, seed=3)
    fit, evaluation = data[:6], data[6:]
    wrapper = DETECTORS.get("pyod.models.ecod:ECOD")(standardize=False).fit(fit)
    ours = ECOD().fit(fit)
    for trajectory_ in evaluation:
        np.testing.assert_allclose(
            ours.score(trajectory_).scores, wrapper.score(trajectory_).scores, rtol=RTOL
        )


@pytest.mark.parametrize("action_dim", [None, 2], ids=["discrete", "continuous"])
def test_the_detector_contract_and_exact_streaming(action_dim):
    data = linear_system_trajectories(10, T=80, episode_length=50, action_dim=action_dim, seed=0)
    check_detector(ECOD, data[:6], data[6:8], data[8:])
    check_streaming(ECOD().fit(data[:6]).calibrate(data[6:8]), data[8:])  # with alarms
    assert ECOD.machine_independent


#: Fits and scores tie-heavy and continuous data; prints the digest of the scores' bytes.
SCRIPT = """
import hashlib, numpy as np
from oodrl.detectors.ecod import ECOD
from oodrl.testing import linear_system_trajectories
data = linear_system_trajectories(6, T=100, seed=2)
rounded = [t.replace(states=np.round(t.states, 1)) for t in data]
scores = [ECOD().fit(d[:4]).score(d[4]).scores for d in (data, rounded)]
print(hashlib.sha256(np.concatenate(scores).tobytes()).hexdigest())
"""


def test_scores_are_the_same_bytes_under_every_kernel_selection():
    """numpy's log and reductions pick SIMD kernels per CPU; ecod's scores must not change."""
    digests = {}
    for name, selection in kernel_selections().items():
        env = {**os.environ, **selection}
        done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                              text=True, check=False)  # fmt: skip
        assert done.returncode == 0, done.stderr
        digests[name] = done.stdout.strip()
    assert len(set(digests.values())) == 1, digests
    assert len(next(iter(digests.values()))) == len(hashlib.sha256().hexdigest())
