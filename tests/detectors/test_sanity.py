"""Each detector, with its default parameters, separates a blatant anomaly from the clean stream.

Matched AUROC (SPEC §6): positives are the post-onset scores of the perturbed trajectories,
negatives the post-onset scores of their matched clean trajectories; chance is 0.5.

The anomaly is a regime switch (SPEC §4, σ = 1) written inline: from the onset on, every
observation x becomes μ + √3 (x − μ) + 2 sd, with μ the post-onset mean and sd the pre-onset
standard deviation of the clean trajectory — a shift by 2 sd and a variance grown threefold,
applied alike to `states` and `next_states`.

`lyapunov_divergence` by design does not flag displaced states: z_t is the log *ratio* of the
distance to the nearest ID neighbour after h steps to that distance now, so a state far from all
ID data has a large denominator as well, and in a contracting system the displaced stream even
converges towards its neighbour (measured: matched AUROC ≈ 0.2–0.45 for the regime switch, and
also for the linear system observed at double speed). What it measures is diverging local
dynamics, which need smooth, weakly noisy dynamics to show: it is tested on two noisy
oscillators (episodes of ~80 steps with fresh amplitudes and phases) whose frequencies double at
the onset. States stay in distribution; only the motion through them changes.
"""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score
from test_contract import POLICIES

from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.testing import linear_system_trajectories
from oodrl.validation import constructor_params

T = 150
ONSET = T // 3
MIN_AUROC = 0.7

FIT = linear_system_trajectories(12, T=T, seed=1)
CLEAN = linear_system_trajectories(16, T=T, seed=1)[12:]


def regime_switch(trajectory: Trajectory, onset: int) -> Trajectory:
    sd = trajectory.states[:onset].std(axis=0)
    mu = trajectory.states[onset:].mean(axis=0)

    def switched(x: np.ndarray) -> np.ndarray:
        return mu + np.sqrt(3.0) * (x - mu) + 2.0 * sd

    states = trajectory.states.copy()
    next_states = trajectory.next_states.copy()
    states[onset:] = switched(states[onset:])
    # next_states[onset − 1] is the observation states[onset] unless an episode ended there.
    first = onset if trajectory.dones[onset - 1] else onset - 1
    next_states[first:] = switched(next_states[first:])
    return trajectory.replace(states=states, next_states=next_states)


def oscillators(n: int, seed: int, speedup: float = 1.0) -> list[Trajectory]:
    """Two noisy 2-d oscillators (d_s = 4); after ONSET their frequencies grow by `speedup`."""
    frequencies = np.array([0.2, 0.34])
    trajectories = []
    for index in range(n):
        rng = np.random.default_rng([seed, index])
        dones = np.zeros(T, dtype=bool)
        dones[79::80] = True
        angle = np.empty((T + 1, 2))
        amplitude = np.empty((T + 1, 2))
        for t in range(T + 1):
            if t == 0 or dones[t - 1]:
                angle[t] = rng.uniform(0, 2 * np.pi, 2)
                amplitude[t] = rng.uniform(0.5, 1.5, 2)
            else:
                step = frequencies * (speedup if t > ONSET else 1.0)
                angle[t] = angle[t - 1] + step + 0.01 * rng.standard_normal(2)
                amplitude[t] = amplitude[t - 1]
        stream = np.hstack([amplitude * np.cos(angle), amplitude * np.sin(angle)])
        stream += 0.01 * rng.standard_normal(stream.shape)
        # At an episode end the terminal observation is the stream's next value of that episode.
        terminal = stream[1:].copy()
        ends = np.flatnonzero(dones)
        terminal[ends] = stream[ends] + (stream[ends] - stream[ends - 1])
        trajectories.append(
            Trajectory(
                states=stream[:-1].astype(np.float32),
                actions=np.zeros(T, dtype=np.int64),
                rewards=np.zeros(T, dtype=np.float32),
                next_states=terminal.astype(np.float32),
                dones=dones,
            )
        )
    return trajectories


def matched_auroc(detector, clean: list[Trajectory], perturbed: list[Trajectory]) -> float:
    negatives = np.concatenate([o.scores[ONSET:] for o in detector.score_many(clean)])
    positives = np.concatenate([o.scores[ONSET:] for o in detector.score_many(perturbed)])
    labels = np.r_[np.ones(len(positives)), np.zeros(len(negatives))]
    return float(roc_auc_score(labels, np.r_[positives, negatives]))


#: The policy view reads how the policy values a state, not where the state is: away from the
#: origin a linear policy grows more confident, so the regime switch is no anomaly of it
#: (matched AUROC 0.1–0.3). Its blatant anomalies: tests/detectors/test_policy_view.py.
POLICY_VIEW = ("q_margin", "q_entropy", "q_energy", "max_softmax")


@pytest.mark.parametrize("name", DETECTORS.names(), ids=DETECTORS.names())
def test_detector_separates_a_blatant_anomaly(name):
    if name in POLICY_VIEW:
        pytest.skip("the policy view's blatant anomalies are test_policy_view.py's")
    if name == "action_consistency":  # how the action moves, not where the state is (as above)
        pytest.skip("its blatant anomaly (a nearby decision boundary): test_action_consistency.py")
    if name == "lyapunov_divergence":
        fit = oscillators(12, seed=0)
        clean, perturbed = oscillators(4, seed=1), oscillators(4, seed=1, speedup=2.0)
    else:
        fit, clean, perturbed = FIT, CLEAN, [regime_switch(t, ONSET) for t in CLEAN]
    cls = DETECTORS.get(name)
    # A detector that reads the agent's policy reads the one that made the data.
    policy = {"policy": POLICIES["discrete"]} if "policy" in constructor_params(cls) else {}
    detector = cls(**policy).fit(fit)
    auroc = matched_auroc(detector, clean, perturbed)
    if not detector.learns_from_data:  # the floor (random_scores): chance, by design
        assert abs(auroc - 0.5) < 0.1
        return
    assert auroc > MIN_AUROC
