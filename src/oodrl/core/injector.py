"""The BaseAnomalyInjector contract: post-hoc perturbations and online fault hooks (SPEC §1, §4).

Injectors act only on labelled steps (onset <= t < offset). Post-hoc injectors rewrite the
observation stream of a copy of a clean trajectory; online injectors hand the collector a
`Fault` whose hooks run inside the live rollout, so the policy reacts to the fault.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import ClassVar

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.core.spec import AnomalySpec
from oodrl.core.trajectory import Trajectory
from oodrl.errors import ContractError
from oodrl.validation import Component, Interval, IsNone


class BaseAnomalyInjector(Component):
    """Common parameters: `severity` (None = use the protocol's headline `anomaly.severity`)."""

    name: ClassVar[str] = ""
    mode: ClassVar[str] = ""

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "severity": [IsNone(), Interval(float, 0, 1, closed="both")],
    }

    def __init__(self, *, severity: float | None = None) -> None:
        self.severity = severity

    @property
    def injector_name(self) -> str:
        return self.name or type(self).__name__

    def check_adapter(self, adapter: EnvironmentAdapter) -> None:
        """Refuse parameters the environment cannot honour (e.g. an action it lacks).

        Called when params are validated and before collection.
        """

    def spec(self, severity: float, onset: int, offset: int | None = None) -> AnomalySpec:
        """The AnomalySpec of this injector at a severity (its own parameters recorded).

        A parameter left at None does not apply to this run (a discrete environment's
        `action_conditioned_dynamics` has no `target_dim`), so it is not part of the spec.
        """
        params = {k: v for k, v in self.get_params().items() if k != "severity" and v is not None}
        return AnomalySpec(self.injector_name, severity, onset, offset, self.mode, params)


class PostHocInjector(BaseAnomalyInjector):
    """Perturbs the observation stream of a recorded trajectory.

    The stream is `states` followed by the last `next_states` row: (T + 1, d). When the stream
    changes at step t, `states[t]` and `next_states[t - 1]` carry the same value unless an
    episode ended at t - 1 (then `next_states[t - 1]` is a terminal observation, kept).
    Actions and rewards are never touched.
    """

    mode: ClassVar[str] = "posthoc"

    @abstractmethod
    def _perturb(
        self, stream: np.ndarray, labels: np.ndarray, spec: AnomalySpec, rng: np.random.Generator
    ) -> np.ndarray:
        """The perturbed (T + 1, d) stream; rows with labels False must stay unchanged."""

    def inject(
        self, trajectory: Trajectory, spec: AnomalySpec, rng: np.random.Generator
    ) -> tuple[Trajectory, np.ndarray]:
        labels = spec.labels(trajectory.T)
        stream = np.concatenate([trajectory.states, trajectory.next_states[-1:]]).astype(np.float32)
        stream_labels = np.append(labels, labels[-1])
        perturbed = np.asarray(
            self._perturb(stream.copy(), stream_labels, spec, rng), dtype=np.float32
        )
        if perturbed.shape != stream.shape:
            raise ContractError(
                f"Injector '{self.injector_name}' returned a stream of shape {perturbed.shape}; "
                f"expected {stream.shape}."
            )
        if not np.array_equal(perturbed[~stream_labels], stream[~stream_labels]):
            raise ContractError(f"Injector '{self.injector_name}' changed unlabelled steps.")
        states = perturbed[:-1]
        next_states = np.array(trajectory.next_states, copy=True)
        continuing = ~trajectory.dones
        next_states[continuing] = perturbed[1:][continuing]
        return trajectory.replace(states=states, next_states=next_states), labels


class Fault:
    """A live fault for one deployment stream; the collector calls it on labelled steps only.

    Default hooks do nothing, so a subclass overrides only the hook its fault needs. `commanded`
    is the policy's action: an int64 index, or a float32 vector for continuous actions.
    """

    def before_step(self, t: int, commanded: np.ndarray, sim: SimulatorHandle) -> np.ndarray:
        """Called before `env.step` at step t; returns the action the simulator executes."""
        return commanded

    def after_step(
        self, t: int, observation: np.ndarray, commanded: np.ndarray, sim: SimulatorHandle
    ) -> np.ndarray:
        """Called after `env.step` at step t; returns the observation the policy sees next
        (writing the simulator's state through `sim` if the fault changes the dynamics)."""
        return observation

    def after_reset(self, t: int, observation: np.ndarray, sim: SimulatorHandle) -> np.ndarray:
        """Called when the episode that ended at step t resets; returns the observation the
        policy sees first in the new episode (a faulty sensor reports it too)."""
        return observation


class OnlineInjector(BaseAnomalyInjector):
    """Makes a `Fault` per deployment stream; randomness comes from `rng`."""

    mode: ClassVar[str] = "online"

    @abstractmethod
    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        """A fresh fault for one stream."""
