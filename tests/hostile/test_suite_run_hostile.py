"""`oodrl suite run` against hostile inputs (issue 37): a DVC remote whose directory does not
exist, a --ray address where something other than Ray answers, the checks that need no DVC made
before where the projects stand is decided, and a run ended by SIGTERM. Each refusal is one line
and changes nothing.

The repository is the suite's shape at its smallest: the root's DVC project and one pipeline's
(pipeline/a), each one stage, and the leaderboard's project (pipeline/suite) reading the
pipeline's results; `oodrl suite run` builds it as it builds the real suite."""

from __future__ import annotations

import http.server
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from tiny_suite import dvc, git, one_pipeline_suite
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.metrics.stamp import PROTOCOL_VERSION
from oodrl.suite import migration
from oodrl.suite import run as suite_run
from oodrl.suite.run import SuiteRunError, run_suite

QUICK = "mkdir -p reports && echo built > reports/results.yaml"
#: A stage that marks its start in its clone, then runs long enough to be interrupted.
SLOW = "mkdir -p reports && touch reports/started && sleep 300 && echo built > reports/results.yaml"


def with_remote(repo: Path, url: Path) -> Path:
    """The remote as the remotes how-to says: the root's git-ignored config.local, the default."""
    dvc(repo, "remote", "add", "--local", "-d", "lab", str(url))
    return repo


def _files(directory: Path) -> dict[str, bytes]:
    """Every file under `directory` but git's and DVC's own scratch."""
    files = {path.relative_to(directory): path for path in directory.rglob("*") if path.is_file()}
    return {
        name.as_posix(): path.read_bytes()
        for name, path in files.items()
        if ".git" not in name.parts and "tmp" not in name.parts
    }


# -- 1. a directory remote that does not exist -------------------------------------------------
def test_a_missing_directory_remote_is_refused_and_not_created(tmp_path):
    missing = tmp_path / "typo" / "remote"
    repo = with_remote(one_pipeline_suite(tmp_path / "repo", QUICK), missing)
    before = _files(tmp_path)
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(repo), "--workers", "2"])
    assert result.exit_code == 1, result.output
    # The error alone, after the one line that says what is being checked: nothing ran.
    assert [line for line in result.output.splitlines() if not line.startswith("suite: ")] == [
        result.output.splitlines()[-1]
    ] and result.output.splitlines()[-1].startswith("error: ")
    assert f"DVC remote 'lab': {missing} does not exist; create the directory yourself" in (
        result.output
    )
    assert not (tmp_path / "typo").exists()
    assert _files(tmp_path) == before


def test_a_remote_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "remote").write_text("not a directory\n")
    repo = with_remote(one_pipeline_suite(tmp_path / "repo", QUICK), tmp_path / "remote")
    with pytest.raises(SuiteRunError, match="remote is not a directory; create the directory"):
        suite_run._check_writable(repo, suite_run.default_remote(repo))


def test_a_root_cache_moved_by_config_is_refused_before_any_task(tmp_path, status_calls):
    """Local tasks fill the root's cache; pipeline/a's .dvc/config names the root's .dvc/cache,
    which `dvc cache dir --local` moved away: the head could not check pipeline/a out."""
    repo = one_pipeline_suite(tmp_path / "repo", QUICK, stamped=True)
    dvc(repo, "cache", "dir", "--local", str(tmp_path / "elsewhere"))
    before = _files(tmp_path)
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(repo), "--workers", "2"])
    assert result.exit_code == 2, result.output
    error = result.output.splitlines()[-1]
    assert error.startswith("error: pipeline/a uses the DVC cache ") and "elsewhere" in error
    assert "dvc cache dir --local" in error
    # Unbuilt, both pipelines are pending (decided from git alone, no `dvc status`): the
    # refusal comes once they are to build, before any task starts.
    assert result.output.splitlines()[:-1] == [
        "suite: 3 projects; checking the DVC remote first",
        "suite: from git, 0 of 2 pipelines current; pending: . (protocol 0), "
        "pipeline/a (protocol 0)",
    ]
    assert status_calls == [("project_states", (".", "pipeline/a"))]
    assert _files(tmp_path) == before
    # The same cache given to every project, as the line says: the run goes on and builds both.
    for project in (repo / "pipeline" / "a", repo / "pipeline" / "suite"):
        dvc(project, "cache", "dir", "--local", str(tmp_path / "elsewhere"))
    built = run_suite(repo, workers=2, echo=lambda line: None)
    assert sorted(run.pipeline for run in built.pipelines) == [".", "pipeline/a"]
    assert built.head_ran == ("pipeline/suite:leaderboard",)
    lines: list[str] = []  # built at this protocol (stamped): current, from git and DVC
    assert run_suite(repo, workers=2, echo=lines.append).pipelines == ()
    assert lines[-1] == "suite: all 3 projects are up to date; nothing to run"


# -- 2. a --ray address where something other than Ray answers ---------------------------------
@pytest.fixture
def http_server():
    """A loopback HTTP server on a free port: it accepts TCP, as a Ray head would."""

    class Quiet(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_a_ray_address_that_is_not_ray_is_refused_in_seconds(http_server, tmp_path):
    repo = one_pipeline_suite(tmp_path / "repo", QUICK)
    began = time.monotonic()
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(repo), "--ray", http_server])
    seconds = time.monotonic() - began
    assert result.exit_code == 1, result.output
    assert (
        result.output.splitlines()[0]
        == "suite: 3 projects; checking the DVC remote and the Ray head first"
    )
    assert result.output.count("\n") == 2
    assert f"--ray: {http_server} accepts connections but does not answer as a Ray head" in (
        result.output
    )
    # ray.init went on for minutes; the handshake is bounded (a loaded machine: some slack).
    assert seconds < suite_run.RAY_HANDSHAKE_S + 10


# A real Ray head passes the handshake: tests/test_suite_run_ray.py (one cluster a run).


# -- 3. the checks that need no DVC first, and a line at once ----------------------------------
@pytest.fixture
def status_calls(monkeypatch) -> list[tuple]:
    """Where the projects stand, asked in order: ("project_states", pipelines) for the
    pipelines decided from git (oodrl.suite.migration, answered as it answers), ("dvc status",
    project) for a project DVC is asked about (found current)."""
    calls: list[tuple] = []
    decide = migration.project_states

    def project_states(root: Path, projects=None, **options):
        calls.append(("project_states", tuple(projects or ())))
        return decide(root, projects, **options)

    def up_to_date(project: Path) -> bool:
        calls.append(("dvc status", project.name))
        return True

    monkeypatch.setattr(migration, "project_states", project_states)
    monkeypatch.setattr(suite_run, "_up_to_date", up_to_date)
    return calls


def test_the_remote_is_refused_before_any_dvc_status(tmp_path, status_calls):
    (tmp_path / "remote").write_text("not a directory\n")
    repo = with_remote(one_pipeline_suite(tmp_path / "repo", QUICK), tmp_path / "remote")
    with pytest.raises(SuiteRunError, match="is not a directory"):
        run_suite(repo, workers=2, echo=lambda line: None)
    assert status_calls == []


def test_ray_without_a_remote_is_refused_before_any_dvc_status(tmp_path, status_calls, monkeypatch):
    from oodrl.errors import ConfigError

    monkeypatch.setattr(suite_run, "_check_reachable", lambda address: None)  # a live cluster
    repo = one_pipeline_suite(tmp_path / "repo", QUICK)
    with pytest.raises(ConfigError, match="--ray: the nodes share stages through a DVC remote"):
        run_suite(repo, workers=2, ray_address="127.0.0.1:6379", echo=lambda line: None)
    assert status_calls == []


def test_a_progress_line_comes_before_the_status_checks(tmp_path, monkeypatch):
    """A first line before DVC is even imported (finding 7: minutes of silence before)."""
    (tmp_path / "remote").mkdir()
    repo = with_remote(one_pipeline_suite(tmp_path / "repo", QUICK), tmp_path / "remote")
    lines: list[str] = []
    seen_by_states: list[list[str]] = []
    seen_by_status: list[list[str]] = []

    def project_states(root: Path, projects=None, **options):  # every pipeline current
        seen_by_states.append(list(lines))
        return [migration.ProjectState(p, migration.CURRENT, PROTOCOL_VERSION) for p in projects]

    def up_to_date(project: Path) -> bool:
        seen_by_status.append(list(lines))
        return True

    monkeypatch.setattr(migration, "project_states", project_states)
    monkeypatch.setattr(suite_run, "_up_to_date", up_to_date)
    run_suite(repo, workers=2, echo=lines.append)
    assert seen_by_states == [["suite: 3 projects; checking the DVC remote first"]]
    # Where the pipelines stand is one line, before the suite's own project is asked of DVC.
    assert seen_by_status == [
        ["suite: 3 projects; checking the DVC remote first",
         "suite: from git, 2 of 2 pipelines current"]
    ]  # fmt: skip
    assert lines[-1] == "suite: all 3 projects are up to date; nothing to run"


# -- 4. SIGTERM during a run ---------------------------------------------------------------------
def _started(scratch: Path) -> int:
    """How many tasks' stages have begun (their clones hold the stage's mark)."""
    try:
        return len(list(scratch.glob("oodrl-suite-*/repo/**/reports/started")))
    except FileNotFoundError:  # a task directory went while it was read
        return 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP"])
def test_a_signal_mid_run_leaves_no_temporary_directory(tmp_path, name):
    (tmp_path / "remote").mkdir()  # with a remote: each task and the head have a DVC config dir
    repo = with_remote(one_pipeline_suite(tmp_path / "repo", SLOW), tmp_path / "remote")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    status = git(repo, "status", "--porcelain", "--untracked-files=all")
    command = [str(Path(sys.executable).parent / "oodrl"), "suite", "run", "--root", str(repo)]
    process = subprocess.Popen(
        command, env={**os.environ, "TMPDIR": str(scratch)}, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 300  # a loaded 2-core machine: DVC starts slowly
        while _started(scratch) < 2:  # both tasks (the root's and pipeline/a) in their stage
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "the tasks never started their stages"
            time.sleep(0.2)
        assert len(list(scratch.glob("oodrl-dvc-config-*"))) == 3  # two tasks' and the head's
        process.send_signal(getattr(signal, name))
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode != 0
    assert "Traceback" not in stderr
    assert sorted(path.name for path in scratch.iterdir() if path.name.startswith("oodrl-")) == []
    assert git(repo, "status", "--porcelain", "--untracked-files=all") == status


def test_a_root_that_is_no_suite_is_one_line_and_exit_2(tmp_path):
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(tmp_path)])
    assert result.exit_code == 2 and result.output.count("\n") == 1
    assert "not an oodrl suite (no pipeline/suite/dvc.yaml)" in result.output
