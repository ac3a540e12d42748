"""lyapunov_divergence: episode-aware delay embedding and the score against a brute-force oracle."""

import numpy as np

from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import Standardizer
from oodrl.detectors.lyapunov import LyapunovDivergence, episode_embedding
from oodrl.testing import linear_system_trajectories


def test_embedding_pads_at_episode_starts_and_appends_the_last_observation():
    states = np.arange(6, dtype=np.float32)[:, None]  # 0 1 2 | 3 4 5
    trajectory = Trajectory(
        states=states,
        actions=np.zeros(6, dtype=np.int64),
        rewards=np.zeros(6, dtype=np.float32),
        next_states=states + 10,  # terminal observations 12 and 15
        dones=np.array([False, False, True, False, False, False]),
    )
    identity = Standardizer(np.zeros(1), np.ones(1))
    embedding = episode_embedding([trajectory], identity, dimension=2, lag=1)
    # Series: 0 1 2 12 | 3 4 5 15; each row is (x_t, x_{t−1}), padded with the episode's first x.
    np.testing.assert_array_equal(
        embedding.vectors,
        [[0, 0], [1, 0], [2, 1], [12, 2], [3, 3], [4, 3], [5, 4], [15, 5]],
    )
    np.testing.assert_array_equal(embedding.steps, [0, 1, 2, 4, 5, 6])
    np.testing.assert_array_equal(embedding.steps_left, [3, 2, 1, 0, 3, 2, 1, 0])


def oracle_scores(detector: LyapunovDivergence, fit, trajectory) -> np.ndarray:
    """The SPEC formula with a brute-force neighbour search, step by step."""
    reference = detector._embed(fit)
    query = detector._embed([trajectory])
    candidates = np.flatnonzero(reference.steps_left >= detector.horizon)
    eps = detector.epsilon
    scores = []
    for position in query.steps:
        y = query.vectors[position]
        j = candidates[np.argmin(np.linalg.norm(reference.vectors[candidates] - y, axis=1))]
        horizon = min(detector.horizon, query.steps_left[position])
        ratios = [
            np.log(
                (np.linalg.norm(query.vectors[position + h] - reference.vectors[j + h]) + eps)
                / (np.linalg.norm(y - reference.vectors[j]) + eps)
            )
            for h in range(1, horizon + 1)
        ]
        scores.append(np.mean(ratios))
    return np.array(scores)


def test_scores_match_the_formula_with_brute_force_neighbours():
    data = linear_system_trajectories(4, T=60, episode_length=25, seed=0)
    fit, scored = data[:3], data[3]
    assert scored.dones.sum() >= 2
    detector = LyapunovDivergence(embedding_dim=3, lag=2, horizon=4).fit(fit)
    np.testing.assert_allclose(detector.score(scored).scores, oracle_scores(detector, fit, scored))
