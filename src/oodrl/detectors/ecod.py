"""`ecod`: PyOD's ECOD score (Li et al. 2022) of each step's state alone, exact, O(d log n) a step.

PyOD's `ECOD.decision_function(x)` for one row x after `fit(X)` (n rows) ranks x among the n + 1
rows (X, x), column by column: `column_ecdf`'s ECDF at a value is the fraction of the n + 1 rows
at or below it, ties included. For column j,

    U_l = −log((#{X_j ≤ x_j} + 1) / (n + 1)),   U_r = −log((#{X_j ≥ x_j} + 1) / (n + 1)),
    s = sign(scipy skew of the n + 1 values), NaN (a constant column) read as 0,
    U_skew = −sign(s − 1)·U_l + sign(s + 1)·U_r,   O_j = max(U_skew, U_l, U_r),

and the score is Σ_j O_j. Through the wrapper (`pyod_ecod`) a stream calls that one row at a
time, sorting n + 1 values per column per step. Here the fit columns are sorted once at fit, the
two counts are binary searches, and −log(k / (n + 1)), k = 1 … n + 1, is a table made at fit.

The skewness. U_skew is U_l when s = −1, U_r when s = +1 and U_l + U_r when s = 0; so
O_j = U_l + U_r where the n + 1 values have zero skewness and max(U_l, U_r) elsewhere. Only
whether the skewness is zero matters, never its sign; and only for min X_j < x_j < max X_j
(elsewhere U_l or U_r is 0 and both forms agree). It is not taken from the fit set: one added row
can make a symmetric column asymmetric (x_j between two values of a balanced three-valued column)
or the reverse. It is decided *exactly* for the n + 1 values, cheaply: with the fit column's exact
power sums (Python integers), their third central moment is a cubic in x_j whose coefficients are
known exactly; its float value with a rigorous error bound settles almost every row, and the
rows it leaves open are settled in integer arithmetic. PyOD's scipy moments are rounded floats:
where they misjudge an exact zero, PyOD's score differs from this one. scipy's near-constant rule
(a variance under (2⁻⁵²·mean)² gives NaN, so s = 0) is not reproduced: it can only hold for x_j
strictly inside the range of a column whose values are within a few ulps of each other.

The feature view is the raw state s_t, not standardised: ECOD depends on the data through ranks
and the zero-skewness test only, and an increasing affine map changes neither (the wrapper's
`pyod_ecod` standardises, which changes nothing but through rounding).

Machine independence (SPEC §14): counts, table look-ups, `max` and + are exact or rounded alike
on every machine; the table holds `numerics.log` values (certified, 32 significant bits); the d
columns are added in index order, one vector addition each. The scores are byte-identical on
every x86-64 machine and agree with PyOD's to the table's rounding, a relative 2⁻³² per column
(the tests ask rtol 1e-9).
"""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import split_scores, stacked

_TINY = np.finfo(np.float64).tiny


def _states(trajectory: Trajectory) -> np.ndarray:
    return trajectory.states.astype(np.float64)


def _keyed(values: np.ndarray) -> np.ndarray:
    """Rows (m, d) as complex keys j + i·value: numpy orders complex numbers by real part, then
    imaginary part, so one sorted array holds every column's sorted values and one binary search
    answers a row's d queries (a stream scores one row per call: d searches would be d calls)."""
    keys = np.empty(values.shape, np.complex128)
    keys.real, keys.imag = np.arange(values.shape[1]), values
    return keys


def _power_sums(column: np.ndarray) -> tuple[int, int, int, int]:
    """(K, S1, S2, S3): the column's values times K (a power of two making them all integers)
    and the sums of their first three powers, exactly."""
    ratios = [v.as_integer_ratio() for v in column.tolist()]
    scale = max(q for _, q in ratios)
    scaled = [p * (scale // q) for p, q in ratios]
    return (
        scale,
        sum(scaled),
        sum(v * v for v in scaled),
        sum(v * v * v for v in scaled),
    )


def _skewness_cubic(n: int, scale: int, s1: int, s2: int, s3: int) -> tuple[float, list[float]]:
    """(c, [p0, p1, p2, p3]): the third central moment of a fit column with a value x added
    (times n + 1) is p0 + p1·t + p2·t² + p3·t³ with t = x − c, c a float next to the column's
    mean; p_k are its exact coefficients, rounded.

    With μ, C2 and C3 the column's mean and central sums of squares and cubes and δ = x − μ, the
    moment is C3 − A·δ + B·δ³, A = 3·C2/(n + 1), B = n(n − 1)/(n + 1)²; δ = t + h, h = c − μ.
    """
    mean, sum2, sum3 = Fraction(s1, n * scale), Fraction(s2, scale**2), Fraction(s3, scale**3)
    c2 = sum2 - n * mean**2
    c3 = sum3 - 3 * mean * sum2 + 2 * n * mean**3
    a, b = 3 * c2 / (n + 1), Fraction(n * (n - 1), (n + 1) ** 2)
    centre = float(mean)
    h = Fraction(centre) - mean
    exact = [b * h**3 - a * h + c3, 3 * b * h * h - a, 3 * b * h, b]
    return centre, [float(p) for p in exact]


@detector_parameters
class ECOD(BaseDetector):
    """PyOD's ECOD score of a step's state scored alone (see the module docstring). No
    parameters of its own; the threshold parameters of every detector."""

    name: ClassVar[str] = "ecod"
    # z_t reads s_t alone, with exact or certified arithmetic: one row scored alone gets the
    # bits it gets in a batch.
    row_independent: ClassVar[bool] = True

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        x = stacked(trajectories, _states)
        n, d = x.shape
        self.n_fit_ = n
        self.keys_ = _keyed(np.sort(x, axis=0)).T.ravel()  # column 0's n keys, column 1's, …
        # The first key of column j in keys_ (searchsorted's position minus it is the count).
        self.offsets_ = np.arange(d) * n
        # tail_[c] = −log((c + 1)/(n + 1)), c = 0 … n; + 0.0 makes −log 1 = −0.0 a plain 0.
        self.tail_ = -numerics.log(np.arange(1, n + 2) / (n + 1)) + 0.0
        self.power_sums_ = [_power_sums(column) for column in x.T]
        cubics = [_skewness_cubic(n, *sums) for sums in self.power_sums_]
        self.centre_ = np.array([centre for centre, _ in cubics])
        self.cubic_ = np.array([p for _, p in cubics]).T  # (4, d): coefficients of t⁰ … t³

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        return split_scores(self._scores(stacked(trajectories, _states)), trajectories)

    def stream(self) -> DetectorStream:
        return ECODStream(self)

    def _scores(self, x: np.ndarray) -> np.ndarray:
        """ECOD scores of rows x (T, d), each ranked among the fit rows and itself alone."""
        n, queries = self.n_fit_, _keyed(x).ravel()
        at_most = np.searchsorted(self.keys_, queries, side="right").reshape(x.shape)
        below = np.searchsorted(self.keys_, queries, side="left").reshape(x.shape)
        at_most -= self.offsets_  # #{X_j ≤ x_j}
        below -= self.offsets_  # #{X_j < x_j}
        left, right = self.tail_[at_most], self.tail_[n - below]
        per_column = np.maximum(left, right)
        zero = self._zero_skewness(x, (below > 0) & (at_most < n))
        if len(zero[0]):
            per_column[zero] = left[zero] + right[zero]
        total = per_column[:, 0].copy()
        for j in range(1, x.shape[1]):  # in index order: the same sum on every machine
            total += per_column[:, j]
        return total

    def _zero_skewness(self, x: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, ...]:
        """The indices (i, j), among `inside`, where column j of the fit rows with x[i, j] added
        has a third central moment of exactly zero."""
        t = x - self.centre_
        p0, p1, p2, p3 = self.cubic_
        value = ((p3 * t + p2) * t + p1) * t + p0
        s, (a0, a1, a2, a3) = np.abs(t), np.abs(self.cubic_)
        size = ((a3 * s + a2) * s + a1) * s + a0
        # Horner's rounding (γ₆), the coefficients' and t's (one u each) stay well inside 2⁻⁴⁸
        # of Σ|p_k||t|^k; + 8·tiny for subnormal results. Outside the bound, certainly not 0.
        open_ = inside & ~(np.abs(value) > 2.0**-48 * size + 8 * _TINY)
        rows, columns = np.nonzero(open_)
        values = x[rows, columns].tolist()
        exact = [self._exactly_zero(j, v) for j, v in zip(columns, values, strict=True)]
        return rows[exact], columns[exact]

    def _exactly_zero(self, j: int, value: float) -> bool:
        """Whether the third central moment of fit column j with `value` added is exactly 0."""
        n1 = self.n_fit_ + 1
        scale, s1, s2, s3 = self.power_sums_[j]
        p, q = value.as_integer_ratio()
        v = p * scale  # the power sums of the n + 1 values, all scaled by K·q
        t1, t2, t3 = s1 * q + v, s2 * q * q + v * v, s3 * q**3 + v**3
        return n1 * n1 * t3 - 3 * n1 * t1 * t2 + 2 * t1**3 == 0


class ECODStream(DetectorStream):
    """Scores each step's state alone with the batch code (`ECOD._scores`): the same bits, in
    O(d log n) a step."""

    def _update(self, step: Trajectory, t: int) -> StepScores:
        return self.scored(t, self.detector._scores(_states(step)))
