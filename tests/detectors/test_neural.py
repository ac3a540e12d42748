"""Scoring runs the fitted ensembles forward in numpy: it must agree with a torch forward pass.

The torch references below rebuild each network from the stored weights and score as the
detectors did when they trained and scored with torch, kept here as the oracle.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch
from test_contract import POLICIES
from torch import nn

from oodrl.core.detector import BaseDetector
from oodrl.detectors import DETECTORS, neural
from oodrl.detectors.features import increments, stacked, stacked_features
from oodrl.detectors.mlp import (
    MAX_LOGVAR,
    MIN_LOGVAR,
    EnsembleWeights,
    gaussian_mean_and_logvar,
    init_weights,
)
from oodrl.detectors.neural import NeuralDetector, chunked_scores
from oodrl.testing import linear_system_trajectories

#: float32 forward passes: torch sums the matrix products in its own order and rounds each
#: partial sum, numpy's layers are correctly rounded.
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
    "fqe_td": {"policy": POLICIES["discrete"], "n_members": 3, "hidden_sizes": [16]},
}


def torch_forward(weights: EnsembleWeights, x: torch.Tensor) -> torch.Tensor:
    """The ensemble's float32 forward pass in torch on (M, B, in) inputs."""
    for weight, bias, relu in zip(weights.weights, weights.biases, weights.relu, strict=True):
        x = torch.baddbmm(torch.from_numpy(bias), x, torch.from_numpy(weight).transpose(1, 2))
        if relu:
            x = torch.relu(x)
    return x


def torch_outputs(weights: EnsembleWeights, inputs: np.ndarray) -> torch.Tensor:
    """(M, N, out) float64 outputs of the torch forward pass on inputs shared by all members."""
    x = torch.as_tensor(inputs, dtype=torch.float32)
    return torch_forward(weights, x.expand(weights.n_members, -1, -1).contiguous()).double()


def torch_gaussian_head(outputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gaussian head as first written for torch: mean and softly bounded log-variance."""
    mean, raw = outputs.chunk(2, dim=-1)
    logvar = MAX_LOGVAR - nn.functional.softplus(MAX_LOGVAR - raw)
    return mean, MIN_LOGVAR + nn.functional.softplus(logvar - MIN_LOGVAR)


def random_weights(n_members: int, sizes: list[int], seed: int) -> EnsembleWeights:
    return init_weights(n_members, sizes, np.random.default_rng(seed))


@pytest.mark.parametrize(
    ("n_members", "sizes"),
    [(1, [3, 2]), (1, [5, 8, 3, 8, 5]), (4, [12, 64, 64, 16]), (2, [7, 1, 7])],
    ids=["linear", "autoencoder-shaped", "pedm-shaped", "width-1"],
)
def test_numpy_forward_matches_torch(n_members, sizes):
    weights = random_weights(n_members, sizes, seed=0)
    rng = np.random.default_rng(1)
    shared = (20 * rng.standard_normal((300, sizes[0]))).astype(np.float32)
    per_member = rng.standard_normal((n_members, 50, sizes[0])).astype(np.float32)
    with np.errstate(all="raise"):
        got_shared = weights.predict(shared)
    assert got_shared.dtype == np.float32
    assert got_shared.shape == (n_members, 300, sizes[-1])
    for got, inputs in [(got_shared, shared), (weights.predict(per_member), per_member)]:
        x = torch.as_tensor(inputs).expand(n_members, *got.shape[1:2], sizes[0]).contiguous()
        expected = torch_forward(weights, x).numpy()
        np.testing.assert_allclose(got, expected, rtol=FORWARD_RTOL, atol=FORWARD_ATOL)


def test_layers_are_correctly_rounded():
    # Each layer is the float64 product (exact up to ~1e-16 here) rounded once to float32.
    weights = random_weights(2, [6, 32, 3], seed=0)
    x = np.random.default_rng(1).standard_normal((100, 6)).astype(np.float32)
    hidden = x.astype(np.float64) @ weights.weights[0].astype(np.float64).transpose(0, 2, 1)
    hidden = np.maximum(hidden + weights.biases[0], 0).astype(np.float32)
    output = hidden.astype(np.float64) @ weights.weights[1].astype(np.float64).transpose(0, 2, 1)
    output = (output + weights.biases[1]).astype(np.float32)
    np.testing.assert_array_equal(weights.predict(x), output)


def test_numpy_gaussian_head_matches_torch():
    raw = np.concatenate([np.linspace(-60, 60, 241), [-1e4, 1e4]])
    outputs = np.stack([np.linspace(-3, 3, raw.size), raw], axis=-1)[None]  # (1, n, 2)
    mean, logvar = gaussian_mean_and_logvar(outputs)
    expected_mean, expected_logvar = torch_gaussian_head(torch.from_numpy(outputs))
    np.testing.assert_array_equal(mean, expected_mean.numpy())
    # torch's softplus returns x itself above x = 20; numerics.softplus keeps 32 bits.
    np.testing.assert_allclose(logvar, expected_logvar.numpy(), rtol=1e-9, atol=1e-8)
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
    inputs = detector.input_standardizer_.transform(
        stacked_features(trajectories, "state_action", detector.action_encoding_)
    )
    targets = torch.as_tensor(
        detector.target_standardizer_.transform(stacked(trajectories, increments))
    )
    steps = torch.as_tensor(np.concatenate([np.arange(t.T) for t in trajectories]))
    rng = np.random.default_rng(detector.seed)
    # (T, M, K, d_s): the detector keeps the samples innermost.
    noise = torch.as_tensor(detector._noise(rng, max(t.T for t in trajectories)).swapaxes(2, 3))
    mean, logvar = torch_gaussian_head(torch_outputs(detector.weights_, inputs))
    std = torch.exp(0.5 * logvar)
    samples = mean.transpose(0, 1)[:, :, None] + std.transpose(0, 1)[:, :, None] * noise[steps]
    errors = ((targets[:, None, None] - samples) ** 2).sum(dim=-1)
    return errors.flatten(start_dim=1).min(dim=1).values


def autoencoder_reference(detector: BaseDetector, trajectories: list) -> torch.Tensor:
    z = detector.standardizer_.transform(
        stacked_features(trajectories, detector.features, detector.action_encoding_)
    )
    outputs = torch_outputs(detector.weights_, z)
    return ((outputs[0] - torch.as_tensor(z)) ** 2).sum(dim=-1)


def ensemble_disagreement_reference(detector: BaseDetector, trajectories: list) -> torch.Tensor:
    inputs = detector.input_standardizer_.transform(
        stacked_features(trajectories, "state_action", detector.action_encoding_)
    )
    outputs = torch_outputs(detector.weights_, inputs)
    spread = outputs - outputs.mean(dim=0, keepdim=True)
    return (spread**2).sum(dim=-1).mean(dim=0)


def fqe_td_reference(detector: BaseDetector, trajectories: list) -> torch.Tensor:
    encoding, standardizer = detector.action_encoding_, detector.input_standardizer_
    states, next_states = (stacked(trajectories, lambda t, f=f: getattr(t, f)) for f in
                           ("states", "next_states"))  # fmt: skip
    actions = stacked(trajectories, lambda t: encoding.encode(t.actions))
    next_actions = encoding.encode(detector.policy_.act(next_states))
    q, q_next = (
        torch_outputs(detector.weights_, standardizer.transform(np.hstack(pair)))[..., 0]
        for pair in [(states, actions), (next_states, next_actions)]
    )
    rewards = torch.as_tensor(stacked(trajectories, lambda t: t.rewards.astype(np.float64)))
    dones = torch.as_tensor(stacked(trajectories, lambda t: t.dones))
    discount = torch.where(dones, 0.0, detector.gamma)
    td = rewards / detector.reward_scale_ + discount * q_next - q
    spread = q.std(dim=0, correction=0)
    return td.abs().mean(dim=0) + detector.disagreement_weight * spread


REFERENCES: dict[str, Callable[[BaseDetector, list], torch.Tensor]] = {
    "pedm": pedm_reference,
    "autoencoder": autoencoder_reference,
    "ensemble_disagreement": ensemble_disagreement_reference,
    "fqe_td": fqe_td_reference,
}


def test_every_neural_detector_has_a_torch_reference():
    neural_names = {n for n in DETECTORS.names() if issubclass(DETECTORS.get(n), NeuralDetector)}
    assert set(REFERENCES) == neural_names


@pytest.mark.parametrize("name", sorted(REFERENCES), ids=sorted(REFERENCES))
def test_scores_match_the_torch_forward(name, monkeypatch):
    detector = DETECTORS.get(name)(**SMALL[name])
    detector.fit(linear_system_trajectories(6, T=120, seed=0))
    # Another system (out of distribution) and uneven lengths; chunk boundaries fall
    # mid-trajectory, so a row's step index must follow it into its chunk.
    scored = linear_system_trajectories(2, T=90, seed=1) + linear_system_trajectories(1, T=37)
    monkeypatch.setattr(neural, "PREDICT_CHUNK", 50)
    scores = np.concatenate([o.scores for o in detector.score_many(scored)])
    expected = REFERENCES[name](detector, scored).numpy()
    np.testing.assert_allclose(scores, expected, rtol=SCORE_RTOL, atol=SCORE_ATOL)
