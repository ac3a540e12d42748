"""A protocol change that lands a step at a time (SPEC §26): the two-environment suite built and
committed at this protocol, then the protocol bumped in its own code (stamp.py's
PROTOCOL_VERSION, which its stages run) and committed with no pipeline rebuilt: every pipeline
pending, the checks passing. Each refusal of `oodrl suite run` is one line before anything runs,
with nothing committed. (A run killed after its first commit and resumed in a fresh clone:
tests/test_migration_resume.py, on the same lab.)

Real git, DVC, processes and HTTP servers on loopback. The suite is built once, at this
protocol (tests/migration_lab.py); every test here runs in a clone of the lab and stops before
any stage."""

from __future__ import annotations

import http.server
import sys
import threading
from pathlib import Path

import pytest
from migration_lab import PIPELINES, clone, head, migration_lab, suite_run, version_of
from suite_repo import SUITE, code_env, locks

from oodrl.suite.checkout_lock import checkout_lock
from oodrl.suite.run import RUN_META
from oodrl.testing.pipeline import run

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def lab(tmp_path_factory, repo_root) -> tuple[Path, Path]:
    return migration_lab(tmp_path_factory, repo_root)


def state(repo: Path) -> tuple:
    return head(repo), run(repo, "git", "status", "--porcelain").stdout, locks(repo)


def refused(repo: Path, *args: str, code: int) -> str:
    """`oodrl suite run ARGS` refused with exit `code` in one line, nothing committed or
    changed: that line."""
    before = state(repo)
    result = suite_run(repo, *args)
    assert result.returncode == code, result.stdout + result.stderr
    (error,) = result.stderr.splitlines()
    assert error.startswith("error: "), result.stderr
    assert state(repo) == before
    return error


STATES = """
import sys
from pathlib import Path
from oodrl.suite.migration import project_states
for state in project_states(Path(sys.argv[1])):
    print(state.project, state.status, state.built_version)
"""


def test_a_protocol_bump_lands_with_every_pipeline_pending(lab):
    repo, _ = lab
    version = version_of(repo)
    states = run(repo, sys.executable, "-c", STATES, str(repo), env=code_env(repo)).stdout
    assert states.splitlines() == [f"{p} pending {version - 1}" for p in PIPELINES]
    check = run(repo, "oodrl", "pipeline", "check", env=code_env(repo), check=False)
    assert check.returncode == 0, check.stdout + check.stderr
    # The leaderboard is the previous version's, labelled so, until every pipeline is rebuilt.
    leaderboard = (repo / SUITE / "reports" / "leaderboard.md").read_text()
    assert f"Protocol version {version - 1};" in leaderboard


@pytest.fixture
def pending(lab, tmp_path) -> Path:
    """A clone of the lab, every pipeline pending; no remote."""
    return clone(lab[0], tmp_path / "clone")


def test_commit_refuses_uncommitted_changes(pending):
    readme = pending / "README.md"
    readme.write_text(readme.read_text() + "\nedited\n")
    error = refused(pending, "--commit", code=2)
    assert "--commit: README.md: uncommitted" in error


def test_commit_refuses_a_detached_head(pending):
    run(pending, "git", "checkout", "-q", "--detach")
    assert "has a detached HEAD" in refused(pending, "--commit", code=2)


def test_commit_refuses_the_middle_of_a_merge(pending):
    run(pending, "git", "checkout", "-q", "-b", "other")
    (pending / "README.md").write_text("theirs\n")
    run(pending, "git", "commit", "-q", "-am", "theirs")
    run(pending, "git", "checkout", "-q", "-")
    (pending / "README.md").write_text("ours\n")
    run(pending, "git", "commit", "-q", "-am", "ours")
    assert run(pending, "git", "merge", "-q", "other", check=False).returncode != 0  # a conflict
    assert "is in the middle of a merge" in refused(pending, "--commit", code=2)


def test_an_unknown_pipeline_is_refused(pending):
    error = refused(pending, "--only", "pipeline/cartpole,pipeline/nope", code=2)
    assert "--only pipeline/nope: not a pipeline of the suite; its pipelines: ., " in error


def test_commit_refuses_a_pipeline_stale_for_another_reason(pending):
    # Before the bump every pipeline is current; a knob committed without its relock is not.
    run(pending, "git", "switch", "-q", "-c", "before-the-bump", "HEAD~1")
    params = pending / "pipeline" / "cartpole" / "params.yaml"
    params.write_text(params.read_text() + "metrics:\n  n_boot: 21\n")
    run(pending, "git", "commit", "-q", "-am", "a CartPole knob, not relocked")
    error = refused(pending, "--commit", code=2)
    assert "pipeline/cartpole" in error.split(": stale, not pending")[0], error


def test_a_second_run_is_refused_by_the_checkout_lock(pending):
    with checkout_lock(pending, "suite run"):
        second = suite_run(pending, "--commit")
    assert second.returncode == 1
    assert second.stdout.splitlines() == []
    assert "another oodrl run is using this checkout" in second.stderr.splitlines()[-1]


@pytest.fixture
def refusing_server():
    """An HTTP server on loopback that answers 403 to every request: its URL."""

    class Refusing(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

        def do_HEAD(self) -> None:  # noqa: N802 - http.server's name
            self.send_response(403)
            self.send_header("Content-Length", "0")
            self.end_headers()

        do_GET = do_POST = do_HEAD  # noqa: N815

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Refusing)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()
    server.server_close()


def test_a_remote_that_refuses_is_named_before_any_stage(pending, refusing_server):
    run(pending, "dvc", "remote", "add", "--local", "-d", "pub", refusing_server)
    error = refused(pending, code=1)
    assert f"DVC remote 'pub' ({refusing_server}) refuses the objects" in error
    assert "HTTP 403 to each of the" in error and "--build-missing" in error


def test_a_remote_that_has_nothing_is_named_and_passed_only_when_asked(pending, serve, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    url = serve(empty)
    run(pending, "dvc", "remote", "add", "--local", "-d", "pub", url)
    error = refused(pending, "--commit", code=1)
    assert f"DVC remote 'pub' ({url}) has none of the " in error and "(HTTP 404)" in error
    # Asked, the run goes on past the remote; a budget that each pipeline's last build would
    # pass (ten hours, as a real environment's) then starts none, and says what is left.
    for pipeline in PIPELINES:
        meta = pending / pipeline / RUN_META
        meta.parent.mkdir(parents=True, exist_ok=True)
        meta.write_text("total_stage_wall_s: 36000.0\n")
    before = state(pending)
    short = suite_run(pending, "--commit", "--build-missing", "--max-hours", "0.5")
    assert short.returncode == 0, short.stdout + short.stderr
    assert "has none of the" in short.stdout and "(--build-missing)" in short.stdout
    assert (
        f"--max-hours 0.5 reached; 2 pipelines left for another run: {', '.join(PIPELINES)}"
        in short.stdout
    )
    assert "started" not in short.stdout and state(pending) == before
