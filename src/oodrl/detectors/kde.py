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

    Machine independence (SPEC §14): the value defined is the log-sum-exp of the exponents
    e_j = x·r_j/h² − ‖r_j‖²/(2h²) summed in index order (`numerics.matmul`, then the subtraction),
    certified to 24 significant bits (`numerics.certify`); the rare rows whose error bound
    straddles a rounding boundary are summed in ``decimal`` from those exponents. The fast path
    differs from it in two machine-dependent ways, both inside the bound:

    - numpy's exp and log differ in the last bits between CPUs (≤ 8 ulp each, with margin).
      With p = max_j e_j and z_j = e_j − p (rounded: relative error u, so exp(z_j) gains
      relative error u·|z_j|), the sum S = Σ_j exp(z_j) ≥ 1 (its peak term is exp(0)) has
      relative error at most 16u + γ_n (n non-negative terms, any order) + u·Σ_j exp(z_j)|z_j|/S
      ≤ (1 + 1/e)·n·u + 17u, since exp(z)|z| ≤ 1/e; log S then errs by about as much, absolute,
      plus 16u·|log S|; the three additions forming the result add u·(magnitude) each, the
      magnitude being |log S| + |p| + |row term| + |log normaliser|. (3n + 64)·u
      + 24u·(magnitude) bounds all of it with room;
    - the exponents come from BLAS (one product of [x, 1] and [r/h²; −‖r‖²/(2h²)], any order).
      Each computed exponent, like the index-order one, is a sum of the d + 1 terms
      x_i·r_ji/h² and −‖r_j‖²/(2h²) with rounded products, so within γ_{d+1}·(S_j + t_j) of the
      exact sum (Higham §3.1, any order), S_j = Σ_i |x_i||r_ji|/h², t_j = ‖r_j‖²/(2h²); the two
      differ by at most 2γ_{d+1}·max_j (S_j + t_j) ≤ 2γ_{d+1}·(Σ_i |x_i|·max_j |r_ji|/h²
      + max_j t_j), a per-row bound; 3γ_{d+1} covers its own rounding. The log-sum-exp is
      1-Lipschitz in the max-norm of its arguments, so the result moves by no more.
    """
    n, d = reference.shape
    inv_h2 = 1.0 / bandwidth**2
    scaled_reference_t = np.ascontiguousarray(reference.T) * inv_h2
    reference_term = 0.5 * inv_h2 * (reference * reference).sum(axis=1)
    # [r/h²; −t]: (d + 1, n), so that [x, 1] @ it gives every exponent in one BLAS product.
    augmented_reference = np.vstack([scaled_reference_t, -reference_term])
    reference_scale = np.abs(scaled_reference_t).max(axis=1)  # max_j |r_ji|/h², (d,)
    exponent_gamma = _gamma(d + 1)
    log_norm = float(
        numerics.log(np.float64(n)) + 0.5 * d * numerics.log(np.float64(2.0 * np.pi * bandwidth**2))
    )
    out = np.empty(x.shape[0])
    bound = np.empty(x.shape[0])
    for start in range(0, x.shape[0], _ROWS_PER_BLOCK):
        block = x[start : start + _ROWS_PER_BLOCK]
        rows = slice(start, start + len(block))
        augmented = np.empty((len(block), d + 1))
        augmented[:, :d] = block
        augmented[:, d] = 1.0
        exponents = augmented @ augmented_reference
        peak = exponents.max(axis=1)
        np.subtract(exponents, peak[:, None], out=exponents)
        np.exp(exponents, out=exponents)
        log_sum = np.log(exponents.sum(axis=1))
        row_term = 0.5 * inv_h2 * (block * block).sum(axis=1)
        out[rows] = log_sum + peak - row_term - log_norm
        magnitude = np.abs(log_sum) + np.abs(peak) + np.abs(row_term) + abs(log_norm)
        exponent_error = np.abs(block) @ reference_scale + reference_term.max()
        bound[rows] = (
            3 * n + 64 + 24 * magnitude
        ) * _UNIT_ROUNDOFF + 3 * exponent_gamma * exponent_error

    def exact(index: tuple[int, ...]) -> float:
        (row,) = index
        exponents = _exponents(x[row : row + 1], scaled_reference_t, reference_term)[0]
        row_term = 0.5 * inv_h2 * float((x[row] * x[row]).sum())
        with decimal.localcontext() as context:
            context.prec = 40
            total = sum(decimal.Decimal(float(e)).exp() for e in exponents)
            return float(total.ln() - decimal.Decimal(row_term) - decimal.Decimal(log_norm))

    return numerics.certify(out, bound, exact, bits=_KDE_BITS)


def _gamma(n: int) -> float:
    """γ_n = n·u / (1 − n·u), Higham's bound on the relative error of an n-term dot product."""
    return n * _UNIT_ROUNDOFF / (1.0 - n * _UNIT_ROUNDOFF)


def _exponents(
    block: np.ndarray, scaled_reference_t: np.ndarray, reference_term: np.ndarray
) -> np.ndarray:
    """x·r/h² − ‖r‖²/(2h²) for every row of ``block`` and every reference point, in index order
    (the machine-independent definition the certified result is the rounding of)."""
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
