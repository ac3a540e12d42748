"""`random_scores` (SPEC §20): uniform, independent, deterministic draws that ignore the data
they are fitted on, shared by matched streams until the streams differ."""

from __future__ import annotations

import numpy as np
from scipy import stats

from oodrl.detectors import DETECTORS
from oodrl.testing import check_streaming, linear_system_trajectories

DATA = linear_system_trajectories(12, T=200, seed=0)


def scores(seed: int = 0, trajectories=DATA[6:]) -> list[np.ndarray]:
    detector = DETECTORS.get("random_scores")(seed=seed).fit(DATA[:6])
    return [o.scores for o in detector.score_many(trajectories)]


def test_scores_are_uniform_and_independent():
    flat = np.concatenate(scores())
    assert flat.min() >= 0 and flat.max() < 1
    assert stats.kstest(flat, "uniform").pvalue > 1e-3
    per_stream = np.array(scores())
    # No dependence on the step (columns) or between consecutive steps (sd ≈ 1/√1200 ≈ 0.03).
    assert abs(np.corrcoef(flat[:-1], flat[1:])[0, 1]) < 0.1
    assert abs(stats.spearmanr(np.tile(np.arange(200), 6), per_stream.ravel())[0]) < 0.1


def test_the_seed_picks_the_draws_and_the_fit_set_does_not():
    first, again, other = scores(0), scores(0), scores(1)
    for a, b, c in zip(first, again, other, strict=True):
        np.testing.assert_array_equal(a, b)
        assert not np.any(a == c)
    moved = [t.replace(states=3 * t.states + 1) for t in DATA[:6]]
    detector = DETECTORS.get("random_scores")().fit(moved)
    np.testing.assert_array_equal(detector.score(DATA[6]).scores, first[0])
    assert not DETECTORS.get("random_scores").learns_from_data


def test_matched_streams_share_scores_until_they_differ():
    clean = DATA[6]
    states = clean.states.copy()
    states[120:] += 0.25
    perturbed = clean.replace(states=states)
    a, b = scores(trajectories=[clean, perturbed])
    np.testing.assert_array_equal(a[:120], b[:120])
    assert not np.any(a[120:] == b[120:])


def test_streams_equal_batch_scores():
    detector = DETECTORS.get("random_scores")(seed=5).fit(DATA[:6]).calibrate(DATA[6:8])
    check_streaming(detector, DATA[8:])
    continuous = linear_system_trajectories(3, T=80, action_dim=2, seed=1)
    check_streaming(DETECTORS.get("random_scores")().fit(continuous[:1]), continuous[1:])
