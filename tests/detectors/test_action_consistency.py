"""action_consistency: the share of 8 fixed small observation perturbations that change the
policy's greedy action (discrete), or the RMS action change over them (continuous)."""

from pathlib import Path

import numpy as np
import pytest
import torch

from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.detectors.action_consistency import N_PERTURBATIONS, ActionConsistency
from oodrl.errors import ConfigError
from oodrl.policies.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION
from oodrl.testing import check_detector, linear_system_policy, linear_system_trajectories

#: The data of the registered detectors' contract tests (tests/detectors/test_contract.py).
DATA = {
    "discrete": linear_system_trajectories(10, T=120, episode_length=80, seed=0),
    "continuous": linear_system_trajectories(10, T=120, action_dim=2, seed=0),
}


def write_policy(path: Path, weight, architecture: dict) -> str:
    """A one-layer oodrl checkpoint: outputs = weight @ s (no bias)."""
    weight = torch.tensor(np.asarray(weight), dtype=torch.float32)
    checkpoint = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "architecture": architecture,
        "state_dict": {"net.0.weight": weight, "net.0.bias": torch.zeros(len(weight))},
    }
    torch.save(checkpoint, path)
    return str(path)


def stream(states) -> Trajectory:
    states = np.asarray(states, dtype=np.float32)
    return Trajectory(
        states=states,
        actions=np.zeros(len(states), dtype=np.int64),
        rewards=np.zeros(len(states), np.float32),
        next_states=states,
        dones=np.zeros(len(states), bool),
    )


#: Fit observations: 2 features of standard deviation ≈ 1 and ≈ 2.
FIT = [stream(np.random.default_rng([7, i]).standard_normal((200, 2)) * [1.0, 2.0]) for i in (0, 1)]


@pytest.fixture(scope="module")
def policies(tmp_path_factory):
    directory = tmp_path_factory.mktemp("action-consistency-policies")
    bounds = {"action_low": [-10.0], "action_high": [10.0]}
    return {
        "discrete": str(linear_system_policy(directory / "discrete.pt")),
        "continuous": str(linear_system_policy(directory / "continuous.pt", action_dim=2)),
        # Action 0 where s_0 > 0, else action 1: the decision boundary is s_0 = 0.
        "boundary": write_policy(directory / "boundary.pt", [[1, 0], [-1, 0]], {"kind": "mlp"}),
        "one_action": write_policy(directory / "one.pt", [[1, 0]], {"kind": "mlp"}),
        # a = clip(s_0 + 0.5 s_1, ±10): linear inside the bounds, constant far outside them.
        "actor": write_policy(
            directory / "actor.pt", [[1.0, 0.5]], {"kind": "clipped_actor", **bounds}
        ),
    }


@pytest.mark.parametrize("actions", ["discrete", "continuous"])
def test_contract(actions, policies):
    data = DATA[actions]
    check_detector(
        lambda: ActionConsistency(policy=policies[actions]), data[:6], data[6:8], data[8:]
    )


def test_perturbations_are_antithetic_sign_vectors_in_units_of_the_fit_spread(policies):
    detector = ActionConsistency(policy=policies["boundary"], scale=0.2).fit(FIT)
    spread = np.concatenate([t.states for t in FIT]).astype(np.float64).std(axis=0)
    deltas = detector.perturbations_
    assert deltas.shape == (N_PERTURBATIONS, 2)
    np.testing.assert_array_equal(deltas[:4], -deltas[4:])
    np.testing.assert_allclose(np.abs(deltas), np.broadcast_to(0.2 * spread, deltas.shape))


def test_a_nearby_decision_boundary_scores_high_and_a_distant_one_zero(policies):
    detector = ActionConsistency(policy=policies["boundary"]).fit(FIT)
    reach = abs(detector.perturbations_[0, 0])  # how far every perturbation moves s_0
    assert 0.05 < reach < 0.15
    near = stream([[0.3 * reach, 1.0], [-0.5 * reach, -2.0], [0.9 * reach, 0.0]])
    far = stream([[5.0, 1.0], [-3.0, 4.0], [2 * reach, 0.0], [-1.5 * reach, 1.0]])
    # Near the boundary, one perturbation of each antithetic pair crosses it: ½ change.
    np.testing.assert_array_equal(detector.score(near).scores, [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(detector.score(far).scores, [0.0, 0.0, 0.0, 0.0])


def test_continuous_score_is_the_rms_action_change(policies):
    detector = ActionConsistency(policy=policies["actor"]).fit(FIT)
    gain = np.array([1.0, 0.5])
    inside = stream([[0.0, 0.0], [1.0, -2.0], [3.0, 1.0]])
    expected = np.sqrt(np.mean((detector.perturbations_ @ gain) ** 2))
    np.testing.assert_allclose(detector.score(inside).scores, expected, rtol=1e-4)
    # Far beyond the clipping bound every perturbed action is the bound: no change.
    saturated = stream([[40.0, 0.0], [-50.0, 3.0]])
    np.testing.assert_array_equal(detector.score(saturated).scores, [0.0, 0.0])


def test_deterministic_across_fits_and_seeded(policies):
    data = DATA["discrete"]
    one = ActionConsistency(policy=policies["discrete"]).fit(data[:6])
    two = ActionConsistency(policy=policies["discrete"]).fit(data[:6])
    np.testing.assert_array_equal(one.perturbations_, two.perturbations_)
    for a, b in zip(one.score_many(data[8:]), two.score_many(data[8:]), strict=True):
        np.testing.assert_array_equal(a.scores, b.scores)
    other = ActionConsistency(policy=policies["discrete"], seed=1).fit(data[:6])
    assert not np.array_equal(other.perturbations_, one.perturbations_)


def test_a_constant_feature_is_not_perturbed(policies):
    constant = [
        t.replace(states=np.c_[t.states[:, :1], np.full((t.T, 1), 3.0, np.float32)]) for t in FIT
    ]
    detector = ActionConsistency(policy=policies["boundary"]).fit(constant)
    assert np.all(detector.perturbations_[:, 1] == 0)
    assert np.all(detector.perturbations_[:, 0] != 0)


def test_scores_are_shares_of_eight_on_the_contract_data(policies):
    data = DATA["discrete"]
    detector = ActionConsistency(policy=policies["discrete"]).fit(data[:6])
    scores = np.concatenate([o.scores for o in detector.score_many(data[6:])])
    assert set(np.unique(scores * N_PERTURBATIONS)) <= set(range(N_PERTURBATIONS + 1))
    assert 0 < scores.mean() < 0.5


def test_refuses_a_one_action_policy_and_a_bad_scale(policies):
    with pytest.raises(ConfigError, match="has one action"):
        ActionConsistency(policy=policies["one_action"]).fit(FIT)
    with pytest.raises(ConfigError, match="'scale' parameter of ActionConsistency"):
        ActionConsistency(policy=policies["boundary"], scale=0.0).fit(FIT)


def test_params_name_it_by_its_path():
    cls = DETECTORS.get("oodrl.detectors.action_consistency:ActionConsistency")
    assert cls is ActionConsistency and cls.name == "action_consistency"
    assert cls.uses_torch and cls.row_independent and cls().latency == 0
