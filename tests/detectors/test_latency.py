"""Every detector's `latency` is its exact look-ahead (SPEC §6 detection delay).

Change the observation stream from step t0 on (as a post-hoc injector does: `states[t]` for
t ≥ t0 and `next_states[t0 − 1]`, the same observation): a detector with latency L must give the
same scores before t0 − L (it cannot see further ahead than it declares) and a different score at
t0 − L (it does see that far, so the declared latency is not an over-estimate).
"""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from test_contract import POLICIES

from oodrl.core.detector import BaseDetector
from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.testing import linear_system_trajectories
from oodrl.validation import constructor_params

#: Small models so that the file runs in seconds; and every look-ahead the params can choose.
VARIANTS: dict[str, dict] = {
    "mahalanobis_distance": {},
    "mahalanobis_distance-transition": {"features": "transition"},
    "time_series_features": {"window": 16},
    "pedm": {"n_members": 2, "n_samples": 3, "hidden_sizes": [16, 16], "epochs": 2},
    "autoencoder": {"hidden_sizes": [16], "latent_dim": 2, "epochs": 2},
    "autoencoder-transition": {
        "features": "transition",
        "hidden_sizes": [16],
        "latent_dim": 2,
        "epochs": 2,
    },
    "ensemble_disagreement": {"n_members": 2, "hidden_sizes": [16, 16], "epochs": 2},
    "cusum": {},
    "cusum-state": {"residual": "state"},
    "kde_density": {"max_reference": 200},
    "kde_density-transition": {"features": "transition", "max_reference": 200},
    "lyapunov_divergence": {"max_reference": 300},
    "lyapunov_divergence-horizon-3": {"max_reference": 300, "horizon": 3},
    "riqn": {"hidden_size": 8, "n_cos": 4, "n_quantiles": 2, "epochs": 1, "chunk_length": 40},
    "conformal_martingale": {},
    "conformal_martingale-transition": {"base_params": {"features": "transition"}},
    "deedee": {},
    "deedee-transition": {"features": "transition"},
    "random_scores": {},
    "q_margin": {},
    "q_entropy": {},
    "q_energy": {},
    "max_softmax": {},
    "fqe_td": {"n_members": 2, "hidden_sizes": [16], "iterations": 3},
    "cusum_tv": {},
    "cusum_tv-state": {"residual": "state"},
    "action_consistency": {},
}

EXPECTED_LATENCY = {
    "cusum_tv": 1,
    "cusum_tv-state": 0,
    "action_consistency": 0,
    "mahalanobis_distance": 0,
    "mahalanobis_distance-transition": 1,
    "time_series_features": 0,
    "pedm": 1,
    "autoencoder": 0,
    "autoencoder-transition": 1,
    "ensemble_disagreement": 0,
    "cusum": 1,
    "cusum-state": 0,
    "kde_density": 0,
    "kde_density-transition": 1,
    "lyapunov_divergence": 5,
    "lyapunov_divergence-horizon-3": 3,
    "riqn": 1,
    "conformal_martingale": 0,
    "conformal_martingale-transition": 1,
    "deedee": 0,
    "deedee-transition": 1,
    "random_scores": 0,
    "q_margin": 0,
    "q_entropy": 0,
    "q_energy": 0,
    "max_softmax": 0,
    "fqe_td": 1,
}

DATA = linear_system_trajectories(8, T=120, episode_length=200, seed=0)
#: Mid-episode (episodes last ≥ 150 steps), past every window, with room for the horizon.
T0 = 70


def make(variant: str) -> BaseDetector:
    cls = DETECTORS.get(variant.split("-")[0])
    # Detectors that read the agent's policy read the one that made the data.
    policy = {"policy": POLICIES["discrete"]} if "policy" in constructor_params(cls) else {}
    return cls(**VARIANTS[variant], **policy)


@cache
def fitted(variant: str) -> BaseDetector:
    return make(variant).fit(DATA[:6])


def shifted_from(trajectory: Trajectory, t0: int, shift: float) -> Trajectory:
    """The observation stream changed from step t0 on, as a post-hoc injector changes it."""
    assert not trajectory.dones[: t0 + 10].any(), "t0 must sit inside the first episode"
    states = trajectory.states.copy()
    next_states = trajectory.next_states.copy()
    states[t0:] += shift
    next_states[t0 - 1 :] += shift
    return dataclasses.replace(trajectory, states=states, next_states=next_states)


def test_every_registered_detector_is_covered():
    assert {v.split("-")[0] for v in VARIANTS} == set(DETECTORS.names())


@pytest.mark.parametrize("variant", sorted(VARIANTS), ids=str)
def test_latency_follows_the_params(variant):
    assert make(variant).latency == EXPECTED_LATENCY[variant]


@pytest.mark.parametrize("variant", sorted(VARIANTS), ids=str)
def test_latency_is_the_exact_look_ahead(variant):
    if variant == "action_consistency":
        # A share of 8 perturbations that flip the action: often 0 on both sides of a shift, so
        # the first changed step need not be the shift's. z_t reads s_t alone (row-independent:
        # the contract's stream-equals-batch check, tests/detectors/test_action_consistency.py).
        pytest.skip("its first changed score need not be the shift's step")
    detector = fitted(variant)
    latency = detector.latency
    clean = DATA[7]
    shifted = shifted_from(clean, T0, shift=3.0)
    before = detector.score(clean).scores
    after = detector.score(shifted).scores
    changed = np.flatnonzero(before != after)
    assert changed.size > 0
    assert changed[0] == T0 - latency, (
        f"{variant}: scores first change at {changed[0]}, the change starts at {T0}, "
        f"so the look-ahead is {T0 - changed[0]} steps; latency says {latency}"
    )
