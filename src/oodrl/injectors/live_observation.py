"""The five observation faults live (SPEC §15): a faulty sensor between simulator and policy.

Post-hoc injectors (`oodrl.injectors.posthoc`) rewrite a recorded stream; here the same faults
act inside the rollout, so the policy acts on what the faulty sensor reports. Conventions:

- The simulator never sees the corruption: its state, dynamics and rewards are the true ones.
- The recorded `states` and `next_states` are what the sensor reports (what the policy saw), the
  terminal observation of an episode and the first observation after a reset included (the
  collector passes both through the fault: `Fault.after_step`, `Fault.after_reset`).
- The fault acts from the onset step t*: the first corrupted observation is the one step t*
  emits (`next_states[t*]`, then `states[t* + 1]`), as for the online dynamics faults. Every
  step before t* is the clean twin's, bit for bit, and severity 0 reproduces the clean stream.
- Random draws do not depend on the severity (common random numbers), as post hoc.

Statistics. The post-hoc faults scale by per-stream statistics of the whole clean stream,
which a live sensor cannot know. The live ones take `mean` and `scale` (per observation
coordinate) as parameters: the clean in-distribution statistics (`reference_statistics` of a
clean set; the impact stage and the monitor pass those of their clean streams). Left None, they
are running statistics of the true observations since the onset (the sensor's own history,
including the current one), so a live fault is always causal; with running statistics the
first faulty step has a spread of 0, and the fault grows in as the history fills.

The two post-hoc definitions that look ahead have causal versions:

- `live_correlation_break`: the ⌈σ·d⌉ chosen coordinates (a permutation of the coordinates drawn
  once, at the onset) each report the true value of a uniformly drawn earlier step since the
  onset (the current one included): the coordinate keeps the marginal of its post-onset history
  but loses its coupling to the other coordinates and to time. Post hoc, the values come from a
  permutation of the whole post-onset window, future steps included.
- `live_regime_switch`: x' = x + (sqrt(1 + 2σ) − 1)(x − m) + 2σ·sd with m and sd the `mean` and
  `scale` (clean ID statistics; running ones if None), not the post-onset window's mean and the
  pre-onset spread.

`live_observation_delay`: the delay line starts at the fault, so for its first k steps the
sensor repeats its first faulty reading, then lags k steps (post hoc, the delay line shows
pre-onset observations, which a fault acting from the onset has not seen). It is not flushed at
a reset, as post hoc.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, ClassVar

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.core.injector import Fault, OnlineInjector
from oodrl.core.spec import AnomalySpec
from oodrl.errors import ConfigError
from oodrl.injectors.posthoc import ObservationDelay
from oodrl.validation import Interval, IsNone, SequenceOf


def reference_statistics(states: np.ndarray) -> dict[str, list[float]]:
    """`mean` and `scale` (std) per coordinate of clean observations (any leading shape)."""
    flat = np.asarray(states, dtype=np.float64).reshape(-1, np.shape(states)[-1])
    return {
        "mean": [float(v) for v in flat.mean(axis=0)],
        "scale": [float(v) for v in flat.std(axis=0)],
    }


class _Statistics:
    """Per-coordinate mean and std: fixed (reference) ones, or running ones over the true
    observations seen so far (Welford's update, the current one included)."""

    def __init__(self, mean: Any = None, scale: Any = None) -> None:
        self.fixed = None if mean is None and scale is None else (mean, scale)
        self.n, self.mean, self.m2 = 0, 0.0, 0.0

    def update(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.n += 1
        delta = x - self.mean
        self.mean = self.mean + delta / self.n
        self.m2 = self.m2 + delta * (x - self.mean)
        running = (self.mean, np.sqrt(self.m2 / self.n))
        if self.fixed is None:
            return running
        mean, scale = self.fixed
        return (
            running[0] if mean is None else np.asarray(mean, np.float64),
            running[1] if scale is None else np.asarray(scale, np.float64),
        )


class SensorFault(Fault):
    """A fault of the sensor: every observation the simulator emits after the onset goes through
    `report` (true observation in, reported observation out, same dtype)."""

    def report(self, true: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _reported(self, observation: np.ndarray) -> np.ndarray:
        true = np.asarray(observation)
        return np.asarray(self.report(true.astype(np.float64)), dtype=true.dtype)

    def after_step(
        self, t: int, observation: np.ndarray, commanded: np.ndarray, sim: SimulatorHandle
    ) -> np.ndarray:
        return self._reported(observation)

    def after_reset(self, t: int, observation: np.ndarray, sim: SimulatorHandle) -> np.ndarray:
        return self._reported(observation)


class NoisySensor(SensorFault):
    def __init__(self, severity: float, statistics: _Statistics, rng: np.random.Generator):
        self.severity, self.statistics, self.rng = severity, statistics, rng

    def report(self, true: np.ndarray) -> np.ndarray:
        noise = self.rng.standard_normal(true.shape)
        _, scale = self.statistics.update(true)
        # x + 0·noise is x bit for bit: severity 0 reproduces the clean stream.
        return true + noise * (self.severity * scale)


class DroppingSensor(SensorFault):
    def __init__(self, severity: float, rng: np.random.Generator) -> None:
        self.severity, self.rng = severity, rng

    def report(self, true: np.ndarray) -> np.ndarray:
        dropped = self.rng.random(true.shape) < 0.8 * self.severity
        return np.where(dropped, 0.0, true)


class DecorrelatingSensor(SensorFault):
    def __init__(self, severity: float, rng: np.random.Generator) -> None:
        self.severity, self.rng = severity, rng
        self.history: list[np.ndarray] = []
        self.chosen: np.ndarray | None = None

    def report(self, true: np.ndarray) -> np.ndarray:
        d = true.shape[-1]
        if self.chosen is None:
            self.chosen = self.rng.permutation(d)[: math.ceil(self.severity * d)]
        self.history.append(true)
        # One draw per coordinate whatever the severity (common random numbers).
        steps = self.rng.integers(0, len(self.history), size=d)
        reported = true.copy()
        for i in self.chosen:
            reported[i] = self.history[steps[i]][i]
        return reported


class ShiftingSensor(SensorFault):
    def __init__(self, severity: float, statistics: _Statistics) -> None:
        self.severity, self.statistics = severity, statistics
        self.widening = math.sqrt(1.0 + 2.0 * severity) - 1.0

    def report(self, true: np.ndarray) -> np.ndarray:
        mean, scale = self.statistics.update(true)
        # Written as x + (...) so that severity 0 returns x bit for bit.
        return true + (self.widening * (true - mean) + 2.0 * self.severity * scale)


class DelayedSensor(SensorFault):
    def __init__(self, delay: int) -> None:
        self.line: deque[np.ndarray] = deque(maxlen=delay + 1)

    def report(self, true: np.ndarray) -> np.ndarray:
        self.line.append(true)
        return self.line[0]


class LiveObservationInjector(OnlineInjector):
    """Base of the live observation faults (mode "online")."""

    def severity_steps(self, adapter: EnvironmentAdapter) -> int | None:
        """How many distinct faults σ ∈ (0, 1] gives when the fault changes in whole steps (a
        count of coordinates, a delay in steps): step k is every σ in ((k − 1)/n, k/n]. None
        when the fault changes continuously with σ (`oodrl.protocol.impact` reads tiers
        accordingly)."""
        return None


class _WithStatistics(LiveObservationInjector):
    """A live fault scaled by clean statistics: `mean`/`scale` lists (one per observation
    coordinate), or None for running statistics since the onset."""

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "mean": [IsNone(), SequenceOf(Interval(float, None, None))],
        "scale": [IsNone(), SequenceOf(Interval(float, 0, None))],
    }

    def __init__(
        self,
        *,
        severity: float | None = None,
        mean: list[float] | None = None,
        scale: list[float] | None = None,
    ) -> None:
        super().__init__(severity=severity)
        self.mean = mean
        self.scale = scale

    def check_adapter(self, adapter: EnvironmentAdapter) -> None:
        self.validate_params()
        for name in ("mean", "scale"):
            value = getattr(self, name)
            if value is not None and len(value) != adapter.state_dim:
                raise ConfigError(
                    f"The '{name}' parameter of {type(self).__name__} must have one entry per "
                    f"observation coordinate of {adapter.env_id} ({adapter.state_dim}). Got "
                    f"{len(value)} entries instead."
                )

    def statistics(self) -> _Statistics:
        return _Statistics(self.mean, self.scale)


class LiveGaussianStateNoise(_WithStatistics):
    """Adds N(0, (σ·sd_i)²) to each reported coordinate; sd_i is `scale[i]`."""

    name: ClassVar[str] = "live_gaussian_state_noise"

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return NoisySensor(spec.severity, self.statistics(), rng)


class LiveStateFeatureDropout(LiveObservationInjector):
    """Reports 0 for each coordinate independently with probability 0.8σ."""

    name: ClassVar[str] = "live_state_feature_dropout"

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return DroppingSensor(spec.severity, rng)


class LiveCorrelationBreak(LiveObservationInjector):
    """⌈σ·d⌉ coordinates report the value of a random earlier post-onset step (causal)."""

    name: ClassVar[str] = "live_correlation_break"

    def severity_steps(self, adapter: EnvironmentAdapter) -> int | None:
        return adapter.state_dim

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return DecorrelatingSensor(spec.severity, rng)


class LiveRegimeSwitch(_WithStatistics):
    """Shifts each reported coordinate by 2σ·sd and widens it by sqrt(1 + 2σ) about the mean."""

    name: ClassVar[str] = "live_regime_switch"

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return ShiftingSensor(spec.severity, self.statistics())


class LiveObservationDelay(LiveObservationInjector):
    """Reports the observation of k = ⌈σ·max_delay⌉ steps earlier (delay line from the onset)."""

    name: ClassVar[str] = "live_observation_delay"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "max_delay": [Interval(int, 1, None)],
    }

    def __init__(self, *, severity: float | None = None, max_delay: int = 10) -> None:
        super().__init__(severity=severity)
        self.max_delay = max_delay

    #: The same k as post hoc.
    delay = ObservationDelay.delay

    def severity_steps(self, adapter: EnvironmentAdapter) -> int | None:
        return self.max_delay

    def fault(self, spec: AnomalySpec, rng: np.random.Generator) -> Fault:
        return DelayedSensor(self.delay(spec.severity))


#: Each post-hoc observation fault's live counterpart.
LIVE_COUNTERPARTS = {
    "gaussian_state_noise": "live_gaussian_state_noise",
    "state_feature_dropout": "live_state_feature_dropout",
    "correlation_break": "live_correlation_break",
    "regime_switch": "live_regime_switch",
    "observation_delay": "live_observation_delay",
}
