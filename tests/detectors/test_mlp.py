"""The numpy ensemble MLP: hand-written gradients match torch autograd, Adam matches torch's,
training is seeded and learns.

That fitted detectors are the same bytes under every SIMD kernel is tested in
test_machine_independence.py.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from oodrl.detectors import mlp

#: Each product and transcendental is rounded once to float32 (32 bits for exp, softplus);
#: torch computes the reference in float64.
GRADIENT_RTOL = 1e-4
GRADIENT_ATOL = 1e-6


def torch_loss(
    weights: mlp.EnsembleWeights, inputs: np.ndarray, targets: np.ndarray, loss: str
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The float64 torch loss of the same network, and its parameters (for autograd)."""
    params = [
        torch.tensor(p, dtype=torch.float64, requires_grad=True)
        for p in (*weights.weights, *weights.biases)
    ]
    n_layers = len(weights.weights)
    x = torch.as_tensor(inputs, dtype=torch.float64)
    for index in range(n_layers):
        x = x @ params[index].transpose(-1, -2) + params[n_layers + index]
        if weights.relu[index]:
            x = torch.relu(x)
    y = torch.as_tensor(targets, dtype=torch.float64)
    if loss == "mse":
        value = ((x - y) ** 2).mean(dim=(1, 2)).sum()
    else:
        mean, raw = x.chunk(2, dim=-1)
        softplus = torch.nn.functional.softplus
        logvar = mlp.MAX_LOGVAR - softplus(mlp.MAX_LOGVAR - raw)
        logvar = mlp.MIN_LOGVAR + softplus(logvar - mlp.MIN_LOGVAR)
        value = (0.5 * ((y - mean) ** 2 * torch.exp(-logvar) + logvar)).mean(dim=(1, 2)).sum()
    return value, params


@pytest.mark.parametrize(
    ("loss", "linear_layers"),
    [("mse", ()), ("gaussian_nll", ()), ("mse", (1,))],
    ids=["mse", "gaussian_nll", "linear-bottleneck"],
)
def test_gradients_match_torch_autograd(loss, linear_layers):
    rng = np.random.default_rng(0)
    n_out = 4 if loss == "mse" else 8
    weights = mlp.init_weights(3, (5, 16, 2, 16, n_out), rng, linear_layers)
    inputs = rng.standard_normal((3, 40, 5)).astype(np.float32)
    # Targets far from the initial outputs push some log-variances into the soft bounds.
    targets = (3 * rng.standard_normal((3, 40, 4))).astype(np.float32)
    loss_fn = {"mse": mlp.mse, "gaussian_nll": mlp.gaussian_nll}[loss]
    value, grads = mlp.gradients(weights, inputs, targets, loss_fn)
    expected_value, params = torch_loss(weights, inputs, targets, loss)
    expected_value.backward()
    assert value == pytest.approx(expected_value.item(), rel=1e-5)
    for got, param in zip((*grads.weights, *grads.biases), params, strict=True):
        assert got.dtype == np.float32 and got.shape == param.shape
        np.testing.assert_allclose(got, param.grad.numpy(), rtol=GRADIENT_RTOL, atol=GRADIENT_ATOL)


def test_gaussian_nll_gradient_matches_finite_differences_in_the_soft_bounds():
    # Raw log-variances from deep below the lower bound to far above the upper one.
    raw = np.linspace(-16.0, 8.0, 25)
    outputs = np.stack([np.full_like(raw, 0.3), raw], axis=-1)[None].astype(np.float32)
    targets = np.full((1, raw.size, 1), -0.5, dtype=np.float32)
    _, grad = mlp.gaussian_nll(outputs, targets)

    def total(o: np.ndarray) -> float:
        mean, logvar = mlp.gaussian_mean_and_logvar(o)
        return float((0.5 * ((targets - mean) ** 2 / np.exp(logvar) + logvar)).sum()) / raw.size

    step = 1e-3
    shift = np.zeros_like(outputs, dtype=np.float64)
    numeric = np.empty(raw.size)
    for row in range(raw.size):
        shift[0, row, 1] = step
        numeric[row] = (total(outputs + shift) - total(outputs - shift)) / (2 * step)
        shift[0, row, 1] = 0
    np.testing.assert_allclose(grad[0, :, 1], numeric, rtol=1e-3, atol=1e-7)


def test_adam_matches_torch():
    rng = np.random.default_rng(0)
    start = rng.standard_normal((3, 4)).astype(np.float32)
    grads = rng.standard_normal((20, 3, 4)).astype(np.float32)
    param = start.copy()
    optimiser = mlp.Adam([param], lr=1e-2)
    reference = torch.tensor(start, requires_grad=True)
    torch_optimiser = torch.optim.Adam([reference], lr=1e-2)
    for grad in grads:
        optimiser.step([param], [grad])
        reference.grad = torch.from_numpy(grad)
        torch_optimiser.step()
    # Same update in float32; torch's lerp and pow round a little differently.
    np.testing.assert_allclose(param, reference.detach().numpy(), rtol=1e-5, atol=1e-6)


def test_relu_follows_every_hidden_layer_but_the_linear_ones():
    rng = np.random.default_rng(0)
    assert mlp.init_weights(1, (4, 8, 8, 2), rng).relu == (True, True, False)
    assert mlp.init_weights(1, (4, 8, 2, 8, 4), rng, (1,)).relu == (True, False, True, False)


def test_initial_weights_follow_torch_linear_default():
    weights = mlp.init_weights(4, (9, 25, 3), np.random.default_rng(0))
    assert [w.shape for w in weights.weights] == [(4, 25, 9), (4, 3, 25)]
    assert [b.shape for b in weights.biases] == [(4, 1, 25), (4, 1, 3)]
    for weight, bias, fan_in in zip(weights.weights, weights.biases, (9, 25), strict=True):
        assert weight.dtype == bias.dtype == np.float32
        assert np.abs(weight).max() <= 1 / np.sqrt(fan_in)
        assert np.abs(bias).max() <= 1 / np.sqrt(fan_in)
        # Spread over the whole interval, and members differ.
        assert np.abs(weight).max() > 0.9 / np.sqrt(fan_in)
        assert not np.array_equal(weight[0], weight[1])


def test_member_indices():
    rng = np.random.default_rng(0)
    resampled = mlp.member_indices(3, 50, True, rng)
    assert resampled.shape == (3, 50) and resampled.min() >= 0 and resampled.max() < 50
    assert len(np.unique(resampled[0])) < 50  # with replacement
    assert not np.array_equal(resampled[0], resampled[1])
    np.testing.assert_array_equal(mlp.member_indices(2, 7, False, rng), [np.arange(7)] * 2)


def test_members_are_independent():
    weights = mlp.init_weights(3, (4, 8, 8, 2), np.random.default_rng(0))
    x = np.random.default_rng(1).standard_normal((5, 4))
    member = mlp.EnsembleWeights(
        tuple(w[1:2] for w in weights.weights),
        tuple(b[1:2] for b in weights.biases),
        weights.relu,
    )
    np.testing.assert_array_equal(member.predict(x)[0], weights.predict(x)[1])


@pytest.mark.parametrize("loss", ["mse", "gaussian_nll"])
def test_training_is_seeded_and_reduces_the_loss(loss):
    rng = np.random.default_rng(0)
    inputs = rng.standard_normal((300, 3))
    targets = np.tanh(inputs @ rng.standard_normal((3, 2)))
    n_out = 2 if loss == "mse" else 4
    loss_fn = {"mse": mlp.mse, "gaussian_nll": mlp.gaussian_nll}[loss]
    settings = mlp.OptimiserSettings(epochs=15, batch_size=32, lr=1e-2)

    def fit(seed: int) -> tuple[mlp.EnsembleWeights, list[float]]:
        generator = np.random.default_rng(seed)
        initial = mlp.init_weights(2, (3, 16, n_out), generator)
        indices = mlp.member_indices(2, 300, True, generator)
        return mlp.train(initial, inputs, targets, loss_fn, settings, indices, generator)

    (first, losses), (second, _), (other, _) = fit(0), fit(0), fit(1)
    pairs = zip((*first.weights, *first.biases), (*second.weights, *second.biases), strict=True)
    for a, b in pairs:
        assert a.tobytes() == b.tobytes()
    assert not np.array_equal(first.weights[0], other.weights[0])
    assert len(losses) == settings.epochs
    members = np.broadcast_to(inputs.astype(np.float32), (2, *inputs.shape))
    untrained = mlp.init_weights(2, (3, 16, n_out), np.random.default_rng(0))
    final = loss_fn(first.predict(members), np.broadcast_to(targets, (2, *targets.shape)))[0]
    initial = loss_fn(untrained.predict(members), np.broadcast_to(targets, (2, *targets.shape)))
    if loss == "mse":
        assert final < 0.05 * initial[0]
    else:  # The NLL is unbounded below: it must fall far, to well under zero.
        assert final < min(initial[0] - 3, -2)
    assert losses[-1] < losses[0]


def test_each_member_may_train_on_its_own_targets():
    rng = np.random.default_rng(0)
    inputs = rng.standard_normal((60, 3))
    targets = rng.standard_normal((60, 1))
    settings = mlp.OptimiserSettings(epochs=3, batch_size=16, lr=1e-2)

    def fit(member_targets: np.ndarray) -> mlp.EnsembleWeights:
        generator = np.random.default_rng(1)
        initial = mlp.init_weights(2, (3, 8, 1), generator)
        indices = mlp.member_indices(2, 60, True, generator)
        return mlp.train(initial, inputs, member_targets, mlp.mse, settings, indices, generator)[0]

    shared = fit(targets)
    # The same targets given to each member train the same bits as shared ones...
    same = fit(np.stack([targets, targets]))
    for a, b in zip((*shared.weights, *shared.biases), (*same.weights, *same.biases), strict=True):
        assert a.tobytes() == b.tobytes()
    # ...and a member's own targets change that member alone.
    own = fit(np.stack([targets, targets + 1.0]))
    np.testing.assert_array_equal(own.weights[0][0], shared.weights[0][0])
    assert not np.array_equal(own.weights[0][1], shared.weights[0][1])
