"""`riqn` (SPEC §20): its numpy GRU and IQN head agree with torch's, forward and backward; it
learns; its scores are exact per stream and per batch."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch

from oodrl.detectors import DETECTORS
from oodrl.detectors.riqn import (
    SCORE_LEVELS,
    TRAINING_LEVELS,
    Chunk,
    RiqnWeights,
    chunk_gradients,
    cos_pi,
    cosine_features,
)
from oodrl.testing import check_streaming, linear_system_trajectories

SMALL = {"hidden_size": 16, "n_cos": 8, "n_quantiles": 3, "epochs": 6, "chunk_length": 20}
FIT = linear_system_trajectories(6, T=120, episode_length=50, seed=0)
SCORED = linear_system_trajectories(3, T=90, episode_length=40, seed=1)


@pytest.fixture(scope="module")
def detector():
    return DETECTORS.get("riqn")(**SMALL).fit(FIT)


def torch_weights(w: RiqnWeights) -> list[torch.Tensor]:
    return [torch.tensor(a, dtype=torch.float32, requires_grad=True) for a in w.arrays()]


def torch_chunk_loss(params, chunk: Chunk, h0: np.ndarray, cosines, taus):
    """The chunk's loss as torch computes it: nn.GRUCell's equations step by step (h restarts
    at 0 where an episode starts), the IQN head on every drawn level, the mean pinball loss."""
    w_i, b_i, w_h, b_h, w_e, b_e, w_1, b_1, w_2, b_2 = params
    x = torch.from_numpy(chunk.inputs)
    h = torch.from_numpy(h0)
    states = []
    for t in range(x.shape[1]):
        h = torch.where(torch.from_numpy(chunk.starts[:, t, None]), torch.zeros_like(h), h)
        h = torch._VF.gru_cell(x[:, t], h, w_i, w_h, b_i, b_h)
        states.append(h)
    states = torch.stack(states, 1)  # (B, L, H)
    k = chunk.levels.shape[2]
    index = torch.from_numpy(chunk.levels.reshape(-1))
    embedding = torch.relu(torch.from_numpy(cosines)[index] @ w_e.T + b_e)
    h_rows = states.reshape(-1, states.shape[2]).repeat_interleave(k, 0)
    q = torch.relu((h_rows * embedding) @ w_1.T + b_1) @ w_2.T + b_2
    targets = torch.from_numpy(chunk.targets.reshape(-1, q.shape[1])).repeat_interleave(k, 0)
    tau = torch.from_numpy(taus)[index][:, None]
    residual = targets.double() - q.double()
    loss = residual * (tau - (residual < 0).double())
    valid = torch.from_numpy(np.repeat(chunk.valid.reshape(-1), k))[:, None]
    count = max(int(chunk.valid.sum()), 1) * k * q.shape[1]
    return torch.where(valid, loss, torch.zeros_like(loss)).sum() / count, h


def random_chunk(rng: np.random.Generator, rows=3, length=12, d_in=5, d_out=4, k=3) -> Chunk:
    starts = rng.random((rows, length)) < 0.15
    starts[:, 0] = True
    valid = np.ones((rows, length), bool)
    valid[2, 8:] = False  # a shorter stream, padded
    return Chunk(
        rng.standard_normal((rows, length, d_in)).astype(np.float32),
        rng.standard_normal((rows, length, d_out)).astype(np.float32),
        starts,
        valid,
        rng.integers(len(TRAINING_LEVELS), size=(rows, length, k)),
    )


def test_gradients_match_torch_autograd():
    rng = np.random.default_rng(0)
    weights = RiqnWeights.initial(5, 8, 6, 4, rng)
    chunk = random_chunk(rng)
    h0 = rng.standard_normal((3, 8)).astype(np.float32) * 0.5
    cosines = cosine_features(TRAINING_LEVELS, 6)
    taus = np.array([float(t) for t in TRAINING_LEVELS])
    loss, grads, h_last = chunk_gradients(weights, chunk, h0, cosines, taus)
    params = torch_weights(weights)
    torch_loss, torch_h = torch_chunk_loss(params, chunk, h0, cosines, taus)
    torch_loss.backward()
    assert loss == pytest.approx(torch_loss.item(), rel=1e-5)
    np.testing.assert_allclose(h_last, torch_h.detach().numpy(), rtol=1e-5, atol=1e-6)
    for mine, theirs, name in zip(grads.arrays(), params, RiqnWeights.__dataclass_fields__,
                                  strict=True):  # fmt: skip
        expected = theirs.grad.numpy()
        scale = np.abs(expected).max()
        assert scale > 0, name
        np.testing.assert_allclose(mine, expected, rtol=1e-3, atol=1e-5 * scale, err_msg=name)


def test_scores_match_a_torch_forward(detector):
    w = detector.weights_
    params = [torch.from_numpy(a) for a in w.arrays()]
    w_i, b_i, w_h, b_h, w_e, b_e, w_1, b_1, w_2, b_2 = params
    cosines = torch.from_numpy(cosine_features(SCORE_LEVELS, SMALL["n_cos"]))
    embedding = torch.relu(cosines @ w_e.T + b_e)  # (7, H)
    taus = torch.tensor([float(t) for t in SCORE_LEVELS], dtype=torch.float64)
    for trajectory, output in zip(SCORED, detector.score_many(SCORED), strict=True):
        x = torch.from_numpy(detector._inputs(trajectory))
        targets = torch.from_numpy(detector._targets(trajectory))
        h = torch.zeros(1, SMALL["hidden_size"])
        expected = []
        for t in range(trajectory.T):
            if t == 0 or trajectory.dones[t - 1]:
                h = torch.zeros_like(h)
            h = torch._VF.gru_cell(x[t : t + 1], h, w_i, w_h, b_i, b_h)
            q = torch.relu((h * embedding) @ w_1.T + b_1) @ w_2.T + b_2  # (7, d_s)
            residual = targets[t][None] - q.double()
            expected.append((residual * (taus[:, None] - (residual < 0).double())).mean())
        np.testing.assert_allclose(output.scores, torch.stack(expected), rtol=1e-4, atol=1e-7)


def test_training_lowers_the_loss(detector):
    losses = detector.training_losses_
    assert len(losses) == SMALL["epochs"]
    assert losses[-1] < 0.7 * losses[0]


def test_cosine_features_are_exact():
    assert cos_pi(Fraction(0)) == 1.0
    assert cos_pi(Fraction(1, 3)) == pytest.approx(0.5, abs=1e-16)
    assert cos_pi(Fraction(1, 2)) == pytest.approx(0.0, abs=1e-40)
    assert cos_pi(Fraction(7, 4)) == pytest.approx(math.sqrt(0.5), abs=1e-16)
    table = cosine_features(TRAINING_LEVELS, 16)
    taus = np.array([float(t) for t in TRAINING_LEVELS])
    expected = np.cos(np.pi * np.arange(16)[None, :] * taus[:, None]).astype(np.float32)
    np.testing.assert_allclose(table, expected, atol=1e-7)


def test_streams_and_batches_of_any_lengths_are_exact(detector):
    # Streams of different lengths scored together are padded; each must keep its own bits.
    mixed = [*SCORED, linear_system_trajectories(1, T=37, seed=2)[0]]
    together = detector.score_many(mixed)
    for trajectory, output in zip(mixed, together, strict=True):
        np.testing.assert_array_equal(detector.score(trajectory).scores, output.scores)
    check_streaming(detector, mixed)


def test_the_hidden_state_restarts_after_a_done(detector):
    # Two streams that differ only before a done score alike after it (but the step of the
    # done itself, whose next state is the terminal observation, is scored as usual).
    trajectory = SCORED[0]
    end = int(np.flatnonzero(trajectory.dones)[0])
    states = trajectory.states.copy()
    states[:end] += 0.5
    changed = trajectory.replace(states=states)
    before, after = detector.score(trajectory).scores, detector.score(changed).scores
    assert not np.array_equal(before[: end + 1], after[: end + 1])
    np.testing.assert_array_equal(before[end + 1 :], after[end + 1 :])


def test_latency_is_one():
    assert DETECTORS.get("riqn")().latency == 1
