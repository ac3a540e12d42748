"""Arithmetic whose float32 results do not depend on the machine (SPEC §14).

BLAS libraries (MKL, OpenBLAS) pick a kernel per CPU (AVX2, AVX-512, …); each kernel sums a
dot product in its own order, so the last bits of a float32 matrix product differ between
machines. Once a policy's action differs by one ulp the simulator's trajectory diverges.

oodrl therefore defines each layer's output as the *correctly rounded* float32 value of the exact
result, a quantity that has one answer whatever the summation order:

1. Products of two float32 numbers are exact in float64, so ``x @ W.T + b`` computed in float64
   by any BLAS kernel is within ``γ_{k+1} · (|x| @ |W|.T + |b|)`` of the exact sum, in any
   summation order (Higham, *Accuracy and Stability of Numerical Algorithms*, §3.1).
2. Rounding is monotonic: if both ends of that interval round to the same float32, so does the
   exact value, and that float32 is the answer.
3. Otherwise (about once in 10^5 outputs) the entry is summed exactly with ``fractions.Fraction``
   and rounded to the nearest float32 (ties to even).

``tanh`` is handled the same way: any libm's float64 ``tanh`` is within a few ulp of the truth;
the rare entries whose interval straddles a float32 rounding boundary are computed with
``decimal`` at 50 significant digits. Elementwise IEEE operations (``+ − × ÷ √``, ``max``) are
exact already and need no care.
"""

from __future__ import annotations

import decimal
import math
from fractions import Fraction

import numpy as np

_UNIT_ROUNDOFF = 2.0**-53
#: Max error of a float64 tanh from any reasonable libm, in ulp, with a wide margin.
_TANH_ULPS = 8


def linear(x: np.ndarray, weight: np.ndarray, bias: np.ndarray | None = None) -> np.ndarray:
    """``x @ weight.T + bias`` for float32 inputs, correctly rounded to float32.

    ``x`` (n, k), ``weight`` (m, k), ``bias`` (m,) — all float32 (or exactly convertible).
    """
    x32 = np.asarray(x, dtype=np.float32)
    w32 = np.asarray(weight, dtype=np.float32)
    x64, w64 = x32.astype(np.float64), w32.astype(np.float64)
    y = x64 @ w64.T
    magnitude = np.abs(x64) @ np.abs(w64).T
    k = x64.shape[-1]
    if bias is not None:
        b64 = np.asarray(bias, dtype=np.float32).astype(np.float64)
        y += b64
        magnitude += np.abs(b64)
        k += 1
    # γ_k = k·u / (1 − k·u) bounds the sum's error; doubling it also covers the rounding error of
    # `magnitude` itself (computed in float64 too) and of forming y ± bound below.
    gamma = k * _UNIT_ROUNDOFF / (1.0 - k * _UNIT_ROUNDOFF)
    bound = 2.0 * gamma * magnitude + np.finfo(np.float64).tiny
    result, uncertain = _round_within(y, bound)
    for index in zip(*np.nonzero(uncertain), strict=True):
        row, col = index[:-1], index[-1]
        terms = [
            Fraction(float(a)) * Fraction(float(b)) for a, b in zip(x32[row], w32[col], strict=True)
        ]
        if bias is not None:
            terms.append(Fraction(float(np.float32(bias[col]))))
        result[index] = _nearest_float32(sum(terms, Fraction(0)))
    return result


def relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, np.float32(0))


def tanh(x: np.ndarray) -> np.ndarray:
    """``tanh`` of float32 values, correctly rounded to float32."""
    x32 = np.asarray(x, dtype=np.float32)
    y = np.tanh(x32.astype(np.float64))
    bound = _TANH_ULPS * np.spacing(np.abs(y)) + np.finfo(np.float64).tiny
    result, uncertain = _round_within(y, bound)
    if uncertain.any():
        with decimal.localcontext() as context:
            context.prec = 50
            for index in zip(*np.nonzero(uncertain), strict=True):
                value = decimal.Decimal(float(x32[index]))
                e2x = (2 * value).exp()
                exact = Fraction((e2x - 1) / (e2x + 1))
                result[index] = _nearest_float32(exact)
    return result


def _round_within(y: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 rounding of ``y`` and a mask of entries where ``y ± bound`` round differently."""
    low = np.nextafter(y - bound, -np.inf).astype(np.float32)
    high = np.nextafter(y + bound, np.inf).astype(np.float32)
    return y.astype(np.float32), low != high


def _nearest_float32(value: Fraction) -> np.float32:
    """The float32 nearest to an exact rational (ties to even)."""
    guess = np.float32(float(value))
    candidates = [
        np.nextafter(guess, np.float32(-np.inf)),
        guess,
        np.nextafter(guess, np.float32(np.inf)),
    ]
    finite = [c for c in candidates if math.isfinite(float(c))]

    def distance(c: np.float32) -> tuple[Fraction, int]:
        mantissa_odd = int(np.float32(c).view(np.uint32)) & 1
        return abs(Fraction(float(c)) - value), mantissa_odd

    return min(finite, key=distance)
