"""`kde_density`: negative log of a Gaussian kernel density estimate (SPEC §5).

    p̂(x) = (1/n) Σ_j N(x; r_j, h² I),   z_t = −log(p̂(x_t) + ε),

on standardised features x_t (state by default), with r_1..r_n the standardised fit features,
subsampled (seeded, without replacement) to at most `max_reference` points. The density is that
of the standardised feature space; the standardisation's constant Jacobian does not change ranks.

The log-density is exact up to floating point: a brute-force log-sum-exp over all reference
points in float64, chunked over the scored rows, with the per-row maximum factored out, so far
outliers get their true (very negative) log-density instead of underflowing. It is computed in
the log domain, so ε is not needed for finiteness; ε > 0 caps every score at −log ε (far
outliers tie), which is why the default is 0.

Bandwidth h: "scott" n^(−1/(d+4)), "silverman" (n(d+2)/4)^(−1/(d+4)) (the standardised-data
forms of scipy's rules, n = number of reference points), or a float in standardised units.
"""

from __future__ import annotations

import decimal
from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import FeatureSetDetector, seeded_subsample, split_scores
from oodrl.validation import Interval, Options

BANDWIDTH_RULES = ("scott", "silverman")

_UNIT_ROUNDOFF = 2.0**-53
#: Significant bits of a certified log-density (relative resolution 2^-24 ≈ 6e-8).
_KDE_BITS = 24

#: Scored rows per block: (rows × reference) float64 temporaries stay cache-sized.
_ROWS_PER_BLOCK = 128


def bandwidth_of(rule: str | float, n: int, d: int) -> float:
    """The kernel width h on standardised data for a rule name or a given float.

    The rules' fractional powers are evaluated in ``decimal``: libm's ``pow`` may differ in the
    last bit between machines (SPEC §14).
    """
    exponent = decimal.Decimal(-1) / (d + 4)
    if rule == "scott":
        return float(decimal.Decimal(n) ** exponent)
    if rule == "silverman":
        return float((decimal.Decimal(n * (d + 2)) / 4) ** exponent)
    return float(rule)


def gaussian_kde_logpdf(x: np.ndarray, reference: np.ndarray, bandwidth: float) -> np.ndarray:
    """log (1/n) Σ_j N(x_i; r_j, h² I) for every row of x, exactly (chunked log-sum-exp).

    −‖x − r‖²/(2h²) = x·r/h² − ‖r‖²/(2h²) − ‖x‖²/(2h²); the last term is constant per row and
    leaves the log-sum-exp, so each block needs one matrix product and one exp.

    Machine independence (SPEC §14): the exponents are computed in a fixed order
    (`numerics.matmul`), but numpy's exp and log differ in the last bits between CPUs. Those
    differences move a row's result by at most (2n + 64)·u·(its magnitude), so the result is
    certified to 24 significant bits (`numerics.certify`); the rare rows where that bound
    straddles a rounding boundary are summed in ``decimal``.
    """
    n, d = reference.shape
    inv_h2 = 1.0 / bandwidth**2
    scaled_reference_t = np.ascontiguousarray(reference.T) * inv_h2
    reference_term = 0.5 * inv_h2 * (reference * reference).sum(axis=1)
    log_norm = float(
        numerics.log(np.float64(n)) + 0.5 * d * numerics.log(np.float64(2.0 * np.pi * bandwidth**2))
    )
    out = np.empty(x.shape[0])
    bound = np.empty(x.shape[0])
    for start in range(0, x.shape[0], _ROWS_PER_BLOCK):
        block = x[start : start + _ROWS_PER_BLOCK]
        rows = slice(start, start + len(block))
        exponents = _exponents(block, scaled_reference_t, reference_term)
        peak = exponents.max(axis=1)
        log_sum = np.log(np.exp(exponents - peak[:, None]).sum(axis=1))
        row_term = 0.5 * inv_h2 * (block * block).sum(axis=1)
        out[rows] = log_sum + peak - row_term - log_norm
        magnitude = np.abs(log_sum) + np.abs(peak) + np.abs(row_term) + abs(log_norm) + 1.0
        bound[rows] = (2 * n + 64) * _UNIT_ROUNDOFF * magnitude

    def exact(index: tuple[int, ...]) -> float:
        (row,) = index
        exponents = _exponents(x[row : row + 1], scaled_reference_t, reference_term)[0]
        row_term = 0.5 * inv_h2 * float((x[row] * x[row]).sum())
        with decimal.localcontext() as context:
            context.prec = 40
            total = sum(decimal.Decimal(float(e)).exp() for e in exponents)
            return float(total.ln() - decimal.Decimal(row_term) - decimal.Decimal(log_norm))

    return numerics.certify(out, bound, exact, bits=_KDE_BITS)


def _exponents(
    block: np.ndarray, scaled_reference_t: np.ndarray, reference_term: np.ndarray
) -> np.ndarray:
    """x·r/h² − ‖r‖²/(2h²) for every row of ``block`` and every reference point."""
    return numerics.matmul(block, scaled_reference_t) - reference_term


@detector_parameters
class KdeDensity(FeatureSetDetector):
    """Negative log Gaussian-kernel density of standardised step features.

    Parameters
    ----------
    features : "state" | "state_action" | "transition", default "state"
    bandwidth : "scott" | "silverman" | float > 0, default "scott"
    max_reference : int >= 1, default 4096
        Largest number of fit points kept as kernel centres (a seeded subsample).
    epsilon : float >= 0, default 0.0
        ε in −log(p̂ + ε).
    """

    name: ClassVar[str] = "kde_density"
    # z_t reads step t alone (s_t, a_t, s_{t+1}): a stream scores each step on its own.
    row_independent: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "bandwidth": [Options(BANDWIDTH_RULES), Interval(float, 0, None, closed="neither")],
        "max_reference": [Interval(int, 1, None)],
        "epsilon": [Interval(float, 0, None)],
    }

    bandwidth: str | float = "scott"
    max_reference: int = 4096
    epsilon: float = 0.0

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        z = self._fit_features(trajectories)
        self.reference_ = z[seeded_subsample(len(z), self.max_reference, self.seed)]
        self.bandwidth_ = bandwidth_of(self.bandwidth, *self.reference_.shape)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        x = self._standardized_features(trajectories)
        log_density = gaussian_kde_logpdf(x, self.reference_, self.bandwidth_)
        if self.epsilon > 0:
            # log(p + ε) = log ε + softplus(log p − log ε), machine-independent.
            log_epsilon = numerics.log(np.float64(self.epsilon))
            log_density = log_epsilon + numerics.softplus(log_density - log_epsilon)
        return split_scores(-log_density, trajectories)
