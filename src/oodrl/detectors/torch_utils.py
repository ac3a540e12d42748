"""The small torch toolkit of the neural detectors: an ensemble MLP, its training loop, devices.

Imported only inside the neural detectors' `_fit` (their modules, parameters, pickles and
scoring are torch-free, see `oodrl.detectors.neural`), so no stage imports torch unless it fits
a neural detector.

An ensemble of M members is one module whose weights carry a leading member axis, so all members
train in one batched matrix product (a single network is M = 1). A fitted detector keeps the
weights as numpy arrays (`EnsembleWeights`), whose `predict` is this module's forward pass in
numpy: scoring needs no torch.

Reproducibility: weights are initialised and data orders drawn from a `torch.Generator` seeded
with the detector's seed; nothing reads the global torch RNG. On one machine and device the same
seed gives the same weights bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import torch
from torch import nn

from oodrl.detectors.neural import EnsembleWeights, TrainSettings, gaussian_mean_and_logvar


def resolve_device(device: str) -> torch.device:
    """'auto' → CUDA when available, else CPU."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def seeded_generator(seed: int) -> torch.Generator:
    """A CPU generator seeded from a detector's `seed`: initial weights, bootstrap, data order."""
    return torch.Generator().manual_seed(seed)


class EnsembleMLP(nn.Module):
    """M independent MLPs (SiLU between layers) evaluated together on inputs of shape (M, B, in).

    `EnsembleWeights.predict` is the same forward pass in numpy; keep the two in step.
    """

    def __init__(
        self,
        n_members: int,
        in_dim: int,
        out_dim: int,
        hidden_sizes: Sequence[int],
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        sizes = (in_dim, *hidden_sizes, out_dim)
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for n_in, n_out in zip(sizes[:-1], sizes[1:], strict=True):
            # PyTorch's nn.Linear default: U(−1/√fan_in, 1/√fan_in), drawn from our generator.
            bound = 1.0 / math.sqrt(n_in)
            weight = (torch.rand(n_members, n_in, n_out, generator=generator) * 2 - 1) * bound
            bias = (torch.rand(n_members, 1, n_out, generator=generator) * 2 - 1) * bound
            self.weights.append(nn.Parameter(weight))
            self.biases.append(nn.Parameter(bias))

    def numpy_weights(self) -> EnsembleWeights:
        """Copies of the weights as numpy arrays (what a fitted detector stores)."""

        def arrays(params: nn.ParameterList) -> tuple[np.ndarray, ...]:
            return tuple(p.detach().cpu().numpy().copy() for p in params)

        return EnsembleWeights(arrays(self.weights), arrays(self.biases))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.weights) - 1
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = torch.baddbmm(bias, x, weight)
            if index < last:
                x = nn.functional.silu(x)
        return x


def member_indices(
    n_members: int, n_samples: int, bootstrap: bool, generator: torch.Generator
) -> torch.Tensor:
    """(M, N) row indices each member trains on: a bootstrap resample each, or all rows."""
    if bootstrap:
        return torch.randint(n_samples, (n_members, n_samples), generator=generator)
    return torch.arange(n_samples).expand(n_members, n_samples)


def _minibatches(
    indices: torch.Tensor, batch_size: int, generator: torch.Generator
) -> Iterator[torch.Tensor]:
    """One epoch: every member's rows in its own random order, in (M, B) index batches."""
    order = torch.argsort(torch.rand(indices.shape, generator=generator), dim=1)
    shuffled = torch.gather(indices, 1, order)
    for start in range(0, indices.shape[1], batch_size):
        yield shuffled[:, start : start + batch_size]


def train_ensemble(
    model: EnsembleMLP,
    inputs: np.ndarray,
    targets: np.ndarray,
    loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    settings: TrainSettings,
    indices: torch.Tensor,
    generator: torch.Generator,
) -> EnsembleWeights:
    """Fit `model` (M members) on rows `indices[m]` for member m; return its weights.

    `loss_fn(output, target)` gets (M, B, out) outputs and (M, B, target_dim) targets and returns
    a scalar: the members' losses summed, so each member follows its own gradient.
    """
    device = resolve_device(settings.device)
    model = model.to(device).train()
    x = torch.as_tensor(inputs, dtype=torch.float32, device=device)
    y = torch.as_tensor(targets, dtype=torch.float32, device=device)
    optimiser = torch.optim.Adam(model.parameters(), lr=settings.lr)
    for _ in range(settings.epochs):
        for batch in _minibatches(indices, settings.batch_size, generator):
            batch = batch.to(device)
            optimiser.zero_grad(set_to_none=True)
            loss = loss_fn(model(x[batch]), y[batch])
            loss.backward()
            optimiser.step()
    return model.numpy_weights()


def member_mse(output: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error of each member, summed over members."""
    return ((output - target) ** 2).mean(dim=(1, 2)).sum()


def member_gaussian_nll(output: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Gaussian negative log-likelihood (up to a constant) of each member, summed over members."""
    mean, logvar = gaussian_mean_and_logvar(output, nn.functional.softplus)
    nll = 0.5 * ((target - mean) ** 2 * torch.exp(-logvar) + logvar)
    return nll.mean(dim=(1, 2)).sum()
