"""The shared torch toolkit: stored weights rebuild the same network; training is seeded."""

import numpy as np
import torch

from oodrl.detectors.neural import EnsembleWeights, TrainSettings
from oodrl.detectors.torch_utils import (
    EnsembleMLP,
    chunked_scores,
    member_indices,
    member_mse,
    resolve_device,
    train_ensemble,
)


def test_auto_device_is_cuda_only_when_available():
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected


def test_weights_round_trip_and_members_are_independent():
    model = EnsembleMLP(3, 4, 2, [8, 8], torch.Generator().manual_seed(0))
    weights = model.numpy_weights()
    x = torch.randn(3, 5, 4, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        cpu = torch.device("cpu")
        torch.testing.assert_close(EnsembleMLP.from_weights(weights, cpu)(x), model(x))
        # Member 1 alone gives the same output as within the ensemble.
        single = EnsembleMLP.from_weights(
            EnsembleWeights(
                tuple(w[1:2] for w in weights.weights), tuple(b[1:2] for b in weights.biases)
            ),
            cpu,
        )
        torch.testing.assert_close(single(x[1:2])[0], model(x)[1])


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

    def mse(outputs, rows):
        return ((outputs - torch.as_tensor(targets[rows])) ** 2).sum(dim=-1).mean(dim=0)

    untrained = EnsembleMLP(2, 3, 2, [16], torch.Generator().manual_seed(0)).numpy_weights()
    assert (
        chunked_scores(first, inputs, "cpu", mse).mean()
        < 0.1 * chunked_scores(untrained, inputs, "cpu", mse).mean()
    )
