"""Online injectors: faults that act inside the live rollout, so the policy reacts (SPEC §4).

The collector calls a `Fault` on labelled steps only, and a fault stays active to the end of the
stream, across episode resets. The three dynamics faults are one `ScalingFault` with different
factor schedules and step conditions. Severity 0 changes nothing: the stuck actuator never holds
and a scaling factor of exactly 1 writes nothing back, so the clean stream is reproduced exactly.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import numpy as np

from oodrl.core.injector import Fault, OnlineInjector, SimulatorHandle
from oodrl.core.spec import AnomalySpec
from oodrl.errors import ConfigError
from oodrl.validation import Interval

#: Factor applied to the state increments at full severity: factor = 1 + DYNAMICS_GAIN · σ.
DYNAMICS_GAIN = 1.5


class StuckFault(Fault):
    """Holds the action commanded at the first labelled step; executes it with probability p."""

    def __init__(self, probability: float, rng: np.random.Generator) -> None:
        self.probability = probability
        self.rng = rng
        self.held: np.ndarray | None = None

    def executed_action(self, t: int, commanded: np.ndarray) -> np.ndarray:
        if self.held is None:
            self.held = np.array(commanded, copy=True)
        # One draw per step whatever the severity: the stuck steps at σ are a subset of those
        # at any larger σ, and a uniform draw in [0, 1) is never below 0.
        stuck = self.rng.random() < self.probability
        return self.held if stuck else commanded


class StuckActuator(OnlineInjector):
    """From the onset, each step executes the action commanded at the onset with probability σ.

    `actions` records what the policy commanded, `executed_actions` what the simulator ran.
    """

    name: ClassVar[str] = "stuck_actuator"

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return StuckFault(spec.severity, rng)


class ScalingFault(Fault):
    """Multiplies the simulator's state increment s_{t+1} − s_t by `factor(t)` after a step.

    The scaled state is written back into the simulator, so the policy and the physics both
    continue from it. Only coordinates the simulator can hold are written (LunarLander: 0..5);
    the others, such as leg contacts, read back as the simulator computes them. `previous` is
    the observation the policy acted on, which after a reset is the fresh reset observation, so
    no increment spans a reset. Steps where `applies(commanded)` is false, or the factor is
    exactly 1, are left untouched.
    """

    def __init__(
        self,
        factor: Callable[[int], float],
        applies: Callable[[np.ndarray], bool] | None = None,
    ) -> None:
        self.factor = factor
        self.applies = applies

    def after_step(
        self,
        t: int,
        previous: np.ndarray,
        observation: np.ndarray,
        commanded: np.ndarray,
        sim: SimulatorHandle,
    ) -> np.ndarray:
        factor = self.factor(t)
        if factor == 1.0 or (self.applies is not None and not self.applies(commanded)):
            return observation
        before = np.asarray(previous, dtype=np.float64)
        after = np.asarray(observation, dtype=np.float64)
        return sim.write_observation(before + factor * (after - before))


class _Constant:
    """factor(t) = value (a picklable schedule, so faults can go to worker processes)."""

    def __init__(self, value: float) -> None:
        self.value = value

    def __call__(self, t: int) -> float:
        return self.value


class _LinearRamp:
    """factor(t) rises linearly from 1 at `start` to `end` at `start + steps`, then stays."""

    def __init__(self, start: int, steps: int, end: float) -> None:
        self.start, self.steps, self.end = start, steps, end

    def __call__(self, t: int) -> float:
        progress = min(1.0, max(0, t - self.start) / self.steps)
        return 1.0 + (self.end - 1.0) * progress


class _CommandedIs:
    """applies(commanded) = the commanded action is `action`."""

    def __init__(self, action: int) -> None:
        self.action = action

    def __call__(self, commanded: np.ndarray) -> bool:
        return int(commanded) == self.action


def full_factor(severity: float) -> float:
    """The dynamics faults' increment factor at a severity: 1 + 1.5σ."""
    return 1.0 + DYNAMICS_GAIN * severity


class DynamicsScaling(OnlineInjector):
    """After each labelled step the state increment is multiplied by 1 + 1.5σ."""

    name: ClassVar[str] = "dynamics_scaling"

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return ScalingFault(_Constant(full_factor(spec.severity)))


class ActionConditionedDynamics(OnlineInjector):
    """As `dynamics_scaling`, only on steps whose commanded action is `target_action`.

    `target_action` is a discrete action index (LunarLander: 2, main engine); it is checked
    against the environment's number of actions when the fault runs (`check_adapter`).
    """

    name: ClassVar[str] = "action_conditioned_dynamics"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "target_action": [Interval(int, 0, None)],
    }

    def __init__(self, *, severity: float | None = None, target_action: int = 2) -> None:
        super().__init__(severity=severity)
        self.target_action = target_action

    def check_adapter(self, adapter) -> None:
        """Refuse a target action the environment does not have."""
        n_actions = adapter.n_actions
        if not 0 <= self.target_action < n_actions:
            raise ConfigError(
                f"The 'target_action' parameter of {type(self).__name__} must be an action of "
                f"{adapter.env_id}, an int in the range [0, {n_actions}). "
                f"Got {self.target_action!r} instead."
            )

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return ScalingFault(_Constant(full_factor(spec.severity)), _CommandedIs(self.target_action))


class GradualDrift(OnlineInjector):
    """As `dynamics_scaling`, the factor ramping linearly from 1 at the onset to 1 + 1.5σ over
    `ramp_steps` steps, then constant."""

    name: ClassVar[str] = "gradual_drift"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "ramp_steps": [Interval(int, 1, None)],
    }

    def __init__(self, *, severity: float | None = None, ramp_steps: int = 200) -> None:
        super().__init__(severity=severity)
        self.ramp_steps = ramp_steps

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return ScalingFault(_LinearRamp(spec.onset, self.ramp_steps, full_factor(spec.severity)))
