"""What the neural detectors (`pedm`, `autoencoder`, `ensemble_disagreement`) share, torch-free.

Every pipeline stage builds and validates every configured detector on start, so a neural
detector's module, constructor and parameter checks must not import torch (~1.5 s). The torch
code lives in `oodrl.detectors.torch_utils`, which a detector imports inside `_fit` and
`_score_many` only. Fitted weights are stored as numpy arrays (`EnsembleWeights`), so pickles
are device-free, byte-reproducible and load without torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from oodrl.core.detector import BaseDetector
from oodrl.validation import Interval, Options
from oodrl.validation import Sequence as SequenceOf

DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class EnsembleWeights:
    """The fitted weights of an M-member MLP ensemble as numpy arrays (what a detector stores).

    Layer l has `weights[l]` of shape (M, in, out) and `biases[l]` of shape (M, 1, out).
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]


@dataclass(frozen=True)
class TrainSettings:
    """Optimisation settings shared by the neural detectors (Adam, a fixed number of epochs)."""

    epochs: int
    batch_size: int
    lr: float
    device: str


class TorchDetector(BaseDetector):
    """Parameters every neural detector shares; subclasses declare the defaults.

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
