"""Machine-independent arithmetic: results equal the exact value correctly rounded to float32."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from oodrl import numerics


def exact_linear(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The reference: exact rational sums, rounded to the nearest float32."""
    out = np.empty((x.shape[0], w.shape[0]), np.float32)
    for i in range(x.shape[0]):
        for j in range(w.shape[0]):
            total = sum(
                (Fraction(float(a)) * Fraction(float(c)) for a, c in zip(x[i], w[j], strict=True)),
                Fraction(float(b[j])),
            )
            out[i, j] = numerics._nearest_float32(total)
    return out


finite32 = st.floats(-1e3, 1e3, width=32, allow_subnormal=False)


@settings(max_examples=60, deadline=None)
@given(
    arrays(np.float32, (3, 7), elements=finite32),
    arrays(np.float32, (4, 7), elements=finite32),
    arrays(np.float32, (4,), elements=finite32),
)
def test_linear_is_the_correctly_rounded_exact_result(x, w, b):
    np.testing.assert_array_equal(numerics.linear(x, w, b), exact_linear(x, w, b))


def test_linear_handles_cancellation_that_float64_blas_gets_wrong():
    # 1e8 + 1 − 1e8 in float32 products: the exact sum is 1 (float64 gets it right here, the
    # point is that near-ties are resolved exactly, not by the kernel's summation order).
    x = np.array([[16777216.0, 1.0, -16777216.0]], np.float32)
    w = np.array([[1.0, 1.0, 1.0]], np.float32)
    assert numerics.linear(x, w, np.zeros(1, np.float32))[0, 0] == np.float32(1.0)


def test_uncertain_entries_take_the_exact_path():
    # A sum whose exact value is a float32 rounding midpoint: 1 + 2^-24 lies halfway between
    # 1 and the next float32; ties go to even (1.0). The float64 sum is exact here too, but
    # the interval check cannot certify it, so the Fraction path decides.
    x = np.array([[1.0, 2.0**-24]], np.float32)
    w = np.array([[1.0, 1.0]], np.float32)
    assert numerics.linear(x, w)[0, 0] == np.float32(1.0)
    x = np.array([[1.0, 3 * 2.0**-24]], np.float32)  # 1 + 1.5 ulp rounds up to 1 + 2 ulp
    assert numerics.linear(x, w)[0, 0] == np.float32(1.0 + 2.0**-22)


@settings(max_examples=200, deadline=None)
@given(arrays(np.float32, (16,), elements=st.floats(-20, 20, width=32)))
def test_tanh_is_correctly_rounded(x):
    import decimal

    expected = []
    with decimal.localcontext() as context:
        context.prec = 60
        for value in x:
            e2x = (2 * decimal.Decimal(float(value))).exp()
            expected.append(numerics._nearest_float32(Fraction((e2x - 1) / (e2x + 1))))
    np.testing.assert_array_equal(numerics.tanh(x), np.array(expected, np.float32))


@pytest.mark.parametrize("n", [1, 5, 16])
def test_linear_rows_do_not_influence_each_other(n):
    rng = np.random.default_rng(0)
    x = rng.standard_normal((n, 33)).astype(np.float32)
    w = rng.standard_normal((9, 33)).astype(np.float32)
    b = rng.standard_normal(9).astype(np.float32)
    batched = numerics.linear(x, w, b)
    one_by_one = np.concatenate([numerics.linear(x[i : i + 1], w, b) for i in range(n)])
    np.testing.assert_array_equal(batched, one_by_one)
