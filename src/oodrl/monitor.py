"""Runtime monitoring: a fitted detector watching a live Gymnasium environment (SPEC §13).

    env = OodMonitor(gym.make("CartPole-v1"), "models/detectors/cusum.pkl")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(action)
    info["ood_score"], info["ood_alarm"]

Each `step` feeds the transition (the observation the action was chosen on, the action as the
agent commanded it, the reward, the new observation, terminated or truncated) to the detector's
stream (`oodrl.core.stream`) and adds to `info`:

- ``"ood_scores"``: the `StepScore` records that became known with this step, usually one, the
  step's own score (a look-ahead detector's comes later; at an episode end, the rest come);
- ``"ood_score"``: the largest of their scores, −inf when the step brought none (the max of
  nothing: no None or NaN, and it never reaches a threshold);
- ``"ood_alarm"``: whether any of them reached the detector's threshold.

`reset` starts a new stream: the detector's state lives exactly as long as the episode. The
detector must be calibrated (its `threshold_` set); `on_alarm` is called with each alarmed
record. Discrete and continuous actions alike; the monitor never changes what the agent sees.

`run_monitor` is the demonstration behind `oodrl monitor`: the environment's committed policy,
a live fault from the onset on (an online injector's `Fault` hooks, as the collector uses them),
alarms printed as they happen and a one-line summary.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle
from oodrl.core.detector import BaseDetector
from oodrl.core.injector import Fault
from oodrl.core.spec import default_onset
from oodrl.core.stream import StepScore
from oodrl.errors import NotFittedError

#: `on_alarm(record)`: called once for every alarmed step score.
AlarmCallback = Callable[[StepScore], None]


def as_detector(detector: BaseDetector | str | Path) -> BaseDetector:
    """A fitted, calibrated detector, or the one pickled at a path by `oodrl fit`."""
    if isinstance(detector, str | Path):
        from oodrl.store import load_detector

        detector = load_detector(Path(detector), stage="fit")
    if getattr(detector, "threshold_", None) is None:
        raise NotFittedError(
            f"{detector.name} has no alarm threshold: call calibrate() on held-out clean "
            "trajectories before monitoring."
        )
    return detector


class OodMonitor(gym.Wrapper):
    """Adds `ood_score`, `ood_alarm` and `ood_scores` to every step's info (module docstring)."""

    def __init__(
        self,
        env: gym.Env,
        detector: BaseDetector | str | Path,
        on_alarm: AlarmCallback | None = None,
    ) -> None:
        super().__init__(env)
        self.detector = as_detector(detector)
        self.on_alarm = on_alarm
        self.stream = self.detector.stream()
        self.observation: np.ndarray | None = None

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        # An episode cut short leaves scores pending: they belong to the old stream.
        self.stream.flush()
        self.observation, info = self.env.reset(**kwargs)
        return self.observation, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        if self.observation is None:
            raise gym.error.ResetNeeded("Call reset() before step() on an OodMonitor.")
        observation, reward, terminated, truncated, info = self.env.step(action)
        ended = terminated or truncated
        records = self.stream.update(self.observation, action, reward, observation, ended)
        if ended:
            records += self.stream.flush()
        self.observation = observation
        info = {**info, **monitor_info(records)}
        if self.on_alarm is not None:
            for record in records:
                if record.alarm:
                    self.on_alarm(record)
        return observation, reward, terminated, truncated, info


def monitor_info(records: tuple[StepScore, ...]) -> dict[str, Any]:
    """The monitor's `info` entries for the records one step brought."""
    return {
        "ood_scores": records,
        "ood_score": max((r.score for r in records), default=-math.inf),
        "ood_alarm": any(r.alarm for r in records),
    }


class FaultInjection(gym.Wrapper):
    """Applies a live `Fault` from step `onset` on, through its hooks, as the collector does:
    `before_step` may change the executed action, `after_step` the simulator state and the
    observation. Wrap it inside the monitor so that the monitor sees the commanded action."""

    def __init__(self, env: gym.Env, handle: SimulatorHandle, fault: Fault, onset: int) -> None:
        super().__init__(env)
        self.handle, self.fault, self.onset = handle, fault, onset
        self.t = 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        t, self.t = self.t, self.t + 1
        if t < self.onset:
            return self.env.step(action)
        executed = self.fault.before_step(t, action, self.handle)
        observation, reward, terminated, truncated, info = self.env.step(executed)
        observation = self.fault.after_step(t, observation, action, self.handle)
        return observation, reward, terminated, truncated, info


@dataclass(frozen=True)
class MonitorSummary:
    """What a monitored run saw: alarms before and after the fault's onset."""

    steps: int
    onset: int | None
    first_alarm_step: int | None
    first_alarm_raised_at: int | None
    false_alarms_before_onset: int

    @property
    def delay(self) -> int | None:
        """Steps from the onset to the step at which the first alarm was raised."""
        if self.onset is None or self.first_alarm_raised_at is None:
            return None
        return self.first_alarm_raised_at - self.onset

    def line(self) -> str:
        if self.onset is None:
            first = "none" if self.first_alarm_step is None else f"step {self.first_alarm_step}"
            return (
                f"{self.steps} clean steps: {self.false_alarms_before_onset} false alarms, "
                f"first at {first}."
            )
        if self.first_alarm_step is None:
            detected = f"no alarm after the onset at step {self.onset}"
        else:
            detected = (
                f"first alarm for step {self.first_alarm_step}, raised at step "
                f"{self.first_alarm_raised_at}, delay {self.delay} steps after the onset at "
                f"step {self.onset}"
            )
        return (
            f"{self.steps} steps: {detected}; "
            f"{self.false_alarms_before_onset} false alarms before the onset."
        )


def run_monitor(
    env_id: str,
    detector: str | BaseDetector | Path,
    fault: str | None = None,
    severity: float = 1.0,
    *,
    steps: int = 500,
    onset: int | None = None,
    seed: int = 0,
    detector_params: Mapping[str, Any] | None = None,
    injector_params: Mapping[str, Any] | None = None,
    fit_streams: int = 8,
    root: Path = Path("."),
    echo: Callable[[str], None] = print,
) -> MonitorSummary:
    """Run the environment's committed policy for one episode (at most `steps` steps) under
    the monitor, the fault `fault` (an online injector's name) from `onset` on
    (default ⌊steps/3⌋), printing each alarm as it is raised and a one-line summary.

    `detector` is a fitted detector, a pickle written by `oodrl fit`, or a registered name: then
    it is fitted here, with `detector_params`, on `fit_streams` clean streams of `steps` steps
    and calibrated on as many more (seeds 10_000 on, apart from the monitored `seed`).
    Policies are read under the project `root`.
    """
    from oodrl.envs import ENVIRONMENTS
    from oodrl.envs.collect import noise_rng
    from oodrl.policies.load import load_policy
    from oodrl.suite import policy_path

    adapter = ENVIRONMENTS.get(env_id)()
    policy = load_policy(
        policy_path(env_id, root), "greedy", None, adapter.state_dim, adapter.action_size
    )
    if isinstance(detector, str) and not Path(detector).suffix:
        detector = fitted_on_clean_streams(
            adapter, policy, detector, detector_params or {}, fit_streams, steps
        )
    env = adapter.make()
    if fault is not None:
        onset = default_onset(steps) if onset is None else onset
        live = live_fault(adapter, fault, severity, onset, injector_params or {}, seed)
        env = FaultInjection(env, adapter.handle(env), live, onset)
    else:
        onset = None
    monitored = OodMonitor(env, detector)
    summary = _monitored_episode(monitored, policy, steps, onset, noise_rng(0, seed), seed, echo)
    monitored.close()
    echo(summary.line())
    return summary


def fitted_on_clean_streams(
    adapter: EnvironmentAdapter,
    policy: Any,
    name: str,
    params: Mapping[str, Any],
    n: int,
    steps: int,
) -> BaseDetector:
    """A registered detector fitted on `n` clean streams and calibrated on `n` more."""
    from oodrl.detectors import DETECTORS
    from oodrl.envs.collect import collect

    clean = collect(adapter, policy, range(10_000, 10_000 + 2 * n), steps).trajectories()
    return DETECTORS.get(name)(**params).fit(clean[:n]).calibrate(clean[n:])


def live_fault(
    adapter: EnvironmentAdapter,
    name: str,
    severity: float,
    onset: int,
    params: Mapping[str, Any],
    seed: int,
) -> Fault:
    """The `Fault` of a registered online injector at a severity, checked for the adapter."""
    from oodrl.injectors import INJECTORS

    injector = INJECTORS.get(name)(**params)
    injector.check_adapter(adapter)
    return injector.fault(injector.spec(severity, onset), np.random.default_rng(seed))


def _monitored_episode(
    env: OodMonitor,
    policy: Any,
    steps: int,
    onset: int | None,
    rng: np.random.Generator,
    seed: int,
    echo: Callable[[str], None],
) -> MonitorSummary:
    observation, _ = env.reset(seed=seed)
    first: StepScore | None = None
    raised_at = None
    false_alarms = 0
    t = 0
    for t in range(steps):
        action = policy.act(np.asarray(observation, dtype=np.float32)[None], [rng])[0]
        observation, _, terminated, truncated, info = env.step(action)
        for record in info["ood_scores"]:
            if not record.alarm:
                continue
            echo(
                f"step {t}: alarm for step {record.step}, score {record.score:.4g} >= "
                f"{env.detector.threshold_:.4g}"
            )
            if onset is None or record.step < onset:
                false_alarms += 1
            elif first is None:
                first, raised_at = record, t
        if terminated or truncated:
            break
    first_step = None if first is None else first.step
    return MonitorSummary(t + 1, onset, first_step, raised_at, false_alarms)
