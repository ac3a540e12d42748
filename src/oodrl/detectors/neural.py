"""What the neural detectors (`pedm`, `autoencoder`, `ensemble_disagreement`) share, torch-free.

Every pipeline stage is a fresh process, and importing torch costs ~1.5 s, so only fitting uses
torch: the training code lives in `oodrl.detectors.torch_utils`, which a detector imports inside
`_fit` only. Fitted weights are stored as numpy arrays (`EnsembleWeights`) and scoring runs the
networks forward in numpy, so pickles are device-free and byte-reproducible, and building,
validating, loading and scoring a neural detector never import torch.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar, TypeVar

import numpy as np

from oodrl.core.detector import BaseDetector
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    ActionEncoding,
    Standardizer,
    increments,
    stacked,
    trajectory_features,
)
from oodrl.validation import Interval, Options
from oodrl.validation import Sequence as SequenceOf

DEVICES = ("auto", "cpu", "cuda")


#: Rows per forward pass when scoring: bounds memory on long score batches, and keeps a chunk's
#: temporaries small enough for the CPU caches (2048 scored fastest of 1024 to 8192, one thread).
PREDICT_CHUNK = 2048

#: Bounds of a Gaussian head's log-variance (standardised units), softly enforced as in PETS.
MAX_LOGVAR = 2.0
MIN_LOGVAR = -10.0

#: A numpy array (scoring) or a torch tensor (training): what `gaussian_mean_and_logvar` takes.
Array = TypeVar("Array")


@dataclass(frozen=True)
class EnsembleWeights:
    """The fitted weights of an M-member MLP ensemble as numpy arrays (what a detector stores).

    Layer l has `weights[l]` of shape (M, in, out) and `biases[l]` of shape (M, 1, out), float32.
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]

    def predict(self, inputs: np.ndarray) -> np.ndarray:
        """Every member's float32 outputs (M, B, out) on inputs (B, in), or (M, B, in).

        The numpy twin of `torch_utils.EnsembleMLP.forward`: x ← x W_l + b_l per member, SiLU
        between layers, in float32. Inputs of shape (B, in) go to every member.
        """
        x = np.asarray(inputs, dtype=np.float32)
        last = len(self.weights) - 1
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = np.matmul(x, weight)
            x += bias
            if index < last:
                _silu_inplace(x)
        return x


def _silu_inplace(x: np.ndarray) -> None:
    """x ← x·σ(x) = x / (1 + e^−x); where e^−x overflows to inf, x / inf is the limit −0."""
    denominator = np.negative(x)
    with np.errstate(over="ignore"):
        np.exp(denominator, out=denominator)
    denominator += 1
    x /= denominator


def chunked_scores(
    weights: EnsembleWeights,
    inputs: np.ndarray,
    reduce: Callable[[np.ndarray, slice], np.ndarray],
) -> np.ndarray:
    """Per-row scores (N,) float64 from every member's outputs, computed chunk by chunk.

    `reduce(outputs, rows)` gets the (M, n, out) float64 outputs of all members on the inputs
    `inputs[rows]` and returns their (n,) scores; chunking bounds memory on long score batches.
    """
    scores = []
    for start in range(0, inputs.shape[0], PREDICT_CHUNK):
        rows = slice(start, start + PREDICT_CHUNK)
        outputs = weights.predict(inputs[rows]).astype(np.float64)
        scores.append(reduce(outputs, rows))
    return np.concatenate(scores)


def _softplus(x: np.ndarray) -> np.ndarray:
    """log(1 + e^x), without overflow."""
    return np.logaddexp(0.0, x)


def gaussian_mean_and_logvar(
    outputs: Array, softplus: Callable[[Array], Array] = _softplus
) -> tuple[Array, Array]:
    """Split (…, 2d) Gaussian-head outputs into the mean and the softly bounded log-variance.

    One definition for numpy arrays (scoring) and torch tensors (training passes torch's
    `softplus`), so the two cannot drift apart.
    """
    half = outputs.shape[-1] // 2
    mean, raw = outputs[..., :half], outputs[..., half:]
    logvar = MAX_LOGVAR - softplus(MAX_LOGVAR - raw)
    return mean, MIN_LOGVAR + softplus(logvar - MIN_LOGVAR)


@dataclass(frozen=True)
class TrainSettings:
    """Optimisation settings shared by the neural detectors (Adam, a fixed number of epochs)."""

    epochs: int
    batch_size: int
    lr: float
    device: str


class TorchDetector(BaseDetector):
    """Parameters every neural detector shares; subclasses declare the defaults.

    `hidden_sizes` (list of ints), `epochs`, `batch_size`, `lr` (Adam) and `device` (where the
    networks train: "auto" = CUDA when available, else CPU; scoring always runs in numpy on the
    CPU) are validated here once for all of them. `uses_torch`: fitting needs torch.
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


class TransitionEnsemble(TorchDetector):
    """An ensemble of M networks from the standardised (s_t, one-hot a_t) to the standardised
    increment s_{t+1} − s_t: the dynamics model `pedm` and `ensemble_disagreement` share."""

    n_members: int

    def _inputs(self, trajectory: Trajectory) -> np.ndarray:
        return trajectory_features(trajectory, "state_action", self.action_encoding_)

    def _fit_ensemble(
        self, trajectories: Sequence[Trajectory], loss: str, outputs_per_coordinate: int,
        bootstrap: bool,
    ) -> Standardizer:  # fmt: skip
        """Train the members with `loss` ("mse" or "gaussian_nll"), each on a bootstrap
        resample or on all transitions; returns the increments' standardizer."""
        from oodrl.detectors import torch_utils

        loss_fn = {"mse": torch_utils.member_mse, "gaussian_nll": torch_utils.member_gaussian_nll}
        self.action_encoding_ = ActionEncoding.fit(trajectories)
        inputs = stacked(trajectories, self._inputs)
        deltas = stacked(trajectories, increments)
        self.input_standardizer_ = Standardizer.fit(inputs)
        target_standardizer = Standardizer.fit(deltas)
        generator = torch_utils.seeded_generator(self.seed)
        model = torch_utils.EnsembleMLP(
            self.n_members, inputs.shape[1], outputs_per_coordinate * deltas.shape[1],
            self.hidden_sizes, generator,
        )  # fmt: skip
        self.weights_ = torch_utils.train_ensemble(
            model,
            self.input_standardizer_.transform(inputs),
            target_standardizer.transform(deltas),
            loss_fn[loss],
            self._train_settings(),
            torch_utils.member_indices(self.n_members, len(inputs), bootstrap, generator),
            generator,
        )
        return target_standardizer
