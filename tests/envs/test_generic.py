"""Generic adapters (SPEC §18): any Gymnasium id outside the suite, with the faults it supports."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from rollout_policies import LinearPolicy

from oodrl.core.spec import AnomalySpec
from oodrl.envs import ENVIRONMENTS, GENERIC_ADAPTER
from oodrl.envs.collect import collect
from oodrl.envs.generic import GenericAdapter, probe_state
from oodrl.envs.mujoco import HopperAdapter, MujocoHandle
from oodrl.errors import ContractError, RegistryError
from oodrl.injectors import INJECTORS
from oodrl.injectors.online import DynamicsScaling
from oodrl.suite.new import fault_support

#: id: (action kind, action size, observation size), as gymnasium documents them.
OUTSIDE = {
    "InvertedPendulum-v5": ("continuous", 1, 4),
    "Swimmer-v5": ("continuous", 2, 8),
    "MountainCarContinuous-v0": ("continuous", 1, 2),
    "MountainCar-v0": ("discrete", 3, 2),
}
DYNAMICS = ("action_conditioned_dynamics", "dynamics_scaling", "gradual_drift")


@pytest.mark.parametrize("env_id", OUTSIDE)
def test_any_gymnasium_id_gets_a_generic_adapter_with_facts_from_its_spaces(env_id):
    adapter = ENVIRONMENTS.get(env_id)()
    assert isinstance(adapter, GenericAdapter) and adapter.env_id == env_id
    assert ENVIRONMENTS.path(env_id) == GENERIC_ADAPTER
    assert (adapter.action_kind, adapter.action_size, adapter.state_dim) == OUTSIDE[env_id]
    again = pickle.loads(pickle.dumps(adapter))  # collection's worker processes get a copy
    assert type(again) is type(adapter) and again.env_id == env_id


def test_the_suite_keeps_its_own_adapters():
    assert ENVIRONMENTS.get("Hopper-v5") is HopperAdapter
    assert "InvertedPendulum-v5" not in ENVIRONMENTS.names()


def test_an_unknown_id_is_one_line_naming_the_suite_and_gymnasium():
    with pytest.raises(RegistryError) as info:
        ENVIRONMENTS.get("InvertedPendulm-v5")
    message = str(info.value)
    assert "\n" not in message and "gymnasium" in message and "Hopper-v5" in message


def test_an_image_observation_is_refused_in_one_line():
    with pytest.raises(ContractError, match="flat Box observation") as info:
        ENVIRONMENTS.get("CarRacing-v3")().make()
    assert "\n" not in str(info.value) and "image" in str(info.value)


@pytest.mark.parametrize("env_id", ["InvertedPendulum-v5", "Swimmer-v5"])
def test_mujoco_environments_get_every_fault_through_qpos_qvel(env_id):
    adapter = ENVIRONMENTS.get(env_id)()
    env = adapter.make()
    assert isinstance(adapter.handle(env), MujocoHandle)
    env.close()
    assert probe_state(adapter) is None
    assert fault_support(adapter, INJECTORS.names()) == dict.fromkeys(INJECTORS.names())


def test_the_suite_keeps_every_fault():
    for env_id in ("LunarLander-v3", "CartPole-v1"):
        adapter = ENVIRONMENTS.get(env_id)()
        assert fault_support(adapter, INJECTORS.names()) == dict.fromkeys(INJECTORS.names())


def test_other_environments_leave_dynamics_faults_out_with_the_reason():
    adapter = ENVIRONMENTS.get("MountainCarContinuous-v0")()
    support = fault_support(adapter, INJECTORS.names())
    assert {name for name, reason in support.items() if reason} == set(DYNAMICS)
    assert all("no state vector" in support[name] for name in DYNAMICS)
    env = adapter.make()
    with pytest.raises(ContractError, match="no state vector"):
        adapter.handle(env).read_state()
    env.close()


def test_a_state_that_does_not_make_a_twin_is_reported(monkeypatch):
    """The probe can fail: a handle whose write-back loses a coordinate is caught."""
    adapter = ENVIRONMENTS.get("InvertedPendulum-v5")()
    write = MujocoHandle.write_state

    def lossy(self, state):
        return write(self, np.where(np.arange(len(state)) == 0, 0.0, state))

    monkeypatch.setattr(MujocoHandle, "write_state", lossy)
    assert "does not read back" in probe_state(adapter)


def test_a_generic_mujoco_dynamics_fault_changes_the_rollout_from_the_onset():
    adapter = ENVIRONMENTS.get("Swimmer-v5")()
    policy, T, onset = LinearPolicy(adapter), 30, 10
    labels = np.arange(T) >= onset
    spec = AnomalySpec("dynamics_scaling", 1.0, onset, mode="online")
    fault = DynamicsScaling().fault(spec, np.random.default_rng(0))
    clean = collect(adapter, policy, [5], T)
    faulty = collect(adapter, policy, [5], T, labels=labels, faults=[fault])
    np.testing.assert_array_equal(faulty.states[0, : onset + 1], clean.states[0, : onset + 1])
    assert not np.allclose(faulty.states[0, onset + 2 :], clean.states[0, onset + 2 :])
