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
alarms printed as they happen and a one-line summary. A detector it fits itself alarms by the
suite's per-stream rule (SPEC §15: `episode_max`, conformal at α over ⌈1/α⌉ − 1 or more clean
streams), so a clean episode raises any alarm with probability ≤ α. `run_monitor_episodes`
(`oodrl monitor --episodes N`) reports the rates over N seeds instead of one anecdote: the
detection rate within K steps of the onset (`oodrl.metrics.operating`), the delays, the first
alarms before the onset, and the clean false-alarm rate beside α.
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
from oodrl.errors import ConfigError, NotFittedError, StoreError
from oodrl.metrics.operating import DEFAULT_ALPHA, MIN_DELAY_COUNT, OperatingPoint

#: `on_alarm(record)`: called once for every alarmed step score.
AlarmCallback = Callable[[StepScore], None]


def as_detector(detector: BaseDetector | str | Path) -> BaseDetector:
    """A fitted, calibrated detector, or the one pickled at a path by `oodrl fit`."""
    if isinstance(detector, str | Path):
        from oodrl.io.store import load_detector

        if not Path(detector).is_file():
            raise ConfigError(f"--detector {detector}: no such file; pass a detector file written "
                              "by `oodrl fit` or a registered detector's name.")  # fmt: skip
        try:
            detector = load_detector(Path(detector), stage=None)
        except StoreError:  # a file the user named: a usage error, and no stage to re-run
            raise ConfigError(
                f"--detector {detector}: not a detector file written by `oodrl fit`."
            ) from None
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
    #: Every step whose score raised an alarm, in order.
    alarm_steps: tuple[int, ...] = ()

    def alarms(self) -> np.ndarray:
        """(steps,) bool: whether the score of each step of the episode raised an alarm."""
        alarms = np.zeros(self.steps, bool)
        alarms[list(self.alarm_steps)] = True
        return alarms

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
    alpha: float = DEFAULT_ALPHA,
    root: Path = Path("."),
    echo: Callable[[str], None] = print,
) -> MonitorSummary:
    """Run the environment's committed policy for one episode (at most `steps` steps) under
    the monitor, the fault `fault` (an online injector's name) from `onset` on
    (default ⌊steps/3⌋), printing each alarm as it is raised and a one-line summary.

    `detector` is a fitted detector, a pickle written by `oodrl fit`, or a registered name: then
    it is fitted here, with `detector_params`, on `fit_streams` clean streams of `steps` steps
    and calibrated by the per-stream rule at `alpha` (unless `detector_params` name another
    `threshold_rule`) on max(`fit_streams`, ⌈1/α⌉ − 1) more (seeds 10_000 on, apart from the
    monitored seeds). Policies are read under the project `root`.
    """
    onset = _checked_onset(fault, onset, steps) if fault is not None else None
    adapter, policy, detector = _monitor_setup(
        env_id, detector, detector_params, fit_streams, steps, alpha, root
    )
    summary = _run_episode(
        adapter, policy, detector, fault, severity, onset, injector_params, steps, seed, echo
    )
    echo(summary.line())
    return summary


def _checked_onset(fault: str, onset: int | None, steps: int) -> int:
    """The onset of a live fault (default ⌊steps/3⌋), refused before any simulation when the
    fault cannot run live or the onset lies outside the episode (SPEC §22)."""
    from oodrl.injectors import INJECTORS

    live = [name for name in INJECTORS.names() if INJECTORS.get(name).mode == "online"]
    if fault not in live:
        what = (
            f"a post-hoc fault (it rewrites recorded data); live it is 'live_{fault}'"
            if f"live_{fault}" in live
            else "not a registered fault"
        )
        raise ConfigError(f"--fault {fault!r} is {what}. The monitor runs live faults: "
                          f"{', '.join(live)}.")  # fmt: skip
    onset = default_onset(steps) if onset is None else onset
    if not 0 <= onset < steps:
        raise ConfigError(f"--onset must be a step of the episode, 0 <= onset < --steps "
                          f"({steps}); got {onset}.")  # fmt: skip
    return onset


def _monitor_setup(
    env_id: str,
    detector: str | BaseDetector | Path,
    detector_params: Mapping[str, Any] | None,
    fit_streams: int,
    steps: int,
    alpha: float,
    root: Path,
) -> tuple[EnvironmentAdapter, Any, BaseDetector]:
    """The adapter, the committed policy, and the detector (fitted here if named)."""
    from oodrl.detectors import DETECTORS
    from oodrl.envs import ENVIRONMENTS
    from oodrl.policies.load import load_policy
    from oodrl.suite.environments import policy_path

    named = isinstance(detector, str) and not Path(detector).suffix
    if named and detector not in DETECTORS.names():
        raise ConfigError(f"--detector {detector!r} is neither a registered detector "
                          f"({', '.join(DETECTORS.names())}) nor a file written by `oodrl "
                          "fit` (a .pkl path).")  # fmt: skip
    adapter = ENVIRONMENTS.get(env_id)()
    policy = load_policy(
        policy_path(env_id, root), "greedy", None, adapter.state_dim, adapter.action_size
    )
    if named:
        params = {"threshold_rule": "episode_max", "alpha": alpha, **(detector_params or {})}
        detector = fitted_on_clean_streams(adapter, policy, detector, params, fit_streams, steps)
    return adapter, policy, as_detector(detector)


def _run_episode(
    adapter: EnvironmentAdapter,
    policy: Any,
    detector: BaseDetector,
    fault: str | None,
    severity: float,
    onset: int | None,
    injector_params: Mapping[str, Any] | None,
    steps: int,
    seed: int,
    echo: Callable[[str], None],
) -> MonitorSummary:
    """One monitored episode from `seed`, the fault live from `onset` (None: clean)."""
    from oodrl.envs.collect import noise_rng

    env = adapter.make()
    if fault is not None and onset is not None:
        live = live_fault(adapter, fault, severity, onset, injector_params or {}, seed)
        env = FaultInjection(env, adapter.handle(env), live, onset)
    monitored = OodMonitor(env, detector)
    try:
        return _monitored_episode(monitored, policy, steps, onset, noise_rng(0, seed), seed, echo)
    finally:
        monitored.close()


def fitted_on_clean_streams(
    adapter: EnvironmentAdapter,
    policy: Any,
    name: str,
    params: Mapping[str, Any],
    n: int,
    steps: int,
) -> BaseDetector:
    """A registered detector fitted on `n` clean streams and calibrated on `n` more, or on the
    ⌈1/α⌉ − 1 its per-stream rule needs at `params["alpha"]` if that is more."""
    from oodrl.detectors import DETECTORS
    from oodrl.envs.collect import collect
    from oodrl.metrics.operating import min_calibration_streams

    n_calibration = n
    if params.get("threshold_rule") == "episode_max":
        n_calibration = max(n, min_calibration_streams(params.get("alpha", DEFAULT_ALPHA)))
    seeds = range(10_000, 10_000 + n + n_calibration)
    clean = collect(adapter, policy, seeds, steps).trajectories()
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
    alarm_steps = []
    t = 0
    for t in range(steps):
        action = policy.act(np.asarray(observation, dtype=np.float32)[None], [rng])[0]
        observation, _, terminated, truncated, info = env.step(action)
        for record in info["ood_scores"]:
            if not record.alarm:
                continue
            alarm_steps.append(record.step)
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
    return MonitorSummary(t + 1, onset, first_step, raised_at, false_alarms, tuple(alarm_steps))


@dataclass(frozen=True)
class EpisodesSummary:
    """`oodrl monitor --episodes N`: the operating point over N seeds (faulty episodes that
    reach the onset; clean episodes of the same seeds), and how many episodes ended before the
    onset (no fault acted on them: left out)."""

    point: OperatingPoint
    onset: int
    seeds: tuple[int, int]
    ended_before_onset: int
    rule: str

    def lines(self) -> list[str]:
        record = self.point.as_dict()
        low, high = record["detection_rate_ci"]
        fa_low, fa_high = record["clean_false_alarm_ci"]
        delay = record["delay"]
        delays = (
            f"delay median {delay['median']:g}, p90 {delay['p90']:g} steps "
            f"({delay['n_detected']} streams detected within K)"
            if delay["median"] is not None
            else f"delays not shown ({delay['n_detected']} streams detected within K, "
            f"fewer than {MIN_DELAY_COUNT})"
        )
        p = self.point
        return [
            f"{p.n_faulty} faulty episodes (seeds {self.seeds[0]}..{self.seeds[1]}, fault from "
            f"step {self.onset}; {self.ended_before_onset} ended before it, left out), "
            f"alarm rule {self.rule}, threshold {p.threshold:.4g}:",
            f"  detection_rate@{p.k}: {record['detection_rate']:.2f} "
            f"[{low:.2f}, {high:.2f}] ({p.detected}/{p.n_faulty}); first alarm before the "
            f"onset: {p.early_false_alarms}/{p.n_faulty}; {delays}",
            f"  clean episodes with any alarm: {p.clean_false_alarms}/{p.n_clean} = "
            f"{record['clean_false_alarm_rate']:.2f} [{fa_low:.2f}, {fa_high:.2f}] "
            f"(nominal α {p.alpha:g}; 95% Clopper-Pearson intervals)",
        ]


def run_monitor_episodes(
    env_id: str,
    detector: str | BaseDetector | Path,
    fault: str,
    severity: float = 1.0,
    *,
    episodes: int,
    k: int = 100,
    steps: int = 500,
    onset: int | None = None,
    seed: int = 0,
    detector_params: Mapping[str, Any] | None = None,
    injector_params: Mapping[str, Any] | None = None,
    fit_streams: int = 8,
    alpha: float = DEFAULT_ALPHA,
    root: Path = Path("."),
    echo: Callable[[str], None] = print,
) -> EpisodesSummary:
    """`run_monitor` over the seeds seed..seed + episodes − 1, each once with the fault and once
    clean: detection_rate@K (the first alarm raised in [t*, t* + K], an alarm on step t raised at
    t + latency as in `oodrl.metrics.operating`), delays, first alarms before the onset, and the
    share of clean episodes with any alarm."""
    from oodrl.metrics.operating import first_raise

    onset = _checked_onset(fault, onset, steps)
    adapter, policy, detector = _monitor_setup(
        env_id, detector, detector_params, fit_streams, steps, alpha, root
    )
    seeds = range(seed, seed + episodes)
    raised, clean_alarms, ended = [], [], 0
    never = np.iinfo(np.int64).max  # a first raise that never comes: beyond any K
    for s in seeds:
        run = _run_episode(
            adapter, policy, detector, fault, severity, onset, injector_params, steps, s, _quiet
        )
        clean = _run_episode(adapter, policy, detector, None, 0.0, None, None, steps, s, _quiet)
        clean_alarms.append(bool(clean.alarm_steps))
        if run.steps <= onset:
            ended += 1
            continue
        first = int(first_raise(run.alarms()[None], detector.latency)[0])
        raised.append(first if first < run.steps else never)
    if not raised:
        raise ConfigError(
            f"Every one of the {episodes} episodes ended before the onset at step {onset}: "
            "choose an earlier --onset."
        )
    rule = detector.threshold_rule + (
        f" (α = {detector.alpha:g})" if detector.threshold_rule == "episode_max" else ""
    )
    point = _operating_point(np.array(raised), np.array(clean_alarms), onset, k, detector, alpha)
    summary = EpisodesSummary(point, onset, (seeds[0], seeds[-1]), ended, rule)
    for line in summary.lines():
        echo(line)
    return summary


def _quiet(line: str) -> None:
    """Over many episodes the rates are the report, not each alarm."""


def _operating_point(
    raised: np.ndarray,
    clean_alarms: np.ndarray,
    onset: int,
    k: int,
    detector: BaseDetector,
    alpha: float,
) -> OperatingPoint:
    """The operating point of first raises (one per faulty episode; never = int64 max)."""
    from oodrl.metrics.operating import detection_rate

    never = np.iinfo(np.int64).max
    detected = (raised >= onset) & (raised <= onset + k)
    nominal = detector.alpha if detector.threshold_rule == "episode_max" else alpha
    return OperatingPoint(
        alpha=float(nominal),
        threshold=float(detector.threshold_),
        k=k,
        n_faulty=len(raised),
        detected=int(np.sum(detected)),
        early_false_alarms=int(np.sum(raised < onset)),
        delays=tuple(int(d) for d in raised[detected] - onset),
        curve={kk: detection_rate(raised, onset, kk, never) for kk in range(0, k + 1, 10)},
        n_clean=len(clean_alarms),
        clean_false_alarms=int(np.sum(clean_alarms)),
        confidence=0.95,
    )
