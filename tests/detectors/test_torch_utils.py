"""The shared torch toolkit: devices resolve, training is seeded and learns.

That the stored weights run forward the same in numpy is tested in test_neural.py.
"""

import numpy as np
import torch

from oodrl.detectors.neural import TrainSettings
from oodrl.detectors.torch_utils import (
    EnsembleMLP,
    member_indices,
    member_mse,
    resolve_device,
    train_ensemble,
)


def test_auto_device_is_cuda_only_when_available():
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected


def test_training_is_seeded_and_reduces_the_loss():
    rng = np.random.default_rng(0)
    inputs = rng.standard_normal((300, 3))
    targets = inputs @ rng.standard_normal((3, 2))
    settings = TrainSettings(epochs=20, batch_size=32, lr=1e-2, device="cpu")

    def fit(seed):
        generator = torch.Generator().manual_seed(seed)
        model = EnsembleMLP(2, 3, 2, [16], generator)
        indices = member_indices(2, 300, True, generator)
        return train_ensemble(model, inputs, targets, member_mse, settings, indices, generator)

    first, second = fit(0), fit(0)
    for a, b in zip(first.weights, second.weights, strict=True):
        np.testing.assert_array_equal(a, b)

    def mse(weights):
        return ((weights.predict(inputs) - targets) ** 2).sum(axis=-1).mean()

    untrained = EnsembleMLP(2, 3, 2, [16], torch.Generator().manual_seed(0)).numpy_weights()
    assert mse(first) < 0.1 * mse(untrained)
