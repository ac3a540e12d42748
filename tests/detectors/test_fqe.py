"""`fqe_td` (SPEC §20): TD errors of an FQE ensemble of the agent's own policy."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score
from test_contract import POLICIES, SPLITS

from oodrl.detectors import DETECTORS
from oodrl.detectors.fqe import member_values
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import collect
from oodrl.errors import ConfigError
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import collect_online
from oodrl.policies.load import load_policy
from oodrl.suite.environments import PIPELINE_DIRS, policy_path

ROOT = Path(__file__).resolve().parents[2]
LUNAR_LANDER = ROOT / "models" / "policy.pt"
T, ONSET = 400, 133
SMALL = {"n_members": 2, "hidden_sizes": [16], "iterations": 3}


@cache
def lunar_lander_sets():
    """Clean fit streams, clean evaluation streams and their twins under `dynamics_scaling`
    (σ = 1: every state increment 2.5 times larger) from ONSET, with the committed policy."""
    adapter, policy = ENVIRONMENTS.get("LunarLander-v3")(), load_policy(LUNAR_LANDER)
    fit = collect(adapter, policy, range(50_000, 50_008), T).trajectories()
    seeds = list(range(60_000, 60_003))
    clean = collect(adapter, policy, seeds, T).trajectories()
    injector = INJECTORS.get("dynamics_scaling")()
    spec = injector.spec(1.0, ONSET)
    faulty = collect_online(injector, adapter, policy, seeds, T, spec, 0, policy_seed=0)
    return fit, clean, faulty.trajectories()


def test_td_errors_are_small_on_clean_data_and_large_under_a_dynamics_fault():
    fit, clean, faulty = lunar_lander_sets()
    # Only the TD error: no ensemble spread in the score.
    detector = DETECTORS.get("fqe_td")(policy=str(LUNAR_LANDER), disagreement_weight=0.0)
    detector.fit(fit)
    clean_td = np.concatenate([o.scores[ONSET:] for o in detector.score_many(clean)])
    faulty_td = np.concatenate([o.scores[ONSET:] for o in detector.score_many(faulty)])
    # In units of the clean rewards' standard deviation.
    assert np.median(clean_td) < 0.6
    assert np.median(faulty_td) > 2 * np.median(clean_td)
    assert matched_auroc_of(detector, clean, faulty) > 0.75
    # The default score (with the spread) separates them too.
    default = DETECTORS.get("fqe_td")(policy=str(LUNAR_LANDER)).fit(fit)
    assert matched_auroc_of(default, clean, faulty) > 0.75


def matched_auroc_of(detector, clean, faulty) -> float:
    """AUROC of the post-onset scores of the faulty streams against their clean twins'."""
    negatives = np.concatenate([o.scores[ONSET:] for o in detector.score_many(clean)])
    positives = np.concatenate([o.scores[ONSET:] for o in detector.score_many(faulty)])
    labels = np.r_[np.ones(len(positives)), np.zeros(len(negatives))]
    return float(roc_auc_score(labels, np.r_[positives, negatives]))


@pytest.mark.parametrize("actions", list(SPLITS))
def test_the_score_is_the_mean_absolute_td_error_plus_the_spread(actions):
    fit, _, evaluation = SPLITS[actions]
    weight = 0.7
    detector = DETECTORS.get("fqe_td")(
        policy=POLICIES[actions], gamma=0.8, disagreement_weight=weight, **SMALL
    ).fit(fit)
    policy = load_policy(POLICIES[actions])
    for trajectory in evaluation:
        encode = detector.action_encoding_.encode
        standardize = detector.input_standardizer_.transform
        inputs = standardize(np.hstack([trajectory.states, encode(trajectory.actions)]))
        # The bootstrap takes the policy's own action on the next observation.
        next_actions = encode(policy.act(trajectory.next_states))
        next_inputs = standardize(np.hstack([trajectory.next_states, next_actions]))
        q, q_next = (member_values(detector.weights_, x) for x in (inputs, next_inputs))
        rewards = trajectory.rewards.astype(np.float64) / detector.reward_scale_
        discount = np.where(trajectory.dones, 0.0, 0.8)[:, None]
        td = rewards[:, None] + discount * q_next - q
        expected = np.abs(td).mean(axis=1) + weight * q.std(axis=1)
        np.testing.assert_allclose(detector.score(trajectory).scores, expected, rtol=1e-12)


def test_the_rewards_are_scaled_by_their_clean_spread():
    fit = SPLITS["discrete"][0]
    detector = DETECTORS.get("fqe_td")(policy=POLICIES["discrete"], **SMALL).fit(fit)
    rewards = np.concatenate([t.rewards for t in fit]).astype(np.float64)
    assert detector.reward_scale_ == pytest.approx(rewards.std(), rel=1e-12)


def test_fitting_is_reproducible_and_the_rounds_reduce_the_loss():
    fit = SPLITS["continuous"][0]
    params = {"policy": POLICIES["continuous"], "n_members": 2, "iterations": 8, "epochs": 3}
    one = DETECTORS.get("fqe_td")(**params).fit(fit)
    two = DETECTORS.get("fqe_td")(**params).fit(fit)
    assert one.training_losses_ == two.training_losses_
    assert len(one.training_losses_) == 8
    assert one.training_losses_[-1] < one.training_losses_[0]


def test_actions_of_another_kind_than_the_policys_are_refused():
    discrete_data = SPLITS["discrete"][0]
    with pytest.raises(ConfigError, match="continuous actions of size 2"):
        DETECTORS.get("fqe_td")(policy=POLICIES["continuous"], **SMALL).fit(discrete_data)


@pytest.mark.parametrize("env_id", list(PIPELINE_DIRS))
def test_it_fits_and_scores_on_every_environment_with_its_committed_policy(env_id):
    policy_file = policy_path(env_id, ROOT)
    adapter, policy = ENVIRONMENTS.get(env_id)(), load_policy(policy_file)
    streams = collect(adapter, policy, [70_000, 70_001], 40).trajectories()
    detector = DETECTORS.get("fqe_td")(policy=str(policy_file), **SMALL).fit(streams[:1])
    assert detector.latency == 1
    scores = detector.score(streams[1]).scores
    assert scores.shape == (40,) and np.isfinite(scores).all()
