"""Q-networks with NoisyNet layers (Fortunato et al. 2018, factorised Gaussian noise).

A noisy layer computes ``y = (W_mu + W_sigma ∘ ε_out ε_inᵀ) x + b_mu + b_sigma ∘ ε_out`` with
``ε = f(z)``, ``f(z) = sign(z) √|z|``, ``z ~ N(0, 1)``. Because the noise is factorised,
``(W_sigma ∘ ε_out ε_inᵀ) x = ε_out ∘ (W_sigma (ε_in ∘ x))``: every row of a batch can carry its
own noise sample at the cost of one extra matrix product, without forming a weight per row.
Noise is therefore passed to ``forward`` explicitly:

- ``None`` — noise off: the mean network (greedy evaluation);
- ``(ε_in, ε_out)`` of shapes ``(in,)`` and ``(out,)`` — one sample shared by the whole batch
  (training);
- ``(ε_in, ε_out)`` of shapes ``(n, in)`` and ``(n, out)`` — one sample per row (noisy evaluation
  with one random stream per environment).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

LayerNoise = tuple[torch.Tensor, torch.Tensor]
"""``(ε_in, ε_out)`` for one noisy layer, already transformed by ``f``."""


def scale_noise(z: torch.Tensor) -> torch.Tensor:
    """The factorised-noise transform ``f(z) = sign(z) √|z|``."""
    return z.sign() * z.abs().sqrt()


class NoisyLinear(nn.Module):
    """Linear layer with learnable factorised Gaussian noise; ``sigma0`` scales the initial σ."""

    def __init__(self, in_features: int, out_features: int, sigma0: float = 0.5) -> None:
        super().__init__()
        self.in_features = in_features
        self.out_features = out_features
        self.sigma0 = sigma0
        self.weight_mu = nn.Parameter(torch.empty(out_features, in_features))
        self.weight_sigma = nn.Parameter(torch.empty(out_features, in_features))
        self.bias_mu = nn.Parameter(torch.empty(out_features))
        self.bias_sigma = nn.Parameter(torch.empty(out_features))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        bound = 1.0 / math.sqrt(self.in_features)
        nn.init.uniform_(self.weight_mu, -bound, bound)
        nn.init.uniform_(self.bias_mu, -bound, bound)
        nn.init.constant_(self.weight_sigma, self.sigma0 * bound)
        nn.init.constant_(self.bias_sigma, self.sigma0 * bound)

    def forward(self, x: torch.Tensor, noise: LayerNoise | None = None) -> torch.Tensor:
        if noise is None:
            return nn.functional.linear(x, self.weight_mu, self.bias_mu)
        eps_in, eps_out = noise
        if eps_in.ndim == 1:
            # One shared sample: forming the noisy weight is cheaper than a second matrix product.
            weight = self.weight_mu + self.weight_sigma * torch.outer(eps_out, eps_in)
            return nn.functional.linear(x, weight, self.bias_mu + self.bias_sigma * eps_out)
        perturbation = nn.functional.linear(x * eps_in, self.weight_sigma) + self.bias_sigma
        return nn.functional.linear(x, self.weight_mu, self.bias_mu) + eps_out * perturbation

    def extra_repr(self) -> str:
        return f"{self.in_features} -> {self.out_features}, sigma0={self.sigma0}"


class NoisyQNetwork(nn.Module):
    """MLP of noisy layers with ReLU between them, mapping a state to one Q-value per action."""

    def __init__(
        self,
        state_dim: int,
        n_actions: int,
        hidden_sizes: Sequence[int] = (256, 256),
        sigma0: float = 0.5,
    ) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.n_actions = n_actions
        self.hidden_sizes = tuple(int(h) for h in hidden_sizes)
        self.sigma0 = sigma0
        sizes = (state_dim, *self.hidden_sizes, n_actions)
        self.layers = nn.ModuleList(
            NoisyLinear(n_in, n_out, sigma0)
            for n_in, n_out in zip(sizes[:-1], sizes[1:], strict=True)
        )

    @property
    def noise_shapes(self) -> list[tuple[int, int]]:
        """``(in_features, out_features)`` of every noisy layer, in forward order."""
        return [(layer.in_features, layer.out_features) for layer in self.layers]

    def sample_noise(self, generator: torch.Generator | None = None) -> list[LayerNoise]:
        """One noise sample shared by a whole batch, drawn from ``generator``."""
        return [
            (
                scale_noise(torch.randn(n_in, generator=generator)),
                scale_noise(torch.randn(n_out, generator=generator)),
            )
            for n_in, n_out in self.noise_shapes
        ]

    def row_noise(self, rngs: Sequence[np.random.Generator]) -> list[LayerNoise]:
        """One noise sample per batch row; row ``i`` draws only from ``rngs[i]``.

        Each generator draws, layer by layer, ``ε_in`` then ``ε_out``, so what a row receives does
        not depend on the other rows of the batch.
        """
        total = sum(n_in + n_out for n_in, n_out in self.noise_shapes)
        z = np.stack([rng.standard_normal(total, dtype=np.float32) for rng in rngs])
        eps = scale_noise(torch.from_numpy(z))
        noise: list[LayerNoise] = []
        start = 0
        for n_in, n_out in self.noise_shapes:
            noise.append(
                (eps[:, start : start + n_in], eps[:, start + n_in : start + n_in + n_out])
            )
            start += n_in + n_out
        return noise

    def forward(self, x: torch.Tensor, noise: Sequence[LayerNoise] | None = None) -> torch.Tensor:
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = layer(x, None if noise is None else noise[i])
            if i < last:
                x = torch.relu(x)
        return x


def mlp(state_dim: int, n_actions: int, hidden_sizes: Sequence[int] = (64, 64)) -> nn.Sequential:
    """Plain Linear/ReLU MLP; its state_dict keys are ``0.weight``, ``0.bias``, ``2.weight``, …"""
    sizes = (state_dim, *(int(h) for h in hidden_sizes), n_actions)
    modules: list[nn.Module] = []
    for n_in, n_out in zip(sizes[:-1], sizes[1:], strict=True):
        modules += [nn.Linear(n_in, n_out), nn.ReLU()]
    return nn.Sequential(*modules[:-1])
