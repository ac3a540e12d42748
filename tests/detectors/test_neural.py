"""Scoring runs the fitted ensembles forward in numpy: it must agree with the torch forward pass.

The torch references below are the scoring code the neural detectors used before it moved to
numpy (a torch module rebuilt from the stored weights), kept here as the oracle.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch
from torch import nn

from oodrl.core.detector import BaseDetector
from oodrl.detectors import DETECTORS, neural
from oodrl.detectors.features import increments, stacked
from oodrl.detectors.neural import (
    MAX_LOGVAR,
    MIN_LOGVAR,
    EnsembleWeights,
    chunked_scores,
    gaussian_mean_and_logvar,
)
from oodrl.detectors.torch_utils import EnsembleMLP
from oodrl.testing import linear_system_trajectories

#: float32 forward passes: numpy and torch may sum the matrix products in different orders.
FORWARD_RTOL = 1e-5
FORWARD_ATOL = 1e-6
#: Scores are float64 reductions of those float32 outputs; a squared error of nearly equal
#: outputs (the autoencoder's) loses a few more digits to cancellation.
SCORE_RTOL = 1e-4
SCORE_ATOL = 1e-7

SMALL: dict[str, dict] = {
    "pedm": {"n_members": 3, "n_samples": 4, "hidden_sizes": [16, 16], "epochs": 5},
    "autoencoder": {"hidden_sizes": [16], "latent_dim": 2, "epochs": 5},
    "ensemble_disagreement": {"n_members": 3, "hidden_sizes": [16, 16], "epochs": 5},
}


def torch_model(weights: EnsembleWeights) -> EnsembleMLP:
    """An EnsembleMLP holding copies of `weights` (what scoring built before it used numpy)."""
    n_members, in_dim, _ = weights.weights[0].shape
    hidden = [w.shape[2] for w in weights.weights[:-1]]
    # A private generator for the throwaway initialisation: the global RNG stays untouched.
    generator = torch.Generator()
    model = EnsembleMLP(n_members, in_dim, weights.weights[-1].shape[2], hidden, generator)
    with torch.no_grad():
        for param, array in zip(
            [*model.weights, *model.biases], [*weights.weights, *weights.biases], strict=True
        ):
            param.copy_(torch.from_numpy(array))
    return model.eval()


def torch_outputs(weights: EnsembleWeights, inputs: np.ndarray) -> torch.Tensor:
    """(M, N, out) float64 outputs of the torch forward pass on inputs shared by all members."""
    x = torch.as_tensor(inputs, dtype=torch.float32)
    with torch.no_grad():
        return torch_model(weights)(x.expand(weights.weights[0].shape[0], -1, -1)).double()


def torch_gaussian_head(outputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gaussian head as first written for torch: mean and softly bounded log-variance."""
    mean, raw = outputs.chunk(2, dim=-1)
    logvar = MAX_LOGVAR - nn.functional.softplus(MAX_LOGVAR - raw)
    return mean, MIN_LOGVAR + nn.functional.softplus(logvar - MIN_LOGVAR)


def random_weights(n_members: int, sizes: list[int], seed: int) -> EnsembleWeights:
    return EnsembleMLP(
        n_members, sizes[0], sizes[-1], sizes[1:-1], torch.Generator().manual_seed(seed)
    ).numpy_weights()


@pytest.mark.parametrize(
    ("n_members", "sizes"),
    [(1, [3, 2]), (1, [5, 8, 3, 8, 5]), (4, [12, 64, 64, 16]), (2, [7, 1, 7])],
    ids=["linear", "autoencoder-shaped", "pedm-shaped", "width-1"],
)
def test_numpy_forward_matches_torch(n_members, sizes):
    weights = random_weights(n_members, sizes, seed=0)
    rng = np.random.default_rng(1)
    # Wide inputs reach SiLU's far tails, where e^−x overflows float32.
    shared = (20 * rng.standard_normal((300, sizes[0]))).astype(np.float32)
    per_member = rng.standard_normal((n_members, 50, sizes[0])).astype(np.float32)
    model = torch_model(weights)
    with torch.no_grad():
        expected_shared = model(torch.from_numpy(shared).expand(n_members, -1, -1)).numpy()
        expected_per_member = model(torch.from_numpy(per_member)).numpy()
    with np.errstate(all="raise"):
        got_shared = weights.predict(shared)
    assert got_shared.dtype == np.float32
    assert got_shared.shape == (n_members, 300, sizes[-1])
    for got, expected in [
        (got_shared, expected_shared),
        (weights.predict(per_member), expected_per_member),
    ]:
        np.testing.assert_allclose(got, expected, rtol=FORWARD_RTOL, atol=FORWARD_ATOL)


def test_members_are_independent():
    weights = random_weights(3, [4, 8, 8, 2], seed=0)
    x = np.random.default_rng(1).standard_normal((5, 4))
    member = EnsembleWeights(
        tuple(w[1:2] for w in weights.weights), tuple(b[1:2] for b in weights.biases)
    )
    np.testing.assert_array_equal(member.predict(x)[0], weights.predict(x)[1])


def test_numpy_gaussian_head_matches_torch():
    raw = np.concatenate([np.linspace(-60, 60, 241), [-1e4, 1e4]])
    outputs = np.stack([np.linspace(-3, 3, raw.size), raw], axis=-1)[None]  # (1, n, 2)
    mean, logvar = gaussian_mean_and_logvar(outputs)
    expected_mean, expected_logvar = torch_gaussian_head(torch.from_numpy(outputs))
    np.testing.assert_array_equal(mean, expected_mean.numpy())
    # torch's softplus returns x itself above x = 20, numpy's the exact log(1 + e^x).
    np.testing.assert_allclose(logvar, expected_logvar.numpy(), rtol=1e-12, atol=1e-8)
    # Soft bounds: the upper one is overshot by softplus(MIN_LOGVAR - MAX_LOGVAR) at most.
    assert logvar.min() >= MIN_LOGVAR and logvar.max() < MAX_LOGVAR + 1e-5


def test_chunked_scores_do_not_depend_on_the_chunk_size(monkeypatch):
    weights = random_weights(2, [3, 8, 2], seed=0)
    inputs = np.random.default_rng(1).standard_normal((100, 3))
    offsets = np.arange(100.0)

    def reduce(outputs: np.ndarray, rows: slice) -> np.ndarray:
        return outputs.sum(axis=(0, 2)) + offsets[rows]

    whole = reduce(weights.predict(inputs).astype(np.float64), slice(None))
    monkeypatch.setattr(neural, "PREDICT_CHUNK", 7)
    np.testing.assert_allclose(chunked_scores(weights, inputs, reduce), whole, rtol=1e-12)


def pedm_reference(detector: BaseDetector, trajectories: list) -> torch.Tensor:
    inputs = detector.input_standardizer_.transform(stacked(trajectories, detector._inputs))
    targets = torch.as_tensor(
        detector.target_standardizer_.transform(stacked(trajectories, increments))
    )
    steps = torch.as_tensor(np.concatenate([np.arange(t.T) for t in trajectories]))
    noise = torch.as_tensor(detector._noise(max(t.T for t in trajectories)))
    mean, logvar = torch_gaussian_head(torch_outputs(detector.weights_, inputs))
    std = torch.exp(0.5 * logvar)
    samples = mean.transpose(0, 1)[:, :, None] + std.transpose(0, 1)[:, :, None] * noise[steps]
    errors = ((targets[:, None, None] - samples) ** 2).sum(dim=-1)
    return errors.flatten(start_dim=1).min(dim=1).values


def autoencoder_reference(detector: BaseDetector, trajectories: list) -> torch.Tensor:
    z = detector.standardizer_.transform(stacked(trajectories, detector._features))
    outputs = torch_outputs(detector.weights_, z)
    return ((outputs[0] - torch.as_tensor(z)) ** 2).sum(dim=-1)


def ensemble_disagreement_reference(detector: BaseDetector, trajectories: list) -> torch.Tensor:
    inputs = detector.input_standardizer_.transform(stacked(trajectories, detector._inputs))
    outputs = torch_outputs(detector.weights_, inputs)
    spread = outputs - outputs.mean(dim=0, keepdim=True)
    return (spread**2).sum(dim=-1).mean(dim=0)


REFERENCES: dict[str, Callable[[BaseDetector, list], torch.Tensor]] = {
    "pedm": pedm_reference,
    "autoencoder": autoencoder_reference,
    "ensemble_disagreement": ensemble_disagreement_reference,
}


def test_every_neural_detector_has_a_torch_reference():
    assert set(REFERENCES) == {n for n in DETECTORS.names() if DETECTORS.get(n).uses_torch}


@pytest.mark.parametrize("name", sorted(REFERENCES), ids=sorted(REFERENCES))
def test_scores_match_the_torch_forward(name, monkeypatch):
    detector = DETECTORS.get(name)(device="cpu", **SMALL[name])
    detector.fit(linear_system_trajectories(6, T=120, seed=0))
    # Another system (out of distribution) and uneven lengths; chunk boundaries fall
    # mid-trajectory, so a row's step index must follow it into its chunk.
    scored = linear_system_trajectories(2, T=90, seed=1) + linear_system_trajectories(1, T=37)
    monkeypatch.setattr(neural, "PREDICT_CHUNK", 50)
    scores = np.concatenate([o.scores for o in detector.score_many(scored)])
    expected = REFERENCES[name](detector, scored).numpy()
    np.testing.assert_allclose(scores, expected, rtol=SCORE_RTOL, atol=SCORE_ATOL)
