"""The Trajectory contract: a fixed-length deployment stream of T steps (SPEC §1)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from oodrl.errors import ContractError


def _frozen(array: np.ndarray) -> np.ndarray:
    """A read-only view, so no detector or injector can change a trajectory in place."""
    view = array.view()
    view.flags.writeable = False
    return view


def _check_array(name: str, value: Any, ndim: tuple[int, ...], kind: str, length: int | None):
    array = np.asarray(value)
    if array.ndim not in ndim:
        raise ContractError(
            f"Trajectory field '{name}' must have {' or '.join(map(str, ndim))} dimension(s); "
            f"got shape {array.shape}."
        )
    if array.dtype.kind not in kind:
        raise ContractError(
            f"Trajectory field '{name}' has dtype {array.dtype}; allowed kinds: {kind!r} "
            "(f float, i/u integer, b bool)."
        )
    if length is not None and array.shape[0] != length:
        raise ContractError(
            f"Trajectory field '{name}' has length {array.shape[0]}; expected T = {length}."
        )
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise ContractError(f"Trajectory field '{name}' contains NaN or inf.")
    return array


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One deployment stream of exactly T steps.

    If an episode ends before T steps the collector resets the environment with the next
    deterministic seed and keeps recording; `dones[t]` marks the boundary and `next_states[t]`
    is then the terminal observation. `info` holds per-step extras of shape (T, ...) such as
    `executed_actions` and `episode_index`, and scalars such as the stream's seed.
    """

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray
    dones: np.ndarray
    info: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        states = _check_array("states", self.states, (2,), "f", None).astype(np.float32, copy=False)
        T = states.shape[0]
        if T < 1:
            raise ContractError("Trajectory field 'states' is empty; T must be >= 1.")
        actions = _check_array("actions", self.actions, (1, 2), "iuf", T)
        actions = actions.astype(np.float32 if actions.ndim == 2 else np.int64, copy=False)
        rewards = _check_array("rewards", self.rewards, (1,), "f", T).astype(np.float32, copy=False)
        next_states = _check_array("next_states", self.next_states, (2,), "f", T)
        if next_states.shape != states.shape:
            raise ContractError(
                f"Trajectory field 'next_states' has shape {next_states.shape}; "
                f"expected {states.shape} like 'states'."
            )
        dones = _check_array("dones", self.dones, (1,), "b", T)
        executed = self.info.get("executed_actions")
        if executed is not None and np.shape(executed) != actions.shape:
            raise ContractError(
                f"Trajectory info['executed_actions'] has shape {np.shape(executed)}; expected "
                f"{actions.shape} like 'actions' (one executed action per commanded one)."
            )
        info = {}
        for key, value in self.info.items():
            if isinstance(value, np.ndarray) and value.ndim >= 1:
                if value.shape[0] != T:
                    raise ContractError(
                        f"Trajectory info['{key}'] has length {value.shape[0]}; expected T = {T}."
                    )
                value = _frozen(value)
            info[key] = value
        object.__setattr__(self, "states", _frozen(states))
        object.__setattr__(self, "actions", _frozen(actions))
        object.__setattr__(self, "rewards", _frozen(rewards))
        object.__setattr__(self, "next_states", _frozen(next_states.astype(np.float32, copy=False)))
        object.__setattr__(self, "dones", _frozen(dones))
        object.__setattr__(self, "info", info)

    @property
    def T(self) -> int:  # noqa: N802 - T is the protocol's name for the horizon
        return self.states.shape[0]

    @property
    def state_dim(self) -> int:
        return self.states.shape[1]

    @property
    def executed_actions(self) -> np.ndarray:
        """The actions the simulator executed (differs from `actions` under actuator faults)."""
        return self.info.get("executed_actions", self.actions)

    def replace(self, **changes: Any) -> Trajectory:
        """A new, validated trajectory with some fields replaced."""
        return dataclasses.replace(self, **changes)


#: Per-step arrays of a trajectory set, in store order; `labels` only on perturbed sets.
STEP_FIELDS = ("states", "actions", "rewards", "next_states", "dones", "executed_actions")


@dataclass(frozen=True, eq=False)
class TrajectorySet:
    """N trajectories of equal length as stacked arrays (N, T, ...), plus labels and provenance.

    This is what collectors return and stores hold; `trajectory(i)` gives the i-th as the
    per-episode `Trajectory` contract detectors and injectors speak.
    """

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray
    dones: np.ndarray
    executed_actions: np.ndarray
    episode_index: np.ndarray
    seeds: np.ndarray
    labels: np.ndarray | None = None
    attrs: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n, T = self.states.shape[:2]
        for name in (*STEP_FIELDS, "episode_index", "labels"):
            value = getattr(self, name)
            if value is not None and value.shape[:2] != (n, T):
                raise ContractError(
                    f"TrajectorySet field '{name}' has shape {value.shape}; "
                    f"expected ({n}, {T}, ...)."
                )
        if self.executed_actions.shape != self.actions.shape:
            raise ContractError(
                f"TrajectorySet 'executed_actions' has shape {self.executed_actions.shape}; "
                f"expected {self.actions.shape} like 'actions'."
            )
        if self.seeds.shape != (n,):
            raise ContractError(
                f"TrajectorySet 'seeds' has shape {self.seeds.shape}; expected ({n},)."
            )

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def T(self) -> int:  # noqa: N802
        return self.states.shape[1]

    def trajectory(self, i: int) -> Trajectory:
        return Trajectory(
            states=self.states[i],
            actions=self.actions[i],
            rewards=self.rewards[i],
            next_states=self.next_states[i],
            dones=self.dones[i],
            info={
                "executed_actions": self.executed_actions[i],
                "episode_index": self.episode_index[i],
                "seed": int(self.seeds[i]),
            },
        )

    def trajectories(self) -> list[Trajectory]:
        return [self.trajectory(i) for i in range(len(self))]

    def subset(self, indices: np.ndarray | list[int]) -> TrajectorySet:
        index = np.asarray(indices, dtype=np.int64)
        take = {
            name: getattr(self, name)[index] for name in (*STEP_FIELDS, "episode_index", "seeds")
        }
        labels = None if self.labels is None else self.labels[index]
        return TrajectorySet(**take, labels=labels, attrs=dict(self.attrs))
