import numpy as np
import pytest

from oodrl.core import (
    AnomalySpec,
    DetectorOutput,
    Trajectory,
    TrajectorySet,
    default_onset,
    make_labels,
)
from oodrl.errors import ContractError


def _fields(T=10, d=3):  # noqa: N803
    rng = np.random.default_rng(0)
    return {
        "states": rng.normal(size=(T, d)).astype(np.float32),
        "actions": rng.integers(0, 4, T),
        "rewards": rng.normal(size=T).astype(np.float32),
        "next_states": rng.normal(size=(T, d)).astype(np.float32),
        "dones": np.zeros(T, bool),
    }


def test_valid_trajectory_is_read_only():
    traj = Trajectory(**_fields())
    assert traj.T == 10 and traj.state_dim == 3
    assert traj.actions.dtype == np.int64
    with pytest.raises(ValueError):
        traj.states[0, 0] = 1.0
    np.testing.assert_array_equal(traj.executed_actions, traj.actions)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("states", np.zeros(10, np.float32), "'states' must have 2"),
        ("actions", np.zeros(9, np.int64), "'actions' has length 9"),
        ("rewards", np.full(10, np.nan, np.float32), "'rewards' contains NaN"),
        ("next_states", np.zeros((10, 4), np.float32), "'next_states' has shape"),
        ("dones", np.zeros(10, np.float32), "'dones' has dtype float32"),
        ("states", np.full((10, 3), np.inf, np.float32), "'states' contains NaN or inf"),
    ],
)
def test_invalid_trajectory_names_the_field(field, value, message):
    fields = _fields()
    fields[field] = value
    with pytest.raises(ContractError, match=message):
        Trajectory(**fields)


def test_info_arrays_must_span_T():
    with pytest.raises(ContractError, match="info\\['executed_actions'\\]"):
        Trajectory(**_fields(), info={"executed_actions": np.zeros(3, np.int64)})


def test_continuous_actions_are_float32_vectors_and_never_rounded():
    fields = {**_fields(), "actions": np.linspace(-1, 1, 20).reshape(10, 2)}
    traj = Trajectory(**fields, info={"executed_actions": np.zeros((10, 2), np.float32)})
    assert traj.actions.dtype == np.float32 and traj.actions.shape == (10, 2)
    np.testing.assert_array_equal(traj.actions, fields["actions"].astype(np.float32))
    with pytest.raises(ContractError, match="executed_actions'\\] has shape \\(10,\\)"):
        Trajectory(**fields, info={"executed_actions": np.zeros(10, np.int64)})


def test_a_set_needs_one_executed_action_per_commanded_one():
    n, T, d = 2, 5, 3  # noqa: N806
    arrays = {
        "states": np.zeros((n, T, d), np.float32),
        "actions": np.zeros((n, T, 2), np.float32),
        "rewards": np.zeros((n, T), np.float32),
        "next_states": np.zeros((n, T, d), np.float32),
        "dones": np.zeros((n, T), bool),
        "episode_index": np.zeros((n, T), np.int32),
        "seeds": np.arange(n),
    }
    assert TrajectorySet(**arrays, executed_actions=np.zeros((n, T, 2), np.float32))
    with pytest.raises(ContractError, match="'executed_actions' has shape \\(2, 5\\)"):
        TrajectorySet(**arrays, executed_actions=np.zeros((n, T), np.int64))


def test_labels_and_default_onset():
    assert default_onset(500) == 166
    labels = make_labels(10, 3, 7)
    np.testing.assert_array_equal(np.flatnonzero(labels), [3, 4, 5, 6])
    assert make_labels(10, 4).sum() == 6
    with pytest.raises(ContractError):
        make_labels(10, 11)


def test_spec_round_trip_and_validation():
    spec = AnomalySpec("x", 0.5, 3, None, "online", {"b": 1, "a": 2})
    assert AnomalySpec.from_dict(spec.to_dict()) == spec
    assert list(spec.to_dict()["params"]) == ["a", "b"]
    with pytest.raises(ContractError, match="severity"):
        AnomalySpec("x", 1.5, 3)
    with pytest.raises(ContractError, match="mode"):
        AnomalySpec("x", 0.5, 3, mode="later")


def test_detector_output_validates():
    out = DetectorOutput(np.arange(4.0), np.array([False, False, True, True]), 2.0)
    assert out.scores.dtype == np.float64
    with pytest.raises(ContractError, match="NaN"):
        DetectorOutput(np.array([0.0, np.nan]))
    with pytest.raises(ContractError, match="alarms"):
        DetectorOutput(np.arange(3.0), np.array([1, 0, 1]))
