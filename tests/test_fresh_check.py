"""benchmarks/fresh_check.py (issue 39, item 7) as a user runs it: a subprocess on the tests'
tiny pipeline (`built_repo`, tests/tiny_pipeline.py: LunarLander with its committed policy, 2
detectors, T = 60), built once a session and shared with tests/pipeline/; the check reads it and
writes nothing there. One fault of its two (`--faults`): the tier check rolls whole episodes."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from benchmark_scripts import BENCHMARKS, load_benchmark
from tiny_pipeline import DETECTORS, file_stamps

from oodrl.metrics.tier_results import load_tier_results

pytestmark = pytest.mark.slow

SCRIPT = BENCHMARKS / "fresh_check.py"
FAULTS = ["stuck_actuator"]
STREAMS, EPISODES, RANDOM_EPISODES = 7, 3, 4


@pytest.fixture
def pipeline(built_repo) -> Path:
    """The tiny pipeline, checked to be as it was after the test: others read and copy it."""
    before = file_stamps(built_repo)
    yield built_repo
    assert file_stamps(built_repo) == before, "fresh_check.py wrote into the pipeline's directory"


def fresh_check(directory: Path, *args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, str(SCRIPT), "--pipeline", ".", "--workers", "1", "--faults",
               *FAULTS, *args]  # fmt: skip
    return subprocess.run(command, cwd=directory, capture_output=True, text=True, timeout=600)


def table(stdout: str, heading: str) -> list[dict[str, str]]:
    """The markdown table under the `## ` heading starting with `heading`, as dicts."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"## {heading}"))
    rows = []
    for line in lines[start + 1 :]:
        if line.startswith("## "):
            break
        if line.startswith("|"):
            rows.append([cell.strip() for cell in line.strip("|").split("|")])
    header, rule, *body = rows
    assert set("".join(rule)) <= set("-:")
    return [dict(zip(header, row, strict=True)) for row in body]


def test_tables_count_what_was_asked(pipeline, tmp_path):
    out = tmp_path / "fresh.json"
    done = fresh_check(pipeline, "--streams", str(STREAMS), "--episodes", str(EPISODES),
                       "--random-episodes", str(RANDOM_EPISODES), "--json", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr
    stdout = done.stdout
    assert f"## False alarms: {STREAMS} fresh clean streams of 60 steps" in stdout
    far = table(stdout, "False alarms")
    # Both per-stream rules: the tiny pipeline's 300 ID scores are the time-aware rule's least.
    assert [(row["detector"], row["rule"]) for row in far] == [
        (d, rule) for d in DETECTORS for rule in ("constant", "time_aware")
    ]
    for row in far:
        assert row["streams"] == str(STREAMS)
        assert 0 <= int(row["alarmed"]) <= STREAMS
        assert row["α"] == "0.05"
        assert row["verdict"] in ("not significantly above α", "above α")
        rate = float(row["FAR [95% CI]"].split()[0])
        assert rate == pytest.approx(int(row["alarmed"]) / STREAMS, abs=5e-4)
    assert f"each rate from {STREAMS} streams" in stdout

    assert f"{EPISODES} fresh whole episodes per condition" in stdout
    assert f"({EPISODES} episodes), R_rand" in stdout
    assert f"({RANDOM_EPISODES} episodes), episodes of up to" in stdout
    tiers = table(stdout, "Tiers")
    impact = yaml.safe_load((pipeline / "data/impact/stuck_actuator.yaml").read_text())
    committed = impact["faults"]["stuck_actuator"]["tiers"]
    assert [(r["fault"], r["tier"]) for r in tiers] == [("stuck_actuator", t) for t in committed]
    for row in tiers:
        tier = committed[row["tier"]]
        assert float(row["level"]) == pytest.approx(tier["level"])
        if tier["severity"] == "unreachable":
            assert row["verdict"] == "not measured"
            continue
        assert float(row["σ"]) == pytest.approx(tier["severity"], rel=1e-3)
        assert row["episodes"] == str(EPISODES)
        assert row["verdict"].startswith(("within ", "misses by ", "undecided at "))

    result = json.loads(out.read_text())
    assert [r["n_streams"] for r in result["false_alarms"]] == [STREAMS] * 2 * len(DETECTORS)
    assert result["tiers"]["returns"]["n_clean"] == EPISODES
    assert result["tiers"]["returns"]["n_random"] == RANDOM_EPISODES
    measured = [r for r in result["tiers"]["rows"] if r["severity"] != "unreachable"]
    assert measured and all(r["n_episodes"] == EPISODES for r in measured)
    # The thresholds are the committed ones of the tier results.
    records = load_tier_results(pipeline)["records"]
    committed_thresholds = {
        **{(r["detector"], "constant"): r["operating_point"]["threshold"] for r in records},
        **{(r["detector"], "time_aware"): r["time_aware"]["operating_point"]["threshold"]
           for r in records},
    }  # fmt: skip
    shown = {(r["detector"], r["rule"]): r["threshold"] for r in result["false_alarms"]}
    assert shown == committed_thresholds


@pytest.fixture(scope="module")
def script():
    """The script as a module, for what its process would only wrap (`sys.exit(main())`)."""
    return load_benchmark("fresh_check")


@pytest.mark.parametrize(
    ("offset", "overlapped"),
    [(0, "ID streams"), (10_000 - STREAMS + 1, "evaluation streams"),
     (20_000, "tier calibration streams"), (50, "policy's impact episodes"),
     (100_000, "policy's tuning episodes")],
)  # fmt: skip
def test_an_offset_onto_protocol_seeds_is_refused(
    built_repo, script, tmp_path, monkeypatch, capsys, offset, overlapped
):
    """The seeds are checked from the params alone, before anything is read; in-process (the
    tests around run the script as a process, its exit codes and one-line errors included)."""
    shutil.copy2(built_repo / "params.yaml", tmp_path / "params.yaml")
    monkeypatch.chdir(tmp_path)
    args = ["--streams", str(STREAMS), "--episodes", str(EPISODES), "--seed-offset", str(offset)]
    code = script.main(["--pipeline", ".", "--workers", "1", "--faults", *FAULTS, *args])
    out, err = capsys.readouterr()
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"error: --seed-offset {offset}: ")
    assert overlapped in lines[0]


def test_too_few_random_episodes_are_refused(script, capsys):
    """R_rand needs an interval: fewer than two random-policy episodes is one line, exit 2,
    before anything is read."""
    code = script.main(["--pipeline", ".", "--random-episodes", "1"])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.strip().splitlines() == ["error: --random-episodes must be >= 2; got 1."]


def test_streams_scored_in_batches_score_as_in_one_call(pipeline, script, monkeypatch):
    """--batch-streams: a few streams a call give each stream the scores of one call."""
    import numpy as np

    from oodrl.io.layout import detector_stage
    from oodrl.io.store import load_detector, read_trajectories

    monkeypatch.chdir(pipeline)
    streams = read_trajectories(Path(script.ID_STORE), stage="collect_id")
    assert len(streams) > 3  # batches of 3: more than one call
    for name in DETECTORS:
        detector = load_detector(
            script.fitted_detector_path(name), stage=detector_stage(name, "fit")
        )
        whole = script.scores_in_batches(detector, name, streams, 0)
        assert whole.shape[0] == len(streams)
        np.testing.assert_array_equal(script.scores_in_batches(detector, name, streams, 3), whole)


def test_a_missing_output_is_one_line_naming_its_restore(pipeline, tmp_path):
    bare = tmp_path / "bare"
    (bare / "models").mkdir(parents=True)
    shutil.copy2(pipeline / "params.yaml", bare / "params.yaml")
    shutil.copy2(pipeline / "models" / "policy.pt", bare / "models" / "policy.pt")
    done = fresh_check(bare, "--streams", "1", "--episodes", "0")
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "reports/tier_results.json" in lines[0] and "dvc checkout" in lines[0]


def test_a_tier_is_judged_by_its_interval_against_the_band(script):
    """Within only when the whole interval is inside level ± 0.02 (or a step's band), a miss only
    when it is wholly outside; otherwise the episodes cannot tell."""
    check = script
    assert check.tier_verdict(0.935, 0.965, 0.95, 0.95, None, 600) == "within 0.02"
    assert check.tier_verdict(0.945, 1.000, 0.974, 0.95, None, 150) == "undecided at 150 episodes"
    assert check.tier_verdict(0.760, 0.786, 0.774, 0.75, None, 150) == "undecided at 150 episodes"
    assert check.tier_verdict(0.973, 0.990, 0.981, 0.95, None, 150) == "misses by +0.031"
    levels = {"mild": 0.95, "moderate": 0.9, "severe": 0.75}
    band = check.tier_band("moderate", levels, stepped=True)
    assert band == pytest.approx((0.73, 0.92))
    assert check.tier_band("severe", levels, stepped=True) == pytest.approx((0.48, 0.77))
    assert check.tier_band("mild", levels, stepped=False) is None
    assert check.tier_verdict(0.74, 0.86, 0.80, 0.9, band, 150) == "within its band (step)"
    assert check.tier_verdict(0.57, 0.65, 0.61, 0.75, (0.48, 0.77), 150) == "within its band (step)"
    assert check.tier_verdict(0.50, 0.60, 0.55, 0.9, band, 150) == "misses by -0.350 (step)"
