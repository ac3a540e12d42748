"""Online injectors: faults that act inside the live rollout, so the policy reacts (SPEC §4).

The collector calls a `Fault` on labelled steps only, and a fault stays active to the end of the
stream, across episode resets. The three dynamics faults are one `ScalingFault` with different
factor schedules and step conditions; it scales the increment of the adapter's state vector
(SPEC §11), not of the observation. Severity 0 changes nothing: the stuck actuator never holds
and a scaling factor of exactly 1 writes nothing back, so the clean stream is reproduced exactly.
Every fault works with discrete and continuous actions alike.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.core.injector import Fault, OnlineInjector
from oodrl.core.spec import AnomalySpec
from oodrl.errors import ConfigError
from oodrl.validation import Interval, IsNone

#: SPEC §4's gain of the dynamics faults: factor = 1 + DYNAMICS_GAIN · σ (per environment: `gain`).
DYNAMICS_GAIN = 1.5


class StuckFault(Fault):
    """Holds the action commanded at the first labelled step (the whole vector, for continuous
    actions); executes it with probability p."""

    def __init__(self, probability: float, rng: np.random.Generator) -> None:
        self.probability = probability
        self.rng = rng
        self.held: np.ndarray | None = None

    def before_step(self, t: int, commanded: np.ndarray, sim: SimulatorHandle) -> np.ndarray:
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
    """Multiplies the increment of the simulator's state vector over a step by `factor(t)`.

    The state is read before the step and after it, and `before + factor · (after − before)` is
    written back, so the policy and the physics both continue from it. The state vector is the
    adapter's (LunarLander: the six body coordinates of the observation; leg contacts are then
    whatever the simulator computes). A reset happens between steps, so no increment spans one.
    Steps where `applies(commanded)` is false, or the factor is exactly 1, are left untouched:
    nothing is read or written.
    """

    def __init__(
        self,
        factor: Callable[[int], float],
        applies: Callable[[np.ndarray], bool] | None = None,
    ) -> None:
        self.factor = factor
        self.applies = applies
        self._before: np.ndarray | None = None

    def before_step(self, t: int, commanded: np.ndarray, sim: SimulatorHandle) -> np.ndarray:
        scales = self.factor(t) != 1.0 and (self.applies is None or self.applies(commanded))
        self._before = sim.read_state() if scales else None
        return commanded

    def after_step(
        self, t: int, observation: np.ndarray, commanded: np.ndarray, sim: SimulatorHandle
    ) -> np.ndarray:
        if self._before is None:
            return observation
        before, self._before = self._before, None
        increment = sim.increment(before, sim.read_state())
        return sim.write_state(before + self.factor(t) * increment)


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
    """applies(commanded) = the commanded discrete action is `action`."""

    def __init__(self, action: int) -> None:
        self.action = action

    def __call__(self, commanded: np.ndarray) -> bool:
        return int(commanded) == self.action


class _ComponentAbove:
    """applies(commanded) = coordinate `dim` of the commanded action vector exceeds `threshold`."""

    def __init__(self, dim: int, threshold: float) -> None:
        self.dim, self.threshold = dim, threshold

    def __call__(self, commanded: np.ndarray) -> bool:
        return bool(commanded[self.dim] > self.threshold)


class ScalingInjector(OnlineInjector):
    """The dynamics faults: state increments scaled by up to `1 + gain·σ` (SPEC §4: gain 1.5).

    `gain` is a per-environment choice (SPEC §11): where the physics cannot take the full
    factor (HalfCheetah's simulation diverges above about 1.3), the environment's params lower it.
    """

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "gain": [Interval(float, 0, None, closed="neither")],
    }

    def __init__(self, *, severity: float | None = None, gain: float = DYNAMICS_GAIN) -> None:
        super().__init__(severity=severity)
        self.gain = gain

    def full_factor(self, severity: float) -> float:
        """The increment factor at a severity: 1 + gain·σ."""
        return 1.0 + self.gain * severity


class DynamicsScaling(ScalingInjector):
    """After each labelled step the state increment is multiplied by 1 + gain·σ."""

    name: ClassVar[str] = "dynamics_scaling"

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return ScalingFault(_Constant(self.full_factor(spec.severity)))


class ActionConditionedDynamics(ScalingInjector):
    """As `dynamics_scaling`, only on steps where a predicate on the commanded action holds.

    Discrete actions: the action is `target_action` (LunarLander: 2, main engine). Continuous
    actions: coordinate `target_dim` of the action vector is above `target_threshold`. Set the
    parameters of one kind and leave the others None; `check_adapter` checks them against the
    environment's action space.
    """

    name: ClassVar[str] = "action_conditioned_dynamics"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        **ScalingInjector._parameter_constraints,
        "target_action": [IsNone(), Interval(int, 0, None)],
        "target_dim": [IsNone(), Interval(int, 0, None)],
        "target_threshold": [IsNone(), Interval(float, None, None)],
    }

    def __init__(
        self,
        *,
        severity: float | None = None,
        gain: float = DYNAMICS_GAIN,
        target_action: int | None = None,
        target_dim: int | None = None,
        target_threshold: float | None = None,
    ) -> None:
        super().__init__(severity=severity, gain=gain)
        self.target_action = target_action
        self.target_dim = target_dim
        self.target_threshold = target_threshold

    def _validate_extra(self) -> None:
        # Which kind of predicate applies is the environment's to say (`check_adapter`); a
        # mixture of the two kinds, or half of the continuous one, is wrong everywhere.
        continuous = (self.target_dim, self.target_threshold)
        mixed = self.target_action is not None and continuous != (None, None)
        if mixed or continuous.count(None) == 1:
            raise ConfigError(
                f"{type(self).__name__} takes either 'target_action' (discrete actions) or both "
                "'target_dim' and 'target_threshold' (continuous actions), the others null. "
                f"Got target_action={self.target_action!r}, target_dim={self.target_dim!r}, "
                f"target_threshold={self.target_threshold!r} instead."
            )

    def check_adapter(self, adapter: EnvironmentAdapter) -> None:
        """Refuse a predicate the environment's action space cannot evaluate."""
        self.validate_params()
        if adapter.action_kind == "discrete":
            self._check_discrete(adapter)
        else:
            self._check_continuous(adapter)

    def _check_discrete(self, adapter: EnvironmentAdapter) -> None:
        n = adapter.action_size
        if self.target_action is None or not 0 <= self.target_action < n:
            raise ConfigError(
                f"The 'target_action' parameter of {type(self).__name__} must be an action of "
                f"{adapter.env_id}, an int in the range [0, {n}), with 'target_dim' and "
                f"'target_threshold' null ({adapter.env_id} has {adapter.describe_actions()}). "
                f"Got {self.target_action!r} instead."
            )

    def _check_continuous(self, adapter: EnvironmentAdapter) -> None:
        size = adapter.action_size
        if self.target_dim is None or not 0 <= self.target_dim < size:
            raise ConfigError(
                f"The 'target_dim' parameter of {type(self).__name__} must be a coordinate of "
                f"{adapter.env_id}'s action vector, an int in the range [0, {size}), with "
                f"'target_threshold' set and 'target_action' null ({adapter.env_id} has "
                f"{adapter.describe_actions()}). Got {self.target_dim!r} instead."
            )
        low = float(adapter.action_low[self.target_dim])
        high = float(adapter.action_high[self.target_dim])
        # A threshold outside the action bounds makes the predicate always or never true.
        if not low <= self.target_threshold < high:
            raise ConfigError(
                f"The 'target_threshold' parameter of {type(self).__name__} must be a float in "
                f"the range [{low}, {high}) of {adapter.env_id}'s action coordinate "
                f"{self.target_dim}. Got {self.target_threshold!r} instead."
            )

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        if self.target_action is not None:
            applies = _CommandedIs(self.target_action)
        else:
            applies = _ComponentAbove(self.target_dim, self.target_threshold)
        return ScalingFault(_Constant(self.full_factor(spec.severity)), applies)


class GradualDrift(ScalingInjector):
    """As `dynamics_scaling`, the factor ramping linearly from 1 at the onset to 1 + gain·σ over
    `ramp_steps` steps, then constant."""

    name: ClassVar[str] = "gradual_drift"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        **ScalingInjector._parameter_constraints,
        "ramp_steps": [Interval(int, 1, None)],
    }

    def __init__(
        self, *, severity: float | None = None, gain: float = DYNAMICS_GAIN, ramp_steps: int = 200
    ) -> None:
        super().__init__(severity=severity, gain=gain)
        self.ramp_steps = ramp_steps

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        end = self.full_factor(spec.severity)
        return ScalingFault(_LinearRamp(spec.onset, self.ramp_steps, end))
