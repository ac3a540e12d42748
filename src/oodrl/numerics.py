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
   exact value, and that float32 is the answer. The magnitude ``|x| @ |W|.T`` need not be
   exact, only an upper bound: :func:`linear` starts from a cheap per-row one and tightens it
   only for the entries it leaves uncertain (see its docstring).
3. Otherwise (rare, unless the sum cancels: gradients) the entry is summed exactly with
   ``math.fsum`` over the exact float64 products and rounded to the nearest float32 (ties to even).

A zero result is always +0: an interval around zero rounds to ±0 at both ends, and which sign
the kernel's rounding produced is not part of the answer.

A policy acts on small batches with the same weights thousands of times: :class:`Affine` is
`linear` with the weights prepared once and a cheaper magnitude bound, the same bits; and where
only a ReLU network's argmax is used (a discrete action), :class:`ReluArgmax` certifies it from
one plain float64 pass without rounding every layer, deferring the rare undecided rows.

``tanh`` is handled the same way: any libm's float64 ``tanh`` is within a few ulp of the truth;
the rare entries whose interval straddles a float32 rounding boundary are computed with
``decimal`` at 50 significant digits. Elementwise IEEE operations (``+ − × ÷ √``, ``max``) are
exact already and need no care.

The detectors compute in float64, where the same problems appear: numpy's own ``exp``, ``log``,
``tanh`` and FFT have per-CPU SIMD implementations that differ in the last bits, and BLAS
products and LAPACK solves depend on the kernel. For them:

- :func:`matmul` sums products in one fixed order with elementwise numpy operations (no BLAS),
  or BLAS's product certified against that order where a caller bounds the difference
  (``kde_density``'s exponents);
- :func:`spd_inverse` and :func:`spd_solve` are a Cholesky factorisation whose inner products
  are ``math.fsum`` (exactly rounded);
- :func:`exp`, :func:`log` and :func:`softplus` return the true value rounded to 32 significant
  bits (relative precision 2⁻³²): certified from numpy's float64 result where its error
  interval allows, else from ``decimal``.

Integer-exact or order-fixed operations (sorting, ranking, ``np.sum`` along an axis, which numpy
reduces in an order fixed by the array's shape) need nothing.
"""

from __future__ import annotations

import decimal
import math
import threading
from collections.abc import Sequence
from fractions import Fraction
from typing import NamedTuple

import numpy as np

_UNIT_ROUNDOFF = 2.0**-53
#: The same for float32 (round to nearest).
_FLOAT32_UNIT = 2.0**-24
#: Max error of a float64 tanh from any reasonable libm, in ulp, with a wide margin.
_TANH_ULPS = 8


def linear(x: np.ndarray, weight: np.ndarray, bias: np.ndarray | None = None) -> np.ndarray:
    """``x @ weightᵀ + bias`` for float32 inputs, correctly rounded to float32 (a zero is +0).

    ``x`` (..., n, k), ``weight`` (..., m, k), ``bias`` broadcastable to (..., n, m); leading
    axes broadcast like ``np.matmul`` (an ensemble: one weight per member).

    Step 1 of the module docstring needs, per entry, the magnitude
    ``M_ij = Σ_l |x_il||w_jl| + |b_ij|``. Computing it for every entry costs a second matrix
    product, so on large outputs it is bounded in levels, each for the entries the previous one
    left uncertain:

    1. per row, ``M_ij ≤ R_i + max_j |b_ij|`` with ``R_i = Σ_l |x_il|·max_j |w_jl|``
       (a matrix-vector product, broadcast along the row: the check needs no bound array);
    2. many entries left (cancelling sums, e.g. gradients): every ``M_ij``, one matrix product;
    3. few left: their own ``M_ij`` from the gathered (exact) float64 products;
    4. ``math.fsum`` of those products: the exact sum, rounded once.

    Small outputs and long sums compute every ``M_ij`` at once. R and the every-entry M are
    float32 products bounded as in `_float32_bound`; the gathered M is a float64 sum of
    non-negative exact products, at most γ_k below its exact value.
    """
    x32 = np.asarray(x, dtype=np.float32)
    w32 = np.asarray(weight, dtype=np.float32)
    x64 = _scratch("x64", x32.shape, np.float64)
    x64[...] = x32
    w64_t = np.swapaxes(w32, -1, -2).astype(np.float64)  # (..., k, m)
    shape = np.broadcast_shapes(x32.shape[:-2], w32.shape[:-2]) + (x32.shape[-2], w32.shape[-2])
    y = np.matmul(x64, w64_t, out=_scratch("y", shape, np.float64))
    k = x32.shape[-1]
    abs_x, abs_w_t = np.abs(x32), np.swapaxes(np.abs(w32), -1, -2)
    # Long sums (gradients over a batch) cancel, and leave many entries to level 2.
    every = y.size <= _EVERY_MAGNITUDE_UP_TO or k >= _EVERY_MAGNITUDE_FROM_K
    magnitude = _float32_bound(abs_x, abs_w_t if every else abs_w_t.max(axis=-1, keepdims=True))
    b64 = abs_b = None
    if bias is not None:
        b64 = np.asarray(bias, dtype=np.float32).astype(np.float64)  # as given: broadcasts
        y += b64
        abs_b = np.abs(b64)
        magnitude = magnitude + (abs_b if every else abs_b.max(axis=-1, keepdims=True))
        k += 1
    # The float64 sum of the k terms (products, bias) is within γ_k·M of the exact one in any
    # summation order, FMA or not. A computed bound B ≥ (1 − γ_k)·(its exact value) ≥ ½·M, so
    # 2γ_k·B bounds the error (with room for the rounding of the bound's own product).
    gamma = _gamma(k)
    result, uncertain = _round_within(y, 2 * gamma * magnitude)
    if not uncertain.any():
        return result
    index = _uncertain_index(uncertain)
    values = y[index]
    if not every and len(values) > _GATHERED_MAGNITUDES_UP_TO:  # level 2
        magnitude = _float32_bound(abs_x, abs_w_t)
        if abs_b is not None:
            magnitude += abs_b
        rounded, still = _round_within(values, 2 * gamma * magnitude[index])
        result[index] = rounded
        index, values = tuple(axis[still] for axis in index), values[still]
    if not len(values):
        return result
    lead, i, j = index[:-2], index[-2], index[-1]
    rows = np.broadcast_to(x64, (*y.shape[:-1], x32.shape[-1]))
    cols = np.broadcast_to(np.swapaxes(w64_t, -1, -2), (*y.shape[:-2], *w32.shape[-2:]))
    entry_bias = None if b64 is None else np.broadcast_to(b64, y.shape)[index]
    result[index] = _exact_entries(rows[(*lead, i)], cols[(*lead, j)], entry_bias, values, gamma)
    return result


def _exact_entries(
    x_rows: np.ndarray, w_rows: np.ndarray, bias: np.ndarray | None, values: np.ndarray, gamma
) -> np.ndarray:
    """Levels 3 and 4 of `linear`: float32 entries ``x_rows · w_rows + bias``, one per row
    of the float64 copies of float32 ``x_rows`` and ``w_rows`` (e, k) and ``bias`` (e,), whose
    float64 sums were ``values``: certified by each entry's own magnitude, else ``math.fsum``."""
    # Products of two float32 numbers are exact in float64: the sums below are exact.
    products = x_rows * w_rows
    if bias is not None:
        products = np.concatenate([products, bias[:, None]], 1)
    rounded, still = _round_within(values, 2 * gamma * np.abs(products).sum(axis=1))
    for entry in np.flatnonzero(still):
        rounded[entry] = _nearest_float32_of_sum(products[entry].tolist())
    return rounded


class Affine:
    """``x @ weightᵀ + bias`` for one fixed float32 weight (m, k) and bias (m,): the same bits
    as `linear`, cheaper for the small batches a policy acts on, call after call.

    The weights' float64 copy and row norms ‖W_j‖₂ are made once. The magnitude bound of step 1
    of the module docstring is then, by Cauchy–Schwarz, ``Σ_l |x_l||w_jl| + |b_j| ≤
    ‖x‖₂‖W_j‖₂ + |b_j|``: one norm per row, no second matrix product. It is looser than
    `linear`'s, but still far inside a float32 rounding interval (γ_{k+1} ≈ k·2⁻⁵³ against
    2⁻²⁴ relative), so few entries are left uncertain; they take `linear`'s levels 3 and 4.
    As there, a computed bound B is at least half its exact value, so ``2γ_{k+1}·B`` bounds the
    error.
    """

    def __init__(self, weight: np.ndarray, bias: np.ndarray) -> None:
        self.w_t = np.asarray(weight, np.float32).T.astype(np.float64)  # (k, m), exact copies
        self.b = np.asarray(bias, np.float32).astype(np.float64)
        self.gamma = _gamma(len(self.w_t) + 1)
        self.norms = np.sqrt(np.square(self.w_t).sum(axis=0))  # ‖W_j‖₂; float32 squares exact
        self.abs_b = np.abs(self.b)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x64 = np.asarray(x, dtype=np.float32).astype(np.float64)
        y = x64 @ self.w_t
        y += self.b
        bound = np.multiply.outer(_row_norms(x64), self.norms)
        bound += self.abs_b
        bound *= 2 * self.gamma
        result, uncertain = _round_within(y, bound)
        if uncertain.any():
            i, j = np.nonzero(uncertain)
            w_rows = self.w_t[:, j].T
            result[i, j] = _exact_entries(x64[i], w_rows, self.b[j], y[i, j], self.gamma)
        return result


#: Outputs up to this size, or sums of this many terms, get every entry's magnitude at once.
_EVERY_MAGNITUDE_UP_TO = 4096
_EVERY_MAGNITUDE_FROM_K = 128
#: Up to this many entries left uncertain by the row bound get their magnitudes one by one.
_GATHERED_MAGNITUDES_UP_TO = 64


def _float32_bound(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """An upper bound on the exact ``a @ b`` of non-negative float32 arrays, as float64.

    The float32 product (any kernel) rounds each of its at most 2k operations within a factor
    1 ± 2⁻²⁴, or within 2⁻¹⁵⁰ absolute where a result is subnormal: the computed value times
    1 + 4(k + 1)·2⁻²⁴, plus (k + 1)·2⁻¹⁴⁸, bounds the exact one (an overflow gives inf: those
    entries are uncertain and go on to the exact path).
    """
    k = a.shape[-1]
    with np.errstate(over="ignore"):
        product = a @ b
    return product.astype(np.float64) * (1.0 + 4.0 * (k + 1) * 2.0**-24) + (k + 1) * 2.0**-148


_SCRATCH = threading.local()


def _scratch(name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """A temporary array of this thread, reused from call to call under ``name``.

    Fresh large arrays cost page faults each time (the allocator hands their memory back to
    the system); `linear`'s temporaries are the same few shapes thousands of times. The array
    is valid until the next request under the same name: use it within one function call.
    """
    size = math.prod(shape)
    buffer = getattr(_SCRATCH, name, None)
    if buffer is None or buffer.size < size or buffer.dtype != dtype:
        buffer = np.empty(size, dtype)
        setattr(_SCRATCH, name, buffer)
    return buffer[:size].reshape(shape)


def _gamma(n: int) -> float:
    """Higham's γ_n = n·u / (1 − n·u): the relative error bound of a float64 sum of n terms."""
    return n * _UNIT_ROUNDOFF / (1.0 - n * _UNIT_ROUNDOFF)


def relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, np.float32(0))


class ReluArgmax:
    """The argmax of a ReLU network's outputs, decided in plain float64 where that is certain.

    The exact network is what `linear` and `relu` compute layer by layer: ``h_0 = x``,
    ``h_l = relu(R(W_l h_{l−1} + b_l))``, outputs ``q = R(W_L h_{L−1} + b_L)``, R the
    rounding to float32; the action is ``q.argmax()``, the first index of the maximum. Here
    the layers run once in float64 (BLAS, any kernel) without R, and each row carries a bound
    D ≥ ‖d‖₂ on its error vector d, ``|h̃ − h| ≤ d`` entrywise (D = 0 for the float32 input).
    For a layer with k inputs, m outputs and a = γ_{k+1}‖h̃‖₂ + D, for output j:

    - ``z̃ = fl(W h̃ + b)`` is within ``γ_{k+1}(|W||h̃| + |b|)`` of ``W h̃ + b`` in any summation
      order, FMA or not (Higham, *Accuracy and Stability of Numerical Algorithms*, (3.5)), and
      ``|W h̃ − W h| ≤ |W| d``; by Cauchy–Schwarz ``e_j = ‖W_j‖₂·a + γ_{k+1}|b_j|`` bounds
      ``|z̃_j − z_j|``;
    - ``|R(z) − z| ≤ u₃₂|z| + 2⁻¹⁵⁰`` (u₃₂ = 2⁻²⁴; 2⁻¹⁵⁰ in float32's subnormal range) while
      R(z) is finite, so ``err = (1 + u₃₂)e + u₃₂|z̃| + 2⁻¹⁴⁹`` bounds ``|z̃ − R(z)|`` (the spare
      2⁻¹⁵⁰ covers float64 underflow, below 2⁻¹⁰⁰⁰);
    - relu is 1-Lipschitz: ``|relu(z̃_j) − relu(R(z_j))| ≤ err_j``, and where ``z̃_j < 0`` it is
      at most ``relu(z̃_j + err_j) ≤ (1 + u₃₂)e_j + 2⁻¹⁴⁹``; so
      ``d_j ≤ (1 + u₃₂)e_j + 2⁻¹⁴⁹ + u₃₂·relu(z̃_j)`` and, by the triangle inequality, the next
      ``D = a·‖(1 + u₃₂)‖W_j‖₂‖₂ + ‖(1 + u₃₂)γ_{k+1}|b_j| + 2⁻¹⁴⁹‖₂ + u₃₂‖relu(z̃)‖₂``, norms
      over j: per row a few scalars, no second matrix product and no per-entry bound;
    - R(z) overflows only where ``z ≥ 2¹²⁸(1 − 2⁻²⁵)``; every z_j is below ``‖relu(z̃)‖₂ + D``,
      so rows where that reaches 2¹²⁷ are left undecided (D = ∞).

    At the outputs, where ``|z̃| + err < 2¹²⁷`` (q finite), ``|z̃ − q| ≤ err``: if
    ``z̃_a − err_a > z̃_b + err_b`` for every ``b ≠ a``, then ``q_a > q_b`` strictly, so a is
    the exact argmax (tied outputs never pass). The bounds are themselves float64 sums, products
    and square roots of non-negative terms, at most 2(k + m) + 32 roundings deep, each losing at
    most a factor (1 − u): each term carries a factor ``μ = 1 + γ_{4(k+m)+64}`` that makes the
    computed value an upper bound again (the thresholds 2¹²⁷, half the overflow, need none).
    Comparisons need no margin: rounding is monotonic, so ``fl(x) > fl(y)`` implies ``x > y``;
    a NaN compares false. A row's verdict may depend on the BLAS kernel, its decided action
    never does.
    """

    def __init__(self, layers: Sequence[Affine]) -> None:
        self.layers = [_BoundedLayer.of(layer) for layer in layers]

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For float32 inputs (n, k): the argmax of each row's outputs (n,) int64, and the rows
        where it is certainly the exact outputs' argmax (n,) bool. The others need those."""
        h = np.asarray(x, np.float32).astype(np.float64)
        norm, bound = _row_norms(h), np.zeros(len(h))  # ‖h̃‖₂ and D per row
        for layer in self.layers[:-1]:
            a = layer.gamma * norm + bound
            h = h @ layer.w_t
            h += layer.b
            np.maximum(h, 0.0, out=h)
            norm = _row_norms(h)
            bound = a * layer.scale_norm + layer.offset_norm + layer.slope * norm
            bound[~(norm + bound < 2.0**127)] = np.inf
        last = self.layers[-1]
        z = h @ last.w_t
        z += last.b
        a = last.gamma * norm + bound
        err = np.multiply.outer(a, last.scale) + last.offset + last.slope * np.abs(z)
        err[~(np.abs(z) + err < 2.0**127)] = np.inf
        rows = np.arange(len(z))
        action = z.argmax(axis=1)
        lowest = z[rows, action] - err[rows, action]
        rival = z + err
        rival[rows, action] = -np.inf
        return action, lowest > rival.max(axis=1, initial=-np.inf)


class _BoundedLayer(NamedTuple):
    """One layer of `ReluArgmax`: its `Affine`'s Wᵀ (k, m) and b (m,) in float64, γ_{k+1}, and
    the terms of its bounds, each with the factor μ: err's ``scale`` (× a) and ``offset`` per
    output and ``slope`` (× |z̃|); D's ``scale_norm`` and ``offset_norm``, their norms over
    the outputs."""

    w_t: np.ndarray
    b: np.ndarray
    gamma: float
    scale: np.ndarray
    offset: np.ndarray
    slope: float
    scale_norm: float
    offset_norm: float

    @classmethod
    def of(cls, layer: Affine) -> _BoundedLayer:
        (k, m), gamma = layer.w_t.shape, layer.gamma
        mu = 1.0 + _gamma(4 * (k + m) + 64)
        rounded = (1.0 + _FLOAT32_UNIT) * mu
        scale = layer.norms * rounded
        offset = gamma * layer.abs_b * rounded + 2.0**-149
        scale_norm = float(np.sqrt(np.square(scale).sum()) * mu)
        offset_norm = float(np.sqrt(np.square(offset).sum()) * mu)
        return cls(
            layer.w_t, layer.b, gamma, scale, offset, _FLOAT32_UNIT * mu, scale_norm, offset_norm
        )


def _row_norms(a: np.ndarray) -> np.ndarray:
    """The Euclidean norm of each row of a float64 matrix (n, k)."""
    return np.sqrt(np.einsum("ij,ij->i", a, a))


def tanh(x: np.ndarray) -> np.ndarray:
    """``tanh`` of float32 values, correctly rounded to float32."""
    x32 = np.asarray(x, dtype=np.float32)
    y = np.tanh(x32.astype(np.float64))
    bound = _TANH_ULPS * np.spacing(np.abs(y)) + np.finfo(np.float64).tiny
    low, high = _round_ends(y, bound)
    # Compared as values: tanh keeps its argument's sign, so a zero's sign is exact already.
    result, uncertain = y.astype(np.float32), low != high
    if uncertain.any():
        with decimal.localcontext() as context:
            context.prec = 50
            for index in zip(*np.nonzero(uncertain), strict=True):
                value = decimal.Decimal(float(x32[index]))
                e2x = (2 * value).exp()
                exact = Fraction((e2x - 1) / (e2x + 1))
                result[index] = _nearest_float32(exact)
    return result


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` in float64, summing over the shared axis in index order, without BLAS.

    ``a`` (..., k), ``b`` (k, m) or (k,). Each step is one elementwise multiply and one add,
    which every CPU rounds identically; cost grows with k, so use it where k is small.

    Every entry is ``((a_0 b_0 + a_1 b_1) + a_2 b_2) + …``, whichever layout the loop runs in:
    with many rows and few columns the loop runs on the transposed (m, rows) layout, so that
    each numpy call's inner loop is long and contiguous (the same products and sums, rounded
    alike, so the same bits). The result is C-contiguous either way, so later reductions over
    its axes run in the same order.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    vector = b.ndim == 1
    if vector:
        b = b[:, None]
    k, m = b.shape
    lead = a.shape[:-1]
    rows = math.prod(lead)
    if m >= 4 and rows >= max(1024, 16 * m) and k > 1:
        a_t = np.moveaxis(a, -1, 0).reshape(k, rows)  # a copy unless already (k, rows)
        out = np.ascontiguousarray(matmul_transposed(a_t, b).T).reshape(*lead, m)
    else:
        out = a[..., 0, None] * b[0]
        for j in range(1, k):
            out += a[..., j, None] * b[j]
    return out[..., 0] if vector else out


def matmul_transposed(a_t: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(a_tᵀ @ b)ᵀ``, (m, rows), for ``a_t`` (k, rows) and ``b`` (k, m): `matmul` on operands
    laid out along the summed axis, summing over it in index order, without BLAS.

    Row j of ``a_t`` is one contiguous array: each step is one (m, rows) multiply and add with
    long inner loops, which every CPU rounds identically.
    """
    a_t = np.asarray(a_t, dtype=np.float64)
    b_t = np.asarray(b, dtype=np.float64)[:, :, None]
    out = np.multiply(b_t[0], a_t[0])
    term = np.empty_like(out)
    for j in range(1, len(a_t)):
        np.multiply(b_t[j], a_t[j], out=term)
        out += term
    return out


def spd_cholesky(matrix: np.ndarray) -> np.ndarray:
    """Lower-triangular L with L Lᵀ = matrix (symmetric positive definite), machine-independent."""
    a = np.asarray(matrix, dtype=np.float64).tolist()
    d = len(a)
    lower = [[0.0] * d for _ in range(d)]
    for j in range(d):
        diagonal = a[j][j] - math.fsum(lower[j][k] * lower[j][k] for k in range(j))
        if not diagonal > 0:
            raise np.linalg.LinAlgError("matrix is not positive definite")
        lower[j][j] = math.sqrt(diagonal)
        for i in range(j + 1, d):
            dot = math.fsum(lower[i][k] * lower[j][k] for k in range(j))
            lower[i][j] = (a[i][j] - dot) / lower[j][j]
    return np.array(lower)


def spd_solve(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``matrix⁻¹ rhs`` for a symmetric positive definite matrix; rhs (d,) or (d, m)."""
    lower = spd_cholesky(matrix).tolist()
    b = np.asarray(rhs, dtype=np.float64)
    columns = b.reshape(len(lower), -1).T.tolist()
    d = len(lower)
    solved = []
    for column in columns:
        y = [0.0] * d
        for i in range(d):  # L y = b
            y[i] = (column[i] - math.fsum(lower[i][k] * y[k] for k in range(i))) / lower[i][i]
        x = [0.0] * d
        for i in reversed(range(d)):  # Lᵀ x = y
            tail = math.fsum(lower[k][i] * x[k] for k in range(i + 1, d))
            x[i] = (y[i] - tail) / lower[i][i]
        solved.append(x)
    return np.array(solved).T.reshape(b.shape)


def spd_inverse(matrix: np.ndarray) -> np.ndarray:
    """The inverse of a symmetric positive definite matrix, made exactly symmetric."""
    inverse = spd_solve(matrix, np.eye(len(matrix)))
    return (inverse + inverse.T) / 2


#: Significant bits kept by the certified transcendental functions.
CERTIFIED_BITS = 32
#: Max error of numpy's float64 exp/log/log1p on any CPU, in ulp, with a wide margin.
_LIBM_ULPS = 8


def exp(x: np.ndarray) -> np.ndarray:
    """e^x rounded to 32 significant bits, the same on every machine (float64 array)."""
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(over="ignore", under="ignore"):
        y = np.exp(x)
    return _certified(y, x, lambda v: v.exp())


def log(x: np.ndarray) -> np.ndarray:
    """ln x (x > 0) rounded to 32 significant bits, the same on every machine (float64 array)."""
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        y = np.log(x)
    return _certified(y, x, lambda v: v.ln())


def softplus(x: np.ndarray) -> np.ndarray:
    """ln(1 + e^x) rounded to 32 significant bits, the same on every machine (float64 array)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.logaddexp(0.0, x)
    return _certified(y, x, lambda v: (1 + v.exp()).ln())


def _certified(y: np.ndarray, x: np.ndarray, reference) -> np.ndarray:
    """``y`` ≈ f(x) rounded to CERTIFIED_BITS; entries numpy's error could flip use ``reference``
    (f on a 50-digit ``decimal.Decimal``). Non-finite results pass through unchanged."""
    finite = np.isfinite(y)
    bound = _LIBM_ULPS * np.spacing(np.where(finite, y, 0.0))

    def exact(index: tuple[int, ...]) -> float:
        with decimal.localcontext() as context:
            context.prec = 50
            context.Emin, context.Emax = -999999, 999999
            return float(reference(decimal.Decimal(float(x[index]))))

    return certify(y, bound, exact)


def certify(values: np.ndarray, bound: np.ndarray, exact, bits: int = CERTIFIED_BITS) -> np.ndarray:
    """Round ``values`` to ``bits`` significant bits, the same on every machine.

    ``values`` are computed by machine-dependent code but within ``bound`` of the true result;
    where ``values ± bound`` round alike, that rounding is certainly the true result's. The other
    entries (rare: about 2·bound / grid spacing) take ``exact(index)``, a float computed by
    machine-independent code (``decimal``, ``fractions``), rounded the same way.
    Non-finite values pass through unchanged.
    """
    shape = np.shape(values)
    values = np.atleast_1d(np.asarray(values, dtype=np.float64))
    finite = np.isfinite(values)
    # 2·bound + tiny: also covers the rounding of the sums below.
    margin = 2 * np.where(finite, bound, 0.0) + np.finfo(np.float64).tiny
    # r = values rounded to `bits` bits (Veltkamp split, as `_round_bits`); values − r is exact.
    # Every float of the open interval (r − h, r + h), h half the smaller spacing of `bits`-bit
    # numbers next to r, rounds to r; so do values ± margin, and the true value, where
    # |values − r| + margin < h. h = 2^(e−bits) for 2^e the power of two just below |r| (the
    # exponent field of |r|·(1 − 2⁻⁵³): e − 1 where |r| = 2^e, whose lower spacing is half);
    # h = 0 for subnormal r. The comparison is false for NaN: non-finite values, and values
    # whose split overflows (near the top of the float64 range), count as uncertain here.
    factor = 2.0 ** (53 - bits) + 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        scaled = values * factor
        rounded = scaled - (scaled - values)
        distance = np.abs(values - rounded)
        distance += margin
        below = np.abs(rounded) * (1.0 - 2.0**-53)
        power = (below.view(np.int64) & np.int64(0x7FF0000000000000)).view(np.float64)
        uncertain = ~(distance < power * 2.0**-bits) & finite
    result = np.where(np.isfinite(rounded), rounded, values)
    for index in zip(*np.nonzero(uncertain), strict=True):
        result[index] = _round_bits(np.float64(exact(index if shape else ())), bits)
    return result.reshape(shape)


def _round_bits(y: np.ndarray, bits: int = CERTIFIED_BITS) -> np.ndarray:
    """Round float64 values to ``bits`` significant bits, to nearest (Veltkamp split)."""
    factor = 2.0 ** (53 - bits) + 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        scaled = y * factor
        rounded = scaled - (scaled - y)
    # Near the top of the float64 range the split overflows; such values stay as they are.
    return np.where(np.isfinite(rounded), rounded, y)


def _round_within(y: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where ``y ± bound`` round to the same float32, that float32 (so also ``y``'s, and the
    exact value's, if within ``bound`` of ``y``), a zero always +0; and the mask of the other
    entries, whose values in the first array are to be replaced.

    ``bound`` may be an array that broadcasts against ``y`` (one value per row). A result that
    rounds to zero is +0 whatever its sign (the kernel's rounding could pick either): adding +0
    turns −0 into +0 and leaves every other value as it is.
    """
    low, high = _round_ends(y, bound)
    uncertain = low != high
    low += np.float32(0)
    return low, uncertain


def _round_ends(y: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 roundings of ``y − 2·bound − tiny`` and ``y + 2·bound + tiny``.

    The doubling covers the rounding of forming the sums themselves, as long as
    bound ≥ u·|y| (true of every error bound here, being ≥ γ·|y|); tiny keeps a zero bound from
    certifying a float32 midpoint. The float64 sums are cast to float32 on the way out of the
    ufunc, without a float64 temporary. Where the two agree, so does y's rounding, which lies
    between them (rounding is monotonic).
    """
    margin = 2 * bound + np.finfo(np.float64).tiny
    low = np.empty(np.shape(y), np.float32)
    high = _scratch("high", np.shape(y), np.float32)
    np.subtract(y, margin, out=low, casting="same_kind")
    np.add(y, margin, out=high, casting="same_kind")
    return low, high


def _uncertain_index(uncertain: np.ndarray) -> tuple[np.ndarray, ...]:
    """``np.nonzero(uncertain)``, faster for a sparse mask (flat search, then unravel)."""
    return np.unravel_index(np.flatnonzero(uncertain), uncertain.shape)


def _nearest_float32_of_sum(terms: list[float]) -> np.float32:
    """The float32 nearest the exact sum of float64 ``terms`` (ties to even); a zero is +0, as
    in `_round_within`."""
    return _nearest_signed_float32_of_sum(terms) + np.float32(0)


def _nearest_signed_float32_of_sum(terms: list[float]) -> np.float32:
    total = math.fsum(terms)  # the exact sum, correctly rounded to float64
    rounded = np.float32(total)
    # Rounding twice (exact → float64 → float32) differs from rounding once only when the float64
    # sum lies exactly on a float32 midpoint; then the sign of the exact remainder decides.
    below = np.nextafter(rounded, np.float32(-np.inf)) if float(rounded) > total else rounded
    above = np.nextafter(below, np.float32(np.inf))
    if math.isfinite(float(above)) and (float(below) + float(above)) / 2 == total:
        remainder = math.fsum([*terms, -total])
        if remainder > 0:
            return above
        if remainder < 0:
            return below
    return rounded


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
