"""action_consistency scores a set in chunks of `CHUNK_STEPS` steps (bounded memory) with the same
bits as one batch of the whole set: the scores are stored in DVC outputs, byte for byte.

On the suite's own multi-layer policies, whose float64 products (BLAS) may round differently for
different batch shapes: the scores hold only because every action is correctly rounded."""

from pathlib import Path

import numpy as np
import pytest

from oodrl.core.trajectory import Trajectory
from oodrl.detectors import action_consistency
from oodrl.detectors.action_consistency import ActionConsistency
from oodrl.suite.environments import policy_path

ROOT = Path(__file__).resolve().parents[2]
POLICIES = {
    # LunarLander's NoisyNet DQN, 256-unit ReLU layers: discrete, the certified argmax.
    "discrete": ROOT / "models/policy.pt",
    # LunarLanderContinuous's SAC actor, 400 and 300 units: continuous, tanh-squashed.
    "continuous": policy_path("LunarLanderContinuous-v3", ROOT),
}
#: Stream lengths: a single step, a length no tested chunk divides, one longer than a chunk.
LENGTHS = (1, 37, 300)
#: Chunk sizes: one step, one that divides no length nor their 338 total, one dividing 338.
CHUNKS = (1, 7, 169)


def stream(seed: int, T: int) -> Trajectory:
    """LunarLander-like 8-dim observations: six continuous features, two 0/1 leg contacts."""
    rng = np.random.default_rng([11, seed])
    states = rng.standard_normal((T, 8)) * [0.3, 0.5, 0.4, 0.3, 0.2, 0.2, 1.0, 1.0]
    states[:, 6:] = rng.random((T, 2)) < 0.3
    states = states.astype(np.float32)
    return Trajectory(
        states=states,
        actions=np.zeros(T, dtype=np.int64),
        rewards=np.zeros(T, np.float32),
        next_states=states,
        dones=np.zeros(T, bool),
    )


@pytest.mark.parametrize("kind", list(POLICIES))
def test_any_chunk_size_gives_the_bits_of_one_batch(kind, monkeypatch):
    detector = ActionConsistency(policy=str(POLICIES[kind])).fit([stream(i, 200) for i in range(3)])
    streams = [stream(10 + i, T) for i, T in enumerate(LENGTHS)]
    # One chunk holding every step: the whole set in one policy batch, as before chunking.
    monkeypatch.setattr(action_consistency, "CHUNK_STEPS", sum(LENGTHS))
    whole = [o.scores for o in detector.score_many(streams)]
    assert np.ptp(np.concatenate(whole)) > 0  # scores that vary: the comparison says something
    for chunk in CHUNKS:
        monkeypatch.setattr(action_consistency, "CHUNK_STEPS", chunk)
        chunked = [o.scores for o in detector.score_many(streams)]
        for a, b in zip(chunked, whole, strict=True):
            assert a.dtype == b.dtype == np.float64
            assert np.array_equal(a, b), f"chunk {chunk}"
