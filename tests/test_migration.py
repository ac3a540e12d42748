"""A protocol change that lands a step at a time (SPEC §26): the two-environment suite built and
committed at this protocol, then the protocol bumped in its own code (stamp.py's
PROTOCOL_VERSION, which its stages run) and committed with no pipeline rebuilt: every pipeline
pending, the checks passing. `oodrl suite run --commit` then builds and commits a pipeline at a
time; killed (SIGKILL) after its first commit, it resumes in a fresh clone with an empty DVC
cache, builds only what is left, and ends where a build in one go ends, byte for byte. Each
refusal is one line before anything runs, with nothing committed.

Real git, DVC, processes and HTTP servers on loopback. The suite is built once, at this
protocol; after the bump, the stages whose code stamps it changed (a few a pipeline) run in one
go, and in two steps split by the kill, the other outputs pulled from the lab's remote. Every
other test here runs in a clone and stops before any stage."""

from __future__ import annotations

import contextlib
import http.server
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from suite_repo import (
    SUITE,
    code_env,
    copy_built,
    head_commit,
    locks,
    run_folder,
    serial_built_suite,
)

from oodrl.suite.checkout_lock import checkout_lock
from oodrl.suite.run import RUN_META, _push
from oodrl.testing.pipeline import environment, run

pytestmark = pytest.mark.slow

PIPELINES = [".", "pipeline/cartpole"]
STAMP = Path("src", "oodrl", "metrics", "stamp.py")


def version_of(repo: Path) -> int:
    return int(re.search(r"^PROTOCOL_VERSION = (\d+)", (repo / STAMP).read_text(), re.M)[1])


@pytest.fixture(scope="module")
def lab(tmp_path_factory, repo_root) -> tuple[Path, Path]:
    """A lab's checkout and its DVC remote (a directory): the suite built at this protocol (the
    test run's one serial build, `suite_repo.serial_built_suite`: the locks `oodrl suite run`
    writes too, test_suite_run checks), pushed as `oodrl suite run` pushes a project, and
    committed; then the protocol bumped and committed, no pipeline rebuilt: every pipeline
    pending. Every clone below comes from it, and reads the remote over HTTP, read-only: a clone
    pulls the outputs of the stages the bump left as they were and computes the others, pushing
    nothing."""
    folder = tmp_path_factory.mktemp("lab")
    built, _ = serial_built_suite(repo_root, head_commit(repo_root), run_folder(tmp_path_factory))
    repo = copy_built(built, folder / "repo")
    remote = folder / "remote"
    remote.mkdir()
    for project in [*PIPELINES, SUITE]:  # each a DVC project of its own
        run(repo / project, "dvc", "remote", "add", "--local", "-d", "lab", str(remote))
        _push(repo / project, code_env(repo))
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "built")
    stamp = repo / STAMP
    version = version_of(repo)
    stamp.write_text(stamp.read_text().replace(f"PROTOCOL_VERSION = {version}",
                                               f"PROTOCOL_VERSION = {version + 1}"))  # fmt: skip
    run(repo, "git", "commit", "-q", "-am", f"protocol {version + 1}")
    return repo, remote


def clone(source: Path, dest: Path, url: str | None = None) -> Path:
    """A fresh clone (git's files only, an empty DVC cache), whose default DVC remote is `url`
    (in config.local, as docs/how-to/remotes.md says), if any."""
    run(source.parent, "git", "clone", "-q", str(source), str(dest))
    assert not (dest / ".dvc" / "cache").exists()
    if url is not None:
        run(dest, "dvc", "remote", "add", "--local", "-d", "pub", url)
    return dest


def head(repo: Path) -> str:
    return run(repo, "git", "rev-parse", "HEAD").stdout.strip()


def subjects(repo: Path, since: str) -> list[str]:
    """The subjects of the commits after `since`, oldest first."""
    log = run(repo, "git", "log", "--reverse", "--format=%s", f"{since}..HEAD").stdout
    return log.splitlines()


def suite_run(repo: Path, *args: str) -> subprocess.CompletedProcess:
    """`oodrl suite run` in a process of its own, as a maintainer runs it, on the checkout's
    own code (its PROTOCOL_VERSION is the target)."""
    command = [sys.executable, "-m", "oodrl", "suite", "run", "--root", str(repo), *args]
    return subprocess.run(command, env=environment(code_env(repo)), capture_output=True,
                          text=True)  # fmt: skip


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


def _descendants(pid: int) -> list[int]:
    """Every process below `pid` (its stage commands lead process groups of their own)."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        parents.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        children = parents.get(todo.pop(), [])
        found += children
        todo += children
    return found


def _kill_after_first_commit(repo: Path, since: str) -> list[str]:
    """`oodrl suite run --commit --workers 1`, SIGKILLed with every process it started as soon
    as it has committed a pipeline (a machine lost mid-build): the commits it made."""
    command = [sys.executable, "-m", "oodrl", "suite", "run", "--commit", "--workers", "1"]
    quiet = subprocess.DEVNULL
    process = subprocess.Popen(command, cwd=repo, env=environment(code_env(repo)), stdout=quiet,
                               stderr=quiet)  # fmt: skip
    try:
        while not subjects(repo, since):
            assert process.poll() is None, "the run ended before its first commit"
            time.sleep(0.2)
    finally:
        for pid in [process.pid, *_descendants(process.pid)]:
            with contextlib.suppress(ProcessLookupError):  # ended meanwhile
                os.kill(pid, signal.SIGKILL)
        process.wait()
    return subjects(repo, since)


def test_a_run_killed_after_its_first_commit_resumes_in_a_fresh_clone(lab, tmp_path, serve):
    repo, remote = lab
    version, bumped, url = version_of(repo), head(repo), serve(remote)

    # The reference: the migration in one go.
    one_go = clone(repo, tmp_path / "one-go", url)
    built = suite_run(one_go, "--commit")
    assert built.returncode == 0, built.stdout + built.stderr
    made = [re.sub(r" in \d+ s$", "", subject) for subject in subjects(one_go, bumped)]
    assert sorted(made[:2]) == [f"suite run: {p} built at protocol {version}" for p in PIPELINES]
    assert made[2:] == [f"suite run: {SUITE} (the leaderboard) built at protocol {version}, "
                        f"every pipeline current"]  # fmt: skip
    progress = [line for line in built.stdout.splitlines() if " done, committed; " in line]
    assert [re.sub(r", \d+:\d\d:\d\d elapsed$", "", line.split("; ")[1]) for line in progress] == [
        "1 of 2 done, 1 to do",
        "2 of 2 done, 0 to do",
    ]

    # The same migration, its machine lost once the first pipeline is committed.
    killed = clone(repo, tmp_path / "killed", url)
    (first,) = _kill_after_first_commit(killed, bumped)
    done = re.fullmatch(r"suite run: (\S+) built at protocol (\d+) in \d+ s", first)
    assert done and done[2] == str(version), first
    (rest,) = [pipeline for pipeline in PIPELINES if pipeline != done[1]]

    # Another machine: a fresh clone of what was committed, an empty DVC cache.
    resumed = clone(killed, tmp_path / "resumed", url)
    since = head(resumed)
    nothing = suite_run(resumed, "--only", done[1])
    assert nothing.returncode == 0, nothing.stdout + nothing.stderr
    assert f"suite: nothing to build among {done[1]}; still to build: {rest}" in nothing.stdout
    again = suite_run(resumed, "--commit")
    assert again.returncode == 0, again.stdout + again.stderr
    lines = again.stdout.splitlines()
    assert [line for line in lines if line.startswith("started")] == [f"started  {rest}"]
    assert [re.sub(r" in \d+ s$", "", s) for s in subjects(resumed, since)] == [
        f"suite run: {rest} built at protocol {version}",
        f"suite run: {SUITE} (the leaderboard) built at protocol {version}, every pipeline current",
    ]
    # Byte for byte the one-go build: every tracked file (locks, results, leaderboard).
    assert locks(resumed) == locks(one_go)
    tree = "HEAD^{tree}"
    assert (
        run(resumed, "git", "rev-parse", tree).stdout
        == run(one_go, "git", "rev-parse", tree).stdout
    )
    # The migration has ended: from git alone, nothing is left to build or commit.
    last = head(resumed)
    ended = suite_run(resumed, "--commit")
    assert ended.returncode == 0, ended.stdout + ended.stderr
    assert ended.stdout.splitlines()[-1].endswith("nothing to run"), ended.stdout
    assert head(resumed) == last  # no commit


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
