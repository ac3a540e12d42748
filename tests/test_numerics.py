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


@settings(max_examples=60, deadline=None)
@given(
    arrays(np.float32, (3, 7), elements=finite32),
    arrays(np.float32, (4, 7), elements=finite32),
    arrays(np.float32, (4,), elements=finite32),
)
def test_affine_is_the_correctly_rounded_exact_result(x, w, b):
    np.testing.assert_array_equal(numerics.Affine(w, b)(x), exact_linear(x, w, b))


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


def exact_tanh(value: float) -> Fraction:
    """tanh to 60 significant digits, as a fraction."""
    import decimal

    with decimal.localcontext() as context:
        context.prec = 60
        e2x = (2 * decimal.Decimal(float(value))).exp()
        return Fraction((e2x - 1) / (e2x + 1))


@settings(max_examples=200, deadline=None)
@given(arrays(np.float32, (16,), elements=st.floats(-20, 20, width=32)))
def test_tanh_is_correctly_rounded(x):
    expected = [numerics._nearest_float32(exact_tanh(value)) for value in x]
    np.testing.assert_array_equal(numerics.tanh(x), np.array(expected, np.float32))


#: The one float32 in [0.25, 4) whose float64 tanh cannot be certified to round to one float32
#: (an exhaustive search: its exact tanh lies 5e-16 below a float32 midpoint, within the float64
#: error bound); random draws hit such a value about once in 10^7.
TANH_NEAR_A_MIDPOINT = np.float32(0.4648849368095398)


@pytest.mark.parametrize("sign", [1, -1])
def test_tanh_near_a_float32_midpoint_is_correctly_rounded(sign):
    x = np.float32(sign * TANH_NEAR_A_MIDPOINT)
    exact = exact_tanh(x)
    below = np.float32(float(exact))  # float64 then float32: either neighbour of the midpoint
    below = below if Fraction(float(below)) <= exact else np.nextafter(below, np.float32(-1))
    above = np.nextafter(below, np.float32(1))
    midpoint = (Fraction(float(below)) + Fraction(float(above))) / 2
    assert abs(exact - midpoint) < Fraction(1, 10**15)  # what makes it uncertain
    nearest = below if exact < midpoint else above
    assert numerics.tanh(np.array([x, 0.5], np.float32))[0] == nearest


@pytest.mark.parametrize("n", [1, 5, 16])
def test_linear_rows_do_not_influence_each_other(n):
    rng = np.random.default_rng(0)
    x = rng.standard_normal((n, 33)).astype(np.float32)
    w = rng.standard_normal((9, 33)).astype(np.float32)
    b = rng.standard_normal(9).astype(np.float32)
    batched = numerics.linear(x, w, b)
    one_by_one = np.concatenate([numerics.linear(x[i : i + 1], w, b) for i in range(n)])
    np.testing.assert_array_equal(batched, one_by_one)


def exact_integer_linear(x: np.ndarray, w: np.ndarray, b: np.ndarray | None, scale: int):
    """The reference for integer-valued inputs times 2^-scale: exact int64 sums, each rounded
    to the nearest float32 through Fraction (a zero is +0)."""
    xi = (x.astype(np.float64) * 2.0**scale).astype(np.int64)
    wi = (w.astype(np.float64) * 2.0**scale).astype(np.int64)
    total = xi @ np.swapaxes(wi, -1, -2)
    if b is not None:
        total = total + (np.broadcast_to(b, total.shape).astype(np.float64) * 4.0**scale).astype(
            np.int64
        )
    flat = [numerics._nearest_float32(Fraction(int(t), 4**scale)) for t in total.ravel()]
    return (np.array(flat, np.float32) + np.float32(0)).reshape(total.shape)


def integer_valued(rng, shape, bits, scale):
    return (rng.integers(-(2**bits), 2**bits, shape) * 2.0**-scale).astype(np.float32)


@pytest.mark.parametrize(
    ("every_up_to", "gathered_up_to"), [(4096, 64), (0, 64), (0, 0), (0, 10**9), (10**9, 64)]
)
@pytest.mark.parametrize("k", [3, 40, 160])
@pytest.mark.parametrize("bits", [12, 20])
def test_linear_every_bound_level_equals_exact_integer_sums(
    monkeypatch, every_up_to, gathered_up_to, k, bits
):
    # Integer-valued float32 inputs: with 12-bit values many sums are exact float32 midpoints
    # (ties), with 20-bit ones few are; and rows built to cancel, so that every level of the
    # bound (row bound, every magnitude, gathered magnitudes, fsum) gets entries.
    monkeypatch.setattr(numerics, "_EVERY_MAGNITUDE_UP_TO", every_up_to)
    monkeypatch.setattr(numerics, "_GATHERED_MAGNITUDES_UP_TO", gathered_up_to)
    rng = np.random.default_rng(k)
    scale = 7
    x = integer_valued(rng, (3, 70, k), bits, scale)
    w = integer_valued(rng, (3, 50, k), bits, scale)
    x[:, :10] = 0  # zero rows: ±0 products, a +0 result
    x[:, 10:20, : k // 2 * 2 : 2] = x[:, 10:20, 1 : k // 2 * 2 : 2]  # x_2l = x_2l+1 ...
    w[:, :25, : k // 2 * 2 : 2] = -w[:, :25, 1 : k // 2 * 2 : 2]  # ... cancels w_2l = −w_2l+1
    b = integer_valued(rng, (3, 1, 50), bits, scale)
    for bias in (None, b):
        got = numerics.linear(x, w, bias)
        expected = exact_integer_linear(x, w, bias, scale)
        np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))


@pytest.mark.parametrize("k", [3, 40, 160])
@pytest.mark.parametrize("bits", [12, 20])
def test_affine_equals_exact_integer_sums_also_where_it_is_uncertain(monkeypatch, k, bits):
    # As for linear: ties, zero rows and cancelling rows, which its Cauchy–Schwarz bound
    # cannot certify: those entries take the exact path.
    rng = np.random.default_rng(k)
    scale = 7
    x = integer_valued(rng, (70, k), bits, scale)
    w = integer_valued(rng, (50, k), bits, scale)
    x[:10] = 0
    x[10:20, : k // 2 * 2 : 2] = x[10:20, 1 : k // 2 * 2 : 2]
    w[:25, : k // 2 * 2 : 2] = -w[:25, 1 : k // 2 * 2 : 2]
    b = integer_valued(rng, (50,), bits, scale)
    exact_entries = []
    original = numerics._exact_entries

    def spy(x_rows, *args):
        exact_entries.append(len(x_rows))
        return original(x_rows, *args)

    monkeypatch.setattr(numerics, "_exact_entries", spy)
    got = numerics.Affine(w, b)(x)
    expected = exact_integer_linear(x, w, b, scale)
    np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))
    assert sum(exact_entries) > 0


def _exact_relu_network(x, layers):
    """The exact network ReluArgmax stands for: `linear` and `relu`, every output rounded."""
    for i, (w, b) in enumerate(layers):
        x = numerics.linear(x, w, b)
        x = numerics.relu(x) if i < len(layers) - 1 else x
    return x


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([2, 6, 24]))
def test_relu_argmax_decides_only_the_exact_argmax(seed, bits):
    # Integer-valued weights of few bits; outputs 0 and 1 tie exactly, output 2 is output 0
    # with one weight a float32 ulp larger: far below the hidden layers' rounding.
    rng = np.random.default_rng(seed)
    sizes = [5, 24, 24, 4]
    layers = [
        (integer_valued(rng, (m, k), bits, 3), integer_valued(rng, (m,), bits, 3))
        for k, m in zip(sizes[:-1], sizes[1:], strict=True)
    ]
    w, b = layers[-1]
    w[1:3], b[1:3] = w[0], b[0]
    w[2, 0] = np.nextafter(w[0, 0], np.float32(np.inf))
    x = integer_valued(rng, (64, 5), bits, 3)
    action, decided = numerics.ReluArgmax([numerics.Affine(w, b) for w, b in layers])(x)
    exact = _exact_relu_network(x, layers).argmax(axis=1)
    np.testing.assert_array_equal(action[decided], exact[decided])
    assert not decided[exact <= 1].any()


def test_relu_argmax_decides_most_rows_of_a_generic_network():
    rng = np.random.default_rng(0)
    sizes = [8, 256, 256, 4]
    layers = [
        (
            (rng.standard_normal((m, k)) / np.sqrt(k)).astype(np.float32),
            rng.standard_normal(m).astype(np.float32),
        )
        for k, m in zip(sizes[:-1], sizes[1:], strict=True)
    ]
    x = rng.standard_normal((1000, 8)).astype(np.float32)
    action, decided = numerics.ReluArgmax([numerics.Affine(w, b) for w, b in layers])(x)
    np.testing.assert_array_equal(action, _exact_relu_network(x, layers).argmax(axis=1))
    assert decided.mean() > 0.99


def test_linear_broadcasts_inputs_over_members():
    rng = np.random.default_rng(3)
    x = integer_valued(rng, (300, 20), 10, 5)
    w = integer_valued(rng, (4, 30, 20), 10, 5)
    b = integer_valued(rng, (4, 1, 30), 10, 5)
    got = numerics.linear(x, w, b)
    assert got.shape == (4, 300, 30)
    for member in range(4):
        np.testing.assert_array_equal(got[member], numerics.linear(x, w[member], b[member, 0]))
    np.testing.assert_array_equal(got, exact_integer_linear(x, w, b, 5))


def test_linear_and_affine_zero_results_are_positive_zero():
    # −0 products (0 × negative), and a tiny negative exact sum that rounds to zero.
    x = np.array([[0.0, 0.0], [2.0**-100, 0.0]], np.float32)
    w = np.array([[-1.0, -2.0], [-(2.0**-100), 1.0]], np.float32)
    out = numerics.linear(x, w)
    zeros = np.array([out[0, 0], out[0, 1], out[1, 1]])  # out[1, 0] = −2^-100
    assert (zeros == 0).all()
    assert not np.signbit(zeros).any()
    assert out[1, 0] == np.float32(-(2.0**-100))
    np.testing.assert_array_equal(
        numerics.Affine(w, np.zeros(2, np.float32))(x).view(np.uint32), out.view(np.uint32)
    )


def test_linear_and_affine_overflowing_magnitude_take_the_exact_path():
    # |x|·|w| overflows float32 in the bound's product, yet the exact sum is small.
    x = np.array([[3e38, 3e38, 1.0]], np.float32)
    w = np.array([[1.0, -1.0, 0.5], [2.0, -2.0, 0.25]], np.float32)
    np.testing.assert_array_equal(numerics.linear(x, w), np.array([[0.5, 0.25]], np.float32))
    affine = numerics.Affine(w, np.zeros(2, np.float32))
    np.testing.assert_array_equal(affine(x), np.array([[0.5, 0.25]], np.float32))


def _index_order_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The definition of numerics.matmul: ((a_0 b_0 + a_1 b_1) + …) in index order."""
    out = a[..., 0, None] * b[0]
    for j in range(1, a.shape[-1]):
        out = out + a[..., j, None] * b[j]
    return out


@pytest.mark.parametrize(
    ("a_shape", "b_shape"),
    [((469, 8, 32), (32, 16)), ((3000, 56), (56, 56)), ((2, 5), (5, 7)), ((4000, 8), (8,))],
)
def test_matmul_sums_in_index_order_in_either_layout(a_shape, b_shape):
    rng = np.random.default_rng(0)
    a = rng.standard_normal(a_shape) * np.logspace(-8, 8, a_shape[-1])
    b = rng.standard_normal(b_shape)
    b2 = b[:, None] if b.ndim == 1 else b
    expected = _index_order_matmul(a, b2)
    got = numerics.matmul(a, b)
    assert got.flags.c_contiguous
    np.testing.assert_array_equal(got, expected[..., 0] if b.ndim == 1 else expected)
