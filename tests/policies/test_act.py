"""The policy step: prepared layers and the certified argmax act exactly as the exact step."""

from __future__ import annotations

import copy
import pickle
from pathlib import Path

import numpy as np
import pytest

from oodrl import numerics
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import BLOCK_SIZE, collect
from oodrl.policies.act import ArgmaxPolicy, policy_from_checkpoint
from oodrl.policies.load import load_policy
from oodrl.suite.environments import PIPELINE_DIRS, policy_path

ROOT = Path(__file__).resolve().parents[2]
FIELDS = (
    "states",
    "actions",
    "executed_actions",
    "rewards",
    "next_states",
    "dones",
    "episode_index",
)


def old_step(policy):
    """The policy as it acted before prepared layers: `numerics.linear` in every layer, every
    output rounded, then the argmax or the squashing."""
    old = copy.copy(policy)  # a copy leaves the prepared layers out (`__getstate__`)
    old._affine = [
        lambda x, w=layer.weight, b=layer.bias: numerics.linear(x, w, b) for layer in old.layers
    ]
    old._certified_argmax = None
    return old


@pytest.mark.parametrize("env_id", list(PIPELINE_DIRS))  # every environment of the suite
def test_collection_with_the_new_step_equals_the_old_step(env_id):
    policy = load_policy(policy_path(env_id, ROOT))
    seeds = range(BLOCK_SIZE + 4)  # a full block and a partial one
    new = collect(ENVIRONMENTS.get(env_id)(), policy, seeds, 40)
    old = collect(ENVIRONMENTS.get(env_id)(), old_step(policy), seeds, 40)
    for field in FIELDS:
        a, b = getattr(new, field), getattr(old, field)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), field


def identity_policy(activation: str = "relu") -> ArgmaxPolicy:
    """q = relu(x) for 2-dim observations: the actions tie wherever x_0 = x_1 > 0."""
    eye, zero = np.eye(2, dtype=np.float32), np.zeros(2, np.float32)
    state = {"0.weight": eye, "0.bias": zero, "1.weight": eye, "1.bias": zero}
    return policy_from_checkpoint({"kind": "mlp", "activation": activation}, state)


def test_an_undecided_row_takes_the_exact_path(monkeypatch):
    policy = identity_policy()
    obs = np.array([[2.0, 1.0], [1.0, 1.0], [1.0, 3.0]], np.float32)
    _, decided = policy._certified_argmax(obs)
    assert decided.tolist() == [True, False, True]  # the tie is within any bound
    exact_rows = []
    exact_act = policy.exact_act

    def spy(observations, rngs=None):
        exact_rows.append(np.array(observations))
        return exact_act(observations, rngs)

    monkeypatch.setattr(policy, "exact_act", spy)
    actions = policy.act(obs)
    assert actions.tolist() == [0, 0, 1]  # the tie: np.argmax's first index, as exactly
    assert actions.dtype == np.int64
    assert len(exact_rows) == 1
    np.testing.assert_array_equal(exact_rows[0], obs[1:2])
    np.testing.assert_array_equal(actions, old_step(policy).act(obs))


def test_near_ties_are_decided_only_where_certain():
    # Outputs 1 ulp of float32 apart, or apart by far less than the hidden layers' rounding:
    # whatever the bound leaves decided must be the exact argmax.
    rng = np.random.default_rng(0)
    state = {
        "0.weight": rng.standard_normal((64, 6)).astype(np.float32),
        "0.bias": rng.standard_normal(64).astype(np.float32),
        "1.weight": rng.standard_normal((3, 64)).astype(np.float32),
        "1.bias": np.zeros(3, np.float32),
    }
    state["1.weight"][1] = state["1.weight"][0]
    state["1.weight"][1, 0] = np.nextafter(state["1.weight"][0, 0], np.float32(np.inf))
    policy = policy_from_checkpoint({"kind": "mlp"}, state)
    obs = rng.standard_normal((2000, 6)).astype(np.float32)
    actions, decided = policy._certified_argmax(obs)
    exact = old_step(policy).act(obs)
    np.testing.assert_array_equal(actions[decided], exact[decided])
    outputs = policy.outputs(obs)
    top_two = outputs[:, :2].max(axis=1) >= outputs[:, 2]
    assert not decided[top_two].any()  # rows 0 and 1 differ by less than the bound
    np.testing.assert_array_equal(policy.act(obs), exact)


def test_non_finite_or_overflowing_rows_are_undecided():
    policy = identity_policy()
    obs = np.array([[np.inf, 1.0], [np.nan, 1.0], [3e38, 1.0], [2.0, 1.0]], np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        _, decided = policy._certified_argmax(obs)
        assert decided.tolist() == [False, False, False, True]
        np.testing.assert_array_equal(policy.act(obs), old_step(policy).act(obs))


def test_noisy_mode_and_tanh_activations_act_exactly():
    noisy = load_policy(ROOT / "models/policy.pt", mode="noisy")
    assert noisy._certified_argmax is None
    assert identity_policy("tanh")._certified_argmax is None


def test_a_pickled_policy_leaves_its_prepared_layers_out():
    # Fitted detectors pickle the policy they hold: acting must not change their bytes.
    policy = load_policy(ROOT / "models/policy.pt")
    before = pickle.dumps(policy, protocol=5)
    obs = np.random.default_rng(0).normal(size=(20, 8)).astype(np.float32)
    actions = policy.act(obs)
    assert "_affine" in vars(policy) and "_certified_argmax" in vars(policy)
    assert pickle.dumps(policy, protocol=5) == before
    np.testing.assert_array_equal(pickle.loads(before).act(obs), actions)
