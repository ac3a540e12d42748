"""`oodrl suite run` with local workers (SPEC §16): every pipeline in its own clone, in parallel,
then the leaderboard; the head's checkout ends with the dvc.lock files of a serial run, byte for
byte. (On a Ray cluster that loses a node mid-task: tests/test_suite_run_ray.py.)"""

from __future__ import annotations

import pytest
import yaml
from suite_repo import SUITE, checkout, locks
from tiny_suite import assert_checking_line_then_the_error
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.suite.migration import project_states
from oodrl.suite.run import RUN_META, _up_to_date, run_suite
from oodrl.testing.pipeline import run

pytestmark = pytest.mark.slow


def test_local_workers_leave_the_locks_of_a_serial_run(fresh_suite, serial_locks):
    lines = []
    first = run_suite(fresh_suite, workers=2, echo=lines.append)
    assert locks(fresh_suite) == serial_locks
    assert sorted(run.pipeline for run in first.pipelines) == [".", "pipeline/cartpole"]
    assert all(run.ran for run in first.pipelines)  # each clone computed its pipeline
    assert all(run.restore_seconds > 0 for run in first.pipelines)  # each restored as it ended
    assert 0 < first.leaderboard_seconds <= first.head_seconds
    # The head writes each task's locks and checks its outputs out of the cache the workers
    # filled: no stage runs on the head but the leaderboard.
    assert first.head_ran == (f"{SUITE}:leaderboard",)
    assert sum(line.startswith("started") for line in lines) == 2
    assert sum(line.startswith("finished") for line in lines) == 2
    # Each task's stage times came back with its locks (git ignores them): the next run orders
    # the pipelines by them.
    for pipeline in (".", "pipeline/cartpole"):
        assert "total_stage_wall_s:" in (fresh_suite / pipeline / RUN_META).read_text()
    assert "run_meta" not in run(fresh_suite, "git", "status", "--porcelain").stdout

    again = run_suite(fresh_suite, workers=2, echo=lines.append)
    assert (again.pipelines, again.head_ran) == ((), ())
    assert lines[-1] == "suite: all 3 projects are up to date; nothing to run"  # DVC said so
    assert locks(fresh_suite) == serial_locks

    # Then nothing has changed: the pipelines are current from git alone, the suite by DVC.
    lines.clear()
    run_suite(fresh_suite, workers=2, echo=lines.append)
    assert lines == [
        "suite: 3 projects; checking the DVC remote first",
        "suite: from git, 2 of 2 pipelines current",
        "suite: all 3 projects are up to date; nothing to run",
    ]
    # A git-tracked result edited is not what its lock records: DVC and git alone both say so;
    # edited back to what it was, the pipeline is current again.
    results = fresh_suite / "pipeline" / "cartpole" / "reports" / "results.yaml"
    kept = results.read_bytes()
    results.write_bytes(kept + b"# edited\n")
    assert not _up_to_date(fresh_suite / "pipeline" / "cartpole")  # DVC: stale
    [state] = project_states(fresh_suite, ["pipeline/cartpole"])
    assert state.status == "stale" and "reports/results.yaml is not what its lock records" in (
        "; ".join(state.reasons)
    )
    results.write_bytes(kept)
    [state] = project_states(fresh_suite, ["pipeline/cartpole"])
    assert state.status == "current"
    run_suite(fresh_suite, workers=2, echo=lines.append)
    assert lines[-1] == "suite: all 3 projects are up to date; nothing to run"

    # One pipeline's knob, committed: only its task runs; the current root is not cloned again.
    params = fresh_suite / "pipeline" / "cartpole" / "params.yaml"
    params.write_text(params.read_text() + "metrics:\n  n_boot: 21\n")
    run(fresh_suite, "git", "commit", "-q", "-am", "a CartPole knob")
    lines.clear()
    third = run_suite(fresh_suite, workers=2, echo=lines.append)
    assert [run.pipeline for run in third.pipelines] == ["pipeline/cartpole"]
    assert "suite: 1 of 2 pipelines are up to date; building the other 1" in lines
    assert [line for line in lines if line.startswith("started")] == ["started  pipeline/cartpole"]
    assert third.head_ran == (f"{SUITE}:leaderboard",)
    assert _up_to_date(fresh_suite / "pipeline" / "cartpole")


def test_an_uncommitted_input_is_refused_before_anything_runs(fresh_suite):
    params = fresh_suite / "params.yaml"
    params.write_text(params.read_text().replace("n_boot: 20", "n_boot: 21"))
    before = locks(fresh_suite)
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(fresh_suite)])
    assert result.exit_code == 2
    *progress, error = result.output.splitlines()  # git alone found what is stale
    assert len(progress) == 2
    assert progress[0] == "suite: 3 projects; checking the DVC remote first"
    # The copy's tiny params are not what its committed locks record (or its results are an
    # older protocol's, between two versions): neither pipeline is current.
    assert progress[1].startswith("suite: from git, 0 of 2 pipelines current; "), progress[1]
    assert "params.yaml: uncommitted" in error
    assert locks(fresh_suite) == before


def test_an_unreachable_ray_address_is_one_line_and_changes_nothing(fresh_suite):
    before = checkout(fresh_suite)
    result = CliRunner().invoke(
        app, ["suite", "run", "--root", str(fresh_suite), "--ray", "127.0.0.1:9"]
    )
    assert result.exit_code == 1
    assert_checking_line_then_the_error(result.output)
    assert "no Ray cluster answers at 127.0.0.1:9" in result.output
    assert checkout(fresh_suite) == before


def test_workers_must_be_positive(fresh_suite):
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(fresh_suite), "--workers", "0"])
    assert result.exit_code == 2
    assert "--workers must be >= 1. Got 0 instead." in result.output


def test_a_copy_keeps_in_its_locks_only_the_stages_its_pipelines_define(fresh_suite, repo_root):
    """oodrl.testing.pipeline.prune_locks: the committed locks also hold the stages the tiny
    params cut (the other injectors'), entries DVC keeps and rewrites after every stage."""
    from oodrl.io import yamlio

    for project in [".", "pipeline/cartpole"]:
        lock = f"{project}/dvc.lock".removeprefix("./")
        committed = yamlio.load(run(repo_root, "git", "show", f"HEAD:{lock}").stdout)["stages"]
        kept = yamlio.load((fresh_suite / lock).read_text())["stages"]
        listed = run(fresh_suite / project, "dvc", "stage", "list", "--name-only").stdout.split()
        assert sorted(kept) == sorted(name for name in listed if ":" not in name)
        assert set(kept) < set(committed)


def test_a_commit_removes_the_tracked_outputs_its_build_no_longer_writes(tmp_path, monkeypatch):
    """A protocol that renames an output (protocol 5's tier_results.json for protocol 4's
    .yaml): the project's commit removes the previous file, tracked and recorded by HEAD's lock,
    and keeps what the build still writes and what git never tracked."""
    from oodrl.suite.run import _commit_project, superseded_outputs

    def git(*args: str) -> str:
        return run(tmp_path, "git", *args).stdout

    project = tmp_path / "pipeline" / "env"
    (project / "reports").mkdir(parents=True)
    (project / "detectors" / "d").mkdir(parents=True)
    old_lock = {"schema": "2.0", "stages": {
        "tier_metrics": {"cmd": "x", "outs": [{"path": "reports/tier_results.yaml", "md5": "a"},
                                              {"path": "reports/tiers", "md5": "b.dir"}]},
        "collect": {"cmd": "y", "outs": [{"path": "data/id.zarr", "md5": "c.dir"}]},
    }}  # fmt: skip
    detector_lock = {"schema": "2.0", "stages": {
        "cells": {"cmd": "z", "outs": [{"path": "../../cells/d.json", "md5": "d"}]}}}  # fmt: skip
    (project / "dvc.lock").write_text(yaml.safe_dump(old_lock))
    (project / "detectors" / "d" / "dvc.lock").write_text(yaml.safe_dump(detector_lock))
    for name in ("reports/tier_results.yaml", "reports/tiers/tables.md", "reports/other.md"):
        (project / name).parent.mkdir(parents=True, exist_ok=True)
        (project / name).write_text(name)
    git("init", "-q")
    git("add", ".")
    git("commit", "-q", "-m", "protocol 4")

    new_lock = {"schema": "2.0", "stages": {
        "tier_metrics": {"cmd": "x", "outs": [{"path": "reports/tier_results.json", "md5": "e"},
                                              {"path": "reports/tiers", "md5": "f.dir"}]},
    }}  # fmt: skip
    files = {
        "dvc.lock": yaml.safe_dump(new_lock).encode(),
        "detectors/d/dvc.lock": yaml.safe_dump(detector_lock).encode(),
        "reports/tier_results.json": b"{}\n",
        "reports/tiers/tables.md": b"new",
    }
    assert superseded_outputs(tmp_path, "pipeline/env", files) == [
        "pipeline/env/reports/tier_results.yaml"  # not data/id.zarr (untracked), nor the kept
    ]
    for name, data in files.items():
        (project / name).write_bytes(data)
    for key in ("GIT_AUTHOR_NAME", "GIT_AUTHOR_EMAIL", "GIT_COMMITTER_NAME", "GIT_COMMITTER_EMAIL"):
        monkeypatch.setenv(key, "oodrl")  # the head commits in the caller's environment
    _commit_project(tmp_path, "pipeline/env", files, "suite run: pipeline/env built")
    assert not (project / "reports" / "tier_results.yaml").exists()
    assert git("ls-files", "pipeline/env/reports").split() == [
        "pipeline/env/reports/other.md",
        "pipeline/env/reports/tier_results.json",
        "pipeline/env/reports/tiers/tables.md",
    ]
    assert git("status", "--porcelain") == ""
    assert superseded_outputs(tmp_path, "pipeline/env", files) == []  # HEAD's locks are the new
