"""The small torch toolkit of the neural detectors: an ensemble MLP, its training loop, devices.

Imported only by the torch detectors (`pedm`, `autoencoder`, `ensemble_disagreement`), never by
the package `__init__`, so numpy-only detectors start without torch.

An ensemble of M members is one module whose weights carry a leading member axis, so all members
train and predict in one batched matrix product (a single network is M = 1). A fitted detector
keeps the weights as numpy arrays (`EnsembleWeights`): pickles are device-free and
byte-reproducible, and scoring rebuilds a module without touching the detector.

Reproducibility: weights are initialised and data orders drawn from a `torch.Generator` seeded
with the detector's seed; nothing reads the global torch RNG. On one machine and device the same
seed gives the same weights bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from oodrl.core.detector import BaseDetector
from oodrl.validation import Interval, Options
from oodrl.validation import Sequence as SequenceOf

DEVICES = ("auto", "cpu", "cuda")

#: Rows per forward pass when predicting, to bound memory on long score batches.
PREDICT_CHUNK = 8192


def resolve_device(device: str) -> torch.device:
    """'auto' → CUDA when available, else CPU."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class EnsembleMLP(nn.Module):
    """M independent MLPs (SiLU between layers) evaluated together on inputs of shape (M, B, in)."""

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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.weights) - 1
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = torch.baddbmm(bias, x, weight)
            if index < last:
                x = nn.functional.silu(x)
        return x


@dataclass(frozen=True)
class EnsembleWeights:
    """The fitted weights of an `EnsembleMLP` as numpy arrays (what a detector stores)."""

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, model: EnsembleMLP) -> EnsembleWeights:
        def arrays(params: nn.ParameterList) -> tuple[np.ndarray, ...]:
            return tuple(p.detach().cpu().numpy().copy() for p in params)

        return cls(arrays(model.weights), arrays(model.biases))

    def module(self, device: torch.device) -> EnsembleMLP:
        """A fresh module holding copies of these weights on `device`."""
        n_members, in_dim, _ = self.weights[0].shape
        out_dim = self.weights[-1].shape[2]
        hidden = [w.shape[2] for w in self.weights[:-1]]
        # A private generator for the throwaway initialisation: the global RNG stays untouched.
        model = EnsembleMLP(n_members, in_dim, out_dim, hidden, torch.Generator())
        with torch.no_grad():
            for param, array in zip(
                [*model.weights, *model.biases], [*self.weights, *self.biases], strict=True
            ):
                param.copy_(torch.from_numpy(array))
        return model.to(device).eval()


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


@dataclass(frozen=True)
class TrainSettings:
    """Optimisation settings shared by the neural detectors (Adam, a fixed number of epochs)."""

    epochs: int
    batch_size: int
    lr: float
    device: str


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
    return EnsembleWeights.of(model)


def chunked_scores(
    weights: EnsembleWeights,
    inputs: np.ndarray,
    device: str,
    reduce: Callable[[torch.Tensor, slice], torch.Tensor],
) -> np.ndarray:
    """Per-row scores (N,) float64 from every member's outputs, computed chunk by chunk.

    `reduce(outputs, rows)` gets the (M, n, out) float64 outputs of all members on the inputs
    `inputs[rows]` and returns their (n,) scores; chunking bounds memory on long score batches.
    """
    target = resolve_device(device)
    model = weights.module(target)
    n_members = weights.weights[0].shape[0]
    scores = []
    with torch.inference_mode():
        for start in range(0, inputs.shape[0], PREDICT_CHUNK):
            rows = slice(start, start + PREDICT_CHUNK)
            x = torch.as_tensor(inputs[rows], dtype=torch.float32, device=target)
            outputs = model(x.expand(n_members, -1, -1)).double()
            scores.append(reduce(outputs, rows).cpu().numpy())
    return np.concatenate(scores)


def member_mse(output: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error of each member, summed over members."""
    return ((output - target) ** 2).mean(dim=(1, 2)).sum()


class TorchDetector(BaseDetector):
    """Parameters and helpers every neural detector shares; subclasses declare the defaults.

    `hidden_sizes` (list of ints), `epochs`, `batch_size`, `lr` (Adam) and `device`
    ("auto" = CUDA when available, else CPU) are validated here once for all of them.
    """

    uses_torch: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "hidden_sizes": [SequenceOf(Interval(int, 1, None))],
        "epochs": [Interval(int, 1, None)],
        "batch_size": [Interval(int, 1, None)],
        "lr": [Interval(float, 0, None, closed="neither")],
        "device": [Options(DEVICES)],
    }

    hidden_sizes: Sequence[int]
    epochs: int
    batch_size: int
    lr: float
    device: str

    def _train_settings(self) -> TrainSettings:
        return TrainSettings(self.epochs, self.batch_size, self.lr, self.device)

    def _generator(self) -> torch.Generator:
        """A CPU generator seeded from `seed`: initial weights, bootstrap and data order."""
        return torch.Generator().manual_seed(self.seed)
