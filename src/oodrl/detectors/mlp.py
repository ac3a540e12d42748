"""The neural detectors' ensemble MLP and its training, in numpy, the same bytes on every machine.

SPEC §14: a fitted detector must not depend on which SIMD kernel a math library picks. Every
matrix product here, forward and backward, is `numerics.linear` (correctly rounded float32);
the nonlinearity is ReLU (a comparison, exact, unlike SiLU's exp); the losses' exp and softplus
are the certified `numerics` functions; everything else is elementwise IEEE arithmetic
(+ − × ÷ √), which every CPU rounds alike. The backward passes are written out by hand.

An ensemble of M members keeps a leading member axis on every array, so all members train in
the same batched products (a single network is M = 1). Layer l of member m maps
x ↦ x W_lᵀ + b_l, with `weights[l]` (M, out, in) and `biases[l]` (M, 1, out), float32.

Reproducibility: initial weights, bootstrap resamples and minibatch orders all come from one
`np.random.default_rng(seed)`, whose streams are integer arithmetic and machine-independent;
nothing reads numpy's global RNG.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from oodrl import numerics

#: Bounds of a Gaussian head's log-variance (standardised units), softly enforced as in PETS.
MAX_LOGVAR = 2.0
MIN_LOGVAR = -10.0

#: Adam's constants (torch's defaults), applied in float32.
ADAM_BETA1 = np.float32(0.9)
ADAM_BETA2 = np.float32(0.999)
ADAM_EPS = np.float32(1e-8)

#: `loss(outputs, targets)` → (the loss, its float32 gradient with respect to `outputs`).
Loss = Callable[[np.ndarray, np.ndarray], tuple[float, np.ndarray]]


@dataclass(frozen=True)
class EnsembleWeights:
    """The weights of an M-member MLP ensemble as float32 numpy arrays (what a detector stores).

    Layer l has `weights[l]` of shape (M, out, in) and `biases[l]` of shape (M, 1, out); ReLU
    follows layer l where `relu[l]` (every hidden layer but a linear bottleneck, never the last).
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    relu: tuple[bool, ...]

    @property
    def n_members(self) -> int:
        return self.weights[0].shape[0]

    def activations(self, inputs: np.ndarray) -> list[np.ndarray]:
        """Every layer's float32 input and, last, the output (M, B, out).

        Inputs (B, in) go to every member; (M, B, in) give each member its own rows.
        """
        x = np.asarray(inputs, dtype=np.float32)
        layers = [x]
        for weight, bias, relu in zip(self.weights, self.biases, self.relu, strict=True):
            x = numerics.linear(x, weight, bias)
            if relu:
                x = numerics.relu(x)
            layers.append(x)
        return layers

    def predict(self, inputs: np.ndarray) -> np.ndarray:
        """Every member's float32 outputs (M, B, out) on inputs (B, in), or (M, B, in)."""
        return self.activations(inputs)[-1]


def init_weights(
    n_members: int,
    sizes: Sequence[int],
    rng: np.random.Generator,
    linear_layers: Sequence[int] = (),
) -> EnsembleWeights:
    """Layers of `sizes` (input, hidden…, output) drawn as torch's nn.Linear default does:
    weights and biases U(−1/√fan_in, 1/√fan_in), every member independently.

    ReLU follows every hidden layer except those in `linear_layers` (e.g. a bottleneck).
    """
    n_layers = len(sizes) - 1
    relu = tuple(index < n_layers - 1 and index not in linear_layers for index in range(n_layers))
    weights, biases = [], []
    for n_in, n_out in zip(sizes[:-1], sizes[1:], strict=True):
        bound = 1.0 / math.sqrt(n_in)
        weights.append(rng.uniform(-bound, bound, (n_members, n_out, n_in)).astype(np.float32))
        biases.append(rng.uniform(-bound, bound, (n_members, 1, n_out)).astype(np.float32))
    return EnsembleWeights(tuple(weights), tuple(biases), relu)


def _softplus_slope(x: np.ndarray) -> np.ndarray:
    """d softplus(x) / dx = σ(x) = 1 / (1 + e^−x); e^−x = inf gives the limit 0."""
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + numerics.exp(-x))


def gaussian_mean_and_logvar(outputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split (…, 2d) Gaussian-head outputs into the mean and the softly bounded log-variance
    (float64): logvar = MIN + softplus(MAX − softplus(MAX − raw) − MIN)."""
    half = outputs.shape[-1] // 2
    mean, raw = outputs[..., :half], np.asarray(outputs[..., half:], dtype=np.float64)
    return mean, _soft_bounds(raw)[1]


def _soft_bounds(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MAX − softplus(MAX − raw) (bounded above) and the log-variance bounded on both sides."""
    bounded_above = MAX_LOGVAR - numerics.softplus(MAX_LOGVAR - raw)
    return bounded_above, MIN_LOGVAR + numerics.softplus(bounded_above - MIN_LOGVAR)


def _logvar_slope(raw: np.ndarray, bounded_above: np.ndarray) -> np.ndarray:
    """d logvar / d raw of `gaussian_mean_and_logvar`'s soft bounds (chain rule, float64), given
    the `bounded_above` of `_soft_bounds(raw)`."""
    return _softplus_slope(bounded_above - MIN_LOGVAR) * _softplus_slope(MAX_LOGVAR - raw)


def mse(outputs: np.ndarray, targets: np.ndarray) -> tuple[float, np.ndarray]:
    """Mean squared error of each member (over its rows and outputs), summed over members."""
    # float32 − float32 is exact in float64; one rounding to float32 at the end.
    diff = outputs.astype(np.float64) - targets
    count = diff.shape[-2] * diff.shape[-1]
    value = float((diff * diff).sum(axis=-1).sum(axis=-1).sum()) / count
    return value, (diff * (2.0 / count)).astype(np.float32)


def gaussian_nll(outputs: np.ndarray, targets: np.ndarray) -> tuple[float, np.ndarray]:
    """Gaussian negative log-likelihood (up to a constant) of each member, summed over members:
    ½ [(y − μ)² e^−logvar + logvar], averaged over each member's rows and coordinates."""
    outputs = outputs.astype(np.float64)
    half = outputs.shape[-1] // 2
    mean, raw = outputs[..., :half], outputs[..., half:]
    bounded_above, logvar = _soft_bounds(raw)
    precision = numerics.exp(-logvar)
    residual = targets - mean
    weighted = residual * residual * precision
    count = mean.shape[-2] * mean.shape[-1]
    value = float((0.5 * (weighted + logvar)).sum(axis=-1).sum(axis=-1).sum()) / count
    grad_mean = -residual * precision / count
    grad_logvar = 0.5 * (1.0 - weighted) / count
    grad_raw = grad_logvar * _logvar_slope(raw, bounded_above)
    return value, np.concatenate([grad_mean, grad_raw], axis=-1).astype(np.float32)


def gradients(
    weights: EnsembleWeights, inputs: np.ndarray, targets: np.ndarray, loss: Loss
) -> tuple[float, EnsembleWeights]:
    """The loss on (M, B, in) inputs and its gradient with respect to every weight and bias
    (as an `EnsembleWeights` without `relu`)."""
    layers = weights.activations(inputs)
    value, grad = loss(layers[-1], targets)
    grad_weights: list[np.ndarray] = []
    grad_biases: list[np.ndarray] = []
    for index in reversed(range(len(weights.weights))):
        grad_t = np.swapaxes(grad, -1, -2)
        # dW = dYᵀ X and db = dYᵀ 1, correctly rounded like the forward products: one product
        # with [X, 1] (each entry is the same exact sum, so the same float32, as two products).
        layer = layers[index]
        augmented = np.concatenate([layer, np.ones((*layer.shape[:-1], 1), np.float32)], -1)
        both = numerics.linear(grad_t, np.swapaxes(augmented, -1, -2))  # (M, out, in + 1)
        grad_weights.append(both[..., :-1])
        grad_biases.append(np.ascontiguousarray(np.swapaxes(both[..., -1:], -1, -2)))
        if index > 0:
            grad = numerics.linear(grad, np.swapaxes(weights.weights[index], -1, -2))
            if weights.relu[index - 1]:
                # ReLU passes the gradient where its input was positive (its output is > 0).
                grad = np.where(layers[index] > 0, grad, np.float32(0))
    grads = EnsembleWeights(tuple(reversed(grad_weights)), tuple(reversed(grad_biases)), ())
    return value, grads


class Adam:
    """Adam with torch's update and bias correction, in float32 elementwise arithmetic.

    β^t is kept as a running float64 product (not `**`, whose libm may differ per CPU).
    """

    def __init__(self, params: Sequence[np.ndarray], lr: float) -> None:
        self.lr = lr
        self.first = [np.zeros_like(p) for p in params]
        self.second = [np.zeros_like(p) for p in params]
        self.beta1_power = 1.0
        self.beta2_power = 1.0

    def step(self, params: Sequence[np.ndarray], grads: Sequence[np.ndarray]) -> None:
        """Update `params` in place from their gradients."""
        self.beta1_power *= float(ADAM_BETA1)
        self.beta2_power *= float(ADAM_BETA2)
        step_size = np.float32(self.lr / (1.0 - self.beta1_power))
        correction2_sqrt = np.float32(math.sqrt(1.0 - self.beta2_power))
        for param, grad, first, second in zip(params, grads, self.first, self.second, strict=True):
            first *= ADAM_BETA1
            first += (np.float32(1) - ADAM_BETA1) * grad
            second *= ADAM_BETA2
            second += (np.float32(1) - ADAM_BETA2) * (grad * grad)
            denominator = np.sqrt(second) / correction2_sqrt + ADAM_EPS
            param -= step_size * (first / denominator)


@dataclass(frozen=True)
class OptimiserSettings:
    """Optimisation settings shared by the neural detectors (Adam, a fixed number of epochs)."""

    epochs: int
    batch_size: int
    lr: float


def member_indices(
    n_members: int, n_samples: int, bootstrap: bool, rng: np.random.Generator
) -> np.ndarray:
    """(M, N) row indices each member trains on: a bootstrap resample each, or all rows."""
    if bootstrap:
        return rng.integers(n_samples, size=(n_members, n_samples))
    return np.tile(np.arange(n_samples), (n_members, 1))


def train(
    weights: EnsembleWeights,
    inputs: np.ndarray,
    targets: np.ndarray,
    loss: Loss,
    settings: OptimiserSettings,
    indices: np.ndarray,
    rng: np.random.Generator,
) -> tuple[EnsembleWeights, list[float]]:
    """Fit the members from `weights`, member m on rows `indices[m]`, with Adam.

    `targets` (N, out) are every member's, or (M, N, out) each member's own (fitted Q
    evaluation: each member regresses on its own bootstrapped values). Each epoch visits every
    member's rows in its own random order, in minibatches of `settings.batch_size` (the last one
    smaller). Returns the trained weights and each epoch's mean minibatch loss (summed over
    members).
    """
    x = np.asarray(inputs, dtype=np.float32)
    y = np.asarray(targets, dtype=np.float32)
    params = tuple(p.copy() for p in (*weights.weights, *weights.biases))
    n_layers = len(weights.weights)
    optimiser = Adam(params, settings.lr)
    epoch_losses = []
    for _ in range(settings.epochs):
        order = rng.permuted(indices, axis=1)
        batch_losses = []
        for start in range(0, order.shape[1], settings.batch_size):
            batch = order[:, start : start + settings.batch_size]
            current = EnsembleWeights(params[:n_layers], params[n_layers:], weights.relu)
            batch_targets = y[batch] if y.ndim == 2 else np.take_along_axis(y, batch[..., None], 1)
            value, grads = gradients(current, x[batch], batch_targets, loss)
            optimiser.step(params, [*grads.weights, *grads.biases])
            batch_losses.append(value)
        epoch_losses.append(math.fsum(batch_losses) / len(batch_losses))
    return EnsembleWeights(params[:n_layers], params[n_layers:], weights.relu), epoch_losses
