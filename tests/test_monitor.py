"""The monitor wrapper on live episodes with a live fault: the alarm appears after the onset,
on a discrete (CartPole) and a continuous-action (Pendulum) environment, with detectors fitted
here on a few clean streams of the committed policies (SPEC §13)."""

from __future__ import annotations

import math
import re
import shlex
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from oodrl.core.detector import BaseDetector
from oodrl.core.trajectory import Trajectory
from oodrl.detectors import DETECTORS
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import collect
from oodrl.errors import NotFittedError
from oodrl.io.store import save_detector
from oodrl.monitor import FaultInjection, OodMonitor, live_fault, run_monitor
from oodrl.policies.load import load_policy
from oodrl.suite.environments import policy_path

ROOT = Path(__file__).resolve().parents[1]

#: env id → (detector, its params, online fault, onset, steps): a detector that sees the fault.
CASES = {
    "CartPole-v1": (
        "mahalanobis_distance",
        {"features": "transition"},
        "dynamics_scaling",
        60,
        200,
    ),
    "Pendulum-v1": ("cusum", {}, "stuck_actuator", 66, 200),
}


@cache
def _policy(env_id: str):
    adapter = ENVIRONMENTS.get(env_id)()
    return load_policy(policy_path(env_id, ROOT), "greedy", None, adapter.state_dim)


@cache
def _detector(env_id: str) -> BaseDetector:
    name, params, _, _, steps = CASES[env_id]
    clean = collect(ENVIRONMENTS.get(env_id)(), _policy(env_id), range(100, 106), steps)
    trajectories = clean.trajectories()
    return DETECTORS.get(name)(**params).fit(trajectories[:3]).calibrate(trajectories[3:])


def _faulted_monitor(env_id: str, alarms: list) -> OodMonitor:
    adapter = ENVIRONMENTS.get(env_id)()
    _, _, fault, onset, _ = CASES[env_id]
    env = adapter.make()
    env = FaultInjection(
        env, adapter.handle(env), live_fault(adapter, fault, 1.0, onset, {}, 0), onset
    )
    return OodMonitor(env, _detector(env_id), on_alarm=alarms.append)


def _episode(env: OodMonitor, env_id: str, seed: int = 0):
    """Drive the policy through one episode; the transitions and the infos of every step."""
    observation, _ = env.reset(seed=seed)
    steps, infos = [], []
    for _ in range(CASES[env_id][4]):
        action = _policy(env_id).act(observation[None])[0]
        following, reward, terminated, truncated, info = env.step(action)
        steps.append((observation, action, reward, following, terminated or truncated))
        infos.append(info)
        observation = following
        if terminated or truncated:
            break
    return steps, infos


@pytest.mark.parametrize("env_id", list(CASES), ids=list(CASES))
def test_a_live_fault_raises_an_alarm_after_the_onset(env_id):
    alarms: list = []
    env = _faulted_monitor(env_id, alarms)
    _, infos = _episode(env, env_id)
    onset = CASES[env_id][3]
    for info in infos:
        assert isinstance(info["ood_score"], float) and not math.isnan(info["ood_score"])
        assert info["ood_alarm"] == any(r.alarm for r in info["ood_scores"])
    raised = [t for t, info in enumerate(infos) if info["ood_alarm"]]
    assert any(t >= onset for t in raised), f"no alarm after the onset at {onset}"
    assert [r.step for r in alarms] == [r.step for i in infos for r in i["ood_scores"] if r.alarm]


@pytest.mark.parametrize("env_id", list(CASES), ids=list(CASES))
def test_the_monitor_scores_are_the_detector_scores_of_the_episode(env_id):
    env = _faulted_monitor(env_id, [])
    steps, infos = _episode(env, env_id)
    records = [r for info in infos for r in info["ood_scores"]]
    assert [r.step for r in records] == list(range(len(steps)))
    states, actions, rewards, following, dones = (np.array(x) for x in zip(*steps, strict=True))
    trajectory = Trajectory(states, actions, rewards.astype(np.float64), following, dones)
    batch = _detector(env_id).score(trajectory)
    np.testing.assert_array_equal([r.score for r in records], batch.scores)
    np.testing.assert_array_equal([r.alarm for r in records], batch.alarms)


def test_reset_starts_a_new_stream():
    env = _faulted_monitor("CartPole-v1", [])
    observation, _ = env.reset(seed=1)
    for _ in range(5):
        observation, *_, info = env.step(_policy("CartPole-v1").act(observation[None])[0])
    assert info["ood_scores"][0].step == 4
    observation, _ = env.reset(seed=2)
    *_, info = env.step(_policy("CartPole-v1").act(observation[None])[0])
    assert info["ood_scores"][0].step == 0


def test_a_pickled_detector_by_its_path(tmp_path):
    path = tmp_path / "detector.pkl"
    save_detector(path, _detector("CartPole-v1"), "mahalanobis_distance", {})
    env = OodMonitor(ENVIRONMENTS.get("CartPole-v1")().make(), path)
    env.reset(seed=0)
    *_, info = env.step(0)
    assert info["ood_scores"][0].step == 0


def test_the_readme_monitor_snippet_runs(tmp_path, monkeypatch, capsys):
    """The monitor page's Python example, as printed, with a cusum fitted here in place of the
    pipeline's pickle (a DVC output, absent from a fresh clone)."""
    from test_readme import blocks, section

    (snippet,) = blocks(section(MONITOR_SECTION), "python")
    pipeline_pickle = "pipeline/cartpole/models/detectors/cusum.pkl"
    assert f'"{pipeline_pickle}"' in snippet
    clean = collect(ENVIRONMENTS.get("CartPole-v1")(), _policy("CartPole-v1"), range(3), 60)
    trajectories = clean.trajectories()
    cusum = DETECTORS.get("cusum")().fit(trajectories[:2]).calibrate(trajectories[2:])
    save_detector(tmp_path / pipeline_pickle, cusum, "cusum", {})
    monkeypatch.chdir(tmp_path)
    exec(compile(snippet, str(MONITOR_SECTION[0]), "exec"), {})
    score, alarm = capsys.readouterr().out.split()[-2:]
    assert math.isfinite(float(score)) and alarm in {"True", "False"}


def test_an_uncalibrated_detector_is_refused():
    trajectories = collect(ENVIRONMENTS.get("CartPole-v1")(), _policy("CartPole-v1"), [7], 50)
    detector = DETECTORS.get("cusum")().fit(trajectories.trajectories())
    with pytest.raises(NotFittedError, match="calibrate"):
        OodMonitor(ENVIRONMENTS.get("CartPole-v1")().make(), detector)


def test_run_monitor_prints_alarms_and_a_summary():
    lines: list[str] = []
    summary = run_monitor(
        "Pendulum-v1", "cusum", "stuck_actuator", 1.0, steps=200, fit_streams=3,
        root=ROOT, echo=lines.append,
    )  # fmt: skip
    assert summary.onset == 66 and summary.first_alarm_step >= 66
    assert summary.delay == summary.first_alarm_raised_at - 66
    assert lines[-1] == summary.line() and "delay" in lines[-1]
    assert any(line.startswith(f"step {summary.first_alarm_raised_at}: alarm") for line in lines)


def test_the_monitor_command_prints_alarms_and_a_summary(monkeypatch):
    from pathlib import Path

    from typer.testing import CliRunner

    from oodrl.cli import app

    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    args = ["monitor", "--env", "CartPole-v1", "--detector", "mahalanobis_distance"]
    result = CliRunner().invoke(app, [*args, "--fault", "dynamics_scaling", "--steps", "120"])
    assert result.exit_code == 0, result.output
    summary = result.output.strip().splitlines()[-1]
    assert "onset at step 40" in summary and "false alarms before the onset" in summary
    bad = CliRunner().invoke(app, [*args, "--fault", "no_such_fault"])
    assert bad.exit_code == 2 and "'no_such_fault' is not a registered fault" in bad.output


def test_a_detector_fitted_by_the_monitor_alarms_by_the_per_stream_rule():
    from oodrl.metrics.operating import min_calibration_streams
    from oodrl.monitor import fitted_on_clean_streams

    adapter = ENVIRONMENTS.get("CartPole-v1")()
    params = {"threshold_rule": "episode_max", "alpha": 0.1}
    detector = fitted_on_clean_streams(adapter, _policy("CartPole-v1"), "cusum", params, 3, 40)
    assert detector.threshold_rule == "episode_max"
    # Calibrated on the ⌈1/α⌉ − 1 = 9 streams the rule needs (seeds 10003..10011), not on 3.
    calibration = collect(adapter, _policy("CartPole-v1"), range(10_003, 10_012), 40)
    maxima = [o.scores.max() for o in detector.score_many(calibration.trajectories())]
    assert len(maxima) == min_calibration_streams(0.1)
    assert detector.threshold_ == np.nextafter(max(maxima), np.inf)


def test_monitor_over_episodes_reports_rates_that_add_up():
    from oodrl.monitor import run_monitor_episodes

    lines: list[str] = []
    summary = run_monitor_episodes(
        "CartPole-v1", "mahalanobis_distance", "dynamics_scaling", 1.0, episodes=4, k=30,
        steps=120, fit_streams=3, detector_params={"features": "transition"}, root=ROOT,
        echo=lines.append,
    )  # fmt: skip
    point = summary.point
    assert summary.rule == "episode_max (α = 0.05)" and summary.onset == 40
    assert point.n_faulty + summary.ended_before_onset == 4 and point.n_clean == 4
    missed = point.n_faulty - point.detected - point.early_false_alarms
    assert missed >= 0 and len(point.delays) >= point.detected
    assert point.curve[30] == point.detection_rate  # K = 30 is the curve's last point
    assert len(lines) == 3 and lines[1].startswith("  detection_rate@30: ")
    assert "Clopper-Pearson" in lines[2]


def test_the_monitor_command_over_episodes_needs_a_fault(monkeypatch):
    from typer.testing import CliRunner

    from oodrl.cli import app

    monkeypatch.chdir(ROOT)
    args = ["monitor", "--env", "CartPole-v1", "--detector", "cusum", "--episodes", "3"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2 and "name a --fault" in result.output


# -- the monitor page's demonstration ------------------------------------------------------------
#: The monitor how-to's section: its Python example, its demo command and the cell it quotes.
MONITOR_SECTION = (
    ROOT / "docs" / "how-to" / "monitor.md",
    "Deploy a detector: the runtime monitor",
)
CELL = re.compile(r"<!-- monitor-cell -->([\d.]+) \[([\d.]+), ([\d.]+)\]<!-- /monitor-cell -->")


def _readme_demo() -> tuple[list[str], tuple[float, float, float]]:
    """The monitor page's `oodrl monitor … --episodes N` command (its arguments) and the
    leaderboard cell it quotes: detection_rate@K and its interval."""
    from test_readme import blocks, section, shell_commands

    demo = section(MONITOR_SECTION)
    (command,) = [c for b in blocks(demo, "bash") for c in shell_commands(b)]
    args = shlex.split(command)
    assert args[:2] == ["oodrl", "monitor"] and "--episodes" in args, command
    rate, low, high = (float(x) for x in CELL.search(demo.prose).groups())
    return args[2:], (rate, low, high)


def _option(args: list[str], name: str) -> str:
    return args[args.index(name) + 1]


@pytest.mark.slow
def test_the_readme_monitor_demo_agrees_with_its_leaderboard_cell(monkeypatch):
    """The rate the monitor page's demo prints (a detector fitted by the monitor, on its own
    seeds) lies in the interval of the leaderboard cell the page quotes for it."""
    from typer.testing import CliRunner

    from oodrl.cli import app

    args, (_, low, high) = _readme_demo()
    monkeypatch.chdir(ROOT)
    result = CliRunner().invoke(app, ["monitor", *args])
    assert result.exit_code == 0, result.output
    k = 100 if "--k" not in args else int(_option(args, "--k"))
    printed = re.search(rf"detection_rate@{k}: ([\d.]+) ", result.output)
    assert printed, result.output
    assert low <= float(printed.group(1)) <= high, (result.output, (low, high))


def test_the_readme_monitor_cell_is_the_committed_result():
    """The cell the monitor page quotes is the committed run's (its tier results, a DVC output:
    present after `dvc repro` or `dvc pull`), at the tier severity the demo deploys."""
    from oodrl.metrics.tier_results import load_tier_results, tier_results_path

    if not tier_results_path(ROOT).is_file():
        pytest.skip("reports/tier_results.json is not built here (run `dvc repro`)")
    args, (rate, low, high) = _readme_demo()
    detector, fault = _option(args, "--detector"), _option(args, "--fault")
    severity = float(_option(args, "--severity"))
    records = load_tier_results(ROOT)["records"]
    (record,) = [
        r
        for r in records
        if r["detector"] == detector and r["injector"] == fault and r["tier"] == "mild"
    ]
    point = record["operating_point"]
    assert round(record["severity"], 3) == severity
    assert (
        round(point["detection_rate"], 2),
        *(round(x, 2) for x in point["detection_rate_ci"]),
    ) == (
        rate,
        low,
        high,
    )
