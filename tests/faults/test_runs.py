"""Runs that meet each other or die (issue 55): a second `oodrl suite run`, `suite try` or `new`
in a checkout another one is using refuses at once, in one line naming the running one's pid and
command; a run killed with its workers (SIGKILL: a lost machine) blocks nothing, and the next run
removes what it left and builds the suite as if nothing had happened.

The suite is the smallest of its shape (as tests/hostile/test_suite_run_hostile.py): the root's
DVC project and pipeline/a, each a stage, and the leaderboard's; the stage sleeps while
OODRL_TEST_SLOW is set, so that a run can be caught in the middle."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from tiny_suite import git, one_pipeline_suite

from oodrl.suite.checkout_lock import CheckoutBusy, checkout_lock, lock_path
from oodrl.suite.scratch import DVC_CONFIG_FOLDER, TASK_FOLDER, TRY_FOLDER, working_folder

pytestmark = pytest.mark.slow

OODRL = str(Path(sys.executable).with_name("oodrl"))
BUILD = ('mkdir -p reports && touch reports/started && if [ -n "$OODRL_TEST_SLOW" ]; then '
         'sleep 300; fi && echo built > reports/results.yaml')  # fmt: skip


def tiny_suite(repo: Path) -> Path:
    return one_pipeline_suite(repo, BUILD)


def _environment(scratch: Path, **more: str) -> dict[str, str]:
    environment = {k: v for k, v in os.environ.items() if k != "OODRL_DEBUG"}
    return {**environment, "TMPDIR": str(scratch), **more}


def _start(repo: Path, scratch: Path) -> subprocess.Popen:
    """`oodrl suite run` with slow stages, in a session of its own."""
    return subprocess.Popen([OODRL, "suite", "run", "--root", str(repo)],
                            env=_environment(scratch, OODRL_TEST_SLOW="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip


def _wait_for(condition, process: subprocess.Popen, what: str, seconds: float = 300) -> None:
    deadline = time.monotonic() + seconds  # a loaded 2-core machine: DVC starts slowly
    while not condition():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, what
        time.sleep(0.1)


def _stages_started(scratch: Path) -> int:
    try:
        return len(list(scratch.glob(f"{TASK_FOLDER}*/repo/**/reports/started")))
    except FileNotFoundError:  # a task directory went while it was read
        return 0


def _kill_run(process: subprocess.Popen, scratch: Path) -> None:
    """SIGKILL the run and every process working in its temporary folders (its git, DVC and
    stage processes lead sessions of their own): what a lost machine does to them."""
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if os.readlink(entry / "cwd").startswith(str(scratch)):
                    os.kill(int(entry.name), signal.SIGKILL)
            except OSError:  # gone meanwhile, or not ours to read
                pass


def _refusal(done: subprocess.CompletedProcess, pid: int) -> str:
    lines = done.stderr.splitlines()
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr and len(lines) == 1, done.stderr
    assert lines[0].startswith("error: ") and f"(pid {pid}: oodrl suite run --root " in lines[0]
    return lines[0]


def test_a_second_run_in_the_checkout_refuses_at_once_naming_the_first(tmp_path):
    repo = tiny_suite(tmp_path / "repo")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    status = git(repo, "status", "--porcelain", "--untracked-files=all")
    first = _start(repo, scratch)
    try:
        _wait_for(lambda: _stages_started(scratch) >= 1, first, "the first run never started")
        environment = _environment(scratch)
        seconds = []
        for args in (["suite", "run", "--root", str(repo)],
                     ["suite", "try", "mine", "--class", "x:Y", "--root", str(repo)],
                     ["new", "mine", "--env", "CartPole-v1", "--train", "ppo", "--root",
                      str(repo)]):  # fmt: skip
            began = time.monotonic()
            done = subprocess.run([OODRL, *args], env=environment, capture_output=True,
                                  text=True, timeout=120)  # fmt: skip
            seconds.append(time.monotonic() - began)
            line = _refusal(done, first.pid)
            assert f"error: {repo}: another oodrl run is using this checkout" in line
            verb = " ".join(args[:2] if args[0] == "suite" else args[:1])
            assert f"`oodrl {verb}` runs one at a time per checkout" in line
        assert max(seconds) < 30, seconds  # at once: no DVC, no status check (imports only)
        assert first.poll() is None  # the first runs on, untouched
        assert not (repo / "pipeline" / "mine").exists()
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            _kill_run(first, scratch)
    assert git(repo, "status", "--porcelain", "--untracked-files=all") == status
    with checkout_lock(repo, "suite run"):  # the first's lock went with it
        pass


def test_a_killed_lock_holder_blocks_nothing(tmp_path):
    """The lock goes with its process, however it ends: SIGKILL gives no chance to release it."""
    repo = tiny_suite(tmp_path / "repo")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom pathlib import Path\n"
         "from oodrl.suite.checkout_lock import checkout_lock\n"
         "with checkout_lock(Path(sys.argv[1]), 'suite run'):\n"
         "    print('held', flush=True)\n    time.sleep(300)\n", str(repo)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        busy = pytest.raises(CheckoutBusy, match=rf"\(pid {holder.pid}: -c {repo}\)")
        with busy, checkout_lock(repo, "suite run"):
            pass
    finally:
        holder.kill()
        holder.wait()
    with checkout_lock(repo, "suite run"):
        assert lock_path(repo) == repo / ".dvc" / "tmp" / "oodrl-run.lock"
    assert git(repo, "status", "--porcelain", "--untracked-files=all") == ""


def _held(path: Path) -> bool:
    """Whether some open file holds the lock (flock: two opens conflict even in one process)."""
    import fcntl

    descriptor = os.open(path, os.O_RDWR)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(descriptor)  # releases it if taken here
    return False


def test_the_process_holding_the_checkout_takes_it_again_and_keeps_it_to_the_outer_end(tmp_path):
    """A verb that runs another's code in-process (`suite try` builds with `suite run`'s) takes
    the lock it holds again without refusing itself; the checkout stays held until the outer
    holder ends."""
    repo = tiny_suite(tmp_path / "repo")
    with checkout_lock(repo, "suite try"):
        with checkout_lock(repo, "suite run"):
            assert _held(lock_path(repo))
        assert _held(lock_path(repo))  # the inner end released nothing
    assert not _held(lock_path(repo))


def test_a_holder_yet_to_write_its_pid_is_named_so(tmp_path):
    """The holder writes its pid just after taking the lock: a refusal in that instant says so
    rather than naming no one or a previous holder."""
    import fcntl

    repo = tiny_suite(tmp_path / "repo")
    path = lock_path(repo)
    path.parent.mkdir(exist_ok=True)
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)  # taken, nothing written yet
        busy = pytest.raises(CheckoutBusy, match=r"\(its pid not yet written\)")
        with busy, checkout_lock(repo, "new"):
            pass
    finally:
        os.close(descriptor)


def test_a_git_checkout_without_dvc_keeps_its_lock_in_git(tmp_path):
    """A checkout with no DVC project yet (`oodrl new` makes one) is still guarded: its lock
    lives in .git, never in the tracked tree."""
    repo = tmp_path / "repo"
    (repo / "sub").mkdir(parents=True)
    git(repo, "init", "-q")
    assert lock_path(repo / "sub") == repo / ".git" / "oodrl-run.lock"
    with checkout_lock(repo / "sub", "new"):
        assert _held(repo / ".git" / "oodrl-run.lock")
    assert git(repo, "status", "--porcelain", "--untracked-files=all") == ""


LEAVE_AND_DIE = """
import os, signal, sys
from pathlib import Path
from oodrl.suite.scratch import working_folder
folders = [working_folder(prefix) for prefix in sys.argv[2:]]  # held: none is finalized
for folder in folders:
    Path(folder.name, "clone").write_text("left by a run killed with its machine")
Path(sys.argv[1], ".mine.new-%d" % os.getpid()).mkdir()  # `oodrl new`'s staging folder
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_run_killed_with_its_workers_leaves_nothing_the_next_run_keeps(tmp_path):
    """SIGKILL of the run and of every process working in its clones, mid-build (a lost
    machine), and of another verb's process holding its folders: the next run neither refuses
    nor finds them; it removes them and builds the suite, ending as a run never interrupted."""
    repo = tiny_suite(tmp_path / "repo")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    (repo / "pipeline").mkdir(exist_ok=True)
    status = git(repo, "status", "--porcelain", "--untracked-files=all")
    run = _start(repo, scratch)
    try:
        _wait_for(lambda: _stages_started(scratch) >= 2, run, "the tasks never started")
    finally:
        _kill_run(run, scratch)
    dead = subprocess.run(
        [
            sys.executable,
            "-c",
            LEAVE_AND_DIE,
            str(repo / "pipeline"),
            TASK_FOLDER,
            DVC_CONFIG_FOLDER,
            TRY_FOLDER,
        ],
        env=_environment(scratch),
    )
    assert dead.returncode == -signal.SIGKILL
    left = sorted(p.name for p in scratch.iterdir())
    assert {name.split("-")[1] for name in left} == {"suite", "dvc", "try"}, left
    assert any(p.name.startswith(".mine.new-") for p in (repo / "pipeline").iterdir())

    with working_folder(TASK_FOLDER) as live:  # a live process's folder is left to it
        done = subprocess.run([OODRL, "suite", "run", "--root", str(repo)],
                              env=_environment(scratch), capture_output=True, text=True,
                              timeout=300)  # fmt: skip
        assert done.returncode == 0, done.stderr
        assert "Traceback" not in done.stderr
        assert Path(live).is_dir()
    assert sorted(p.name for p in scratch.iterdir()) == []
    for built in ("reports/results.yaml", "pipeline/a/reports/results.yaml",
                  "pipeline/suite/leaderboard.txt"):  # fmt: skip
        assert (repo / built).read_text() == "built\n"
    assert not [p for p in (repo / "pipeline").iterdir() if p.name.startswith(".mine.new-")]
    changed = git(repo, "status", "--porcelain", "--untracked-files=all").splitlines()
    assert sorted(set(changed) - set(status.splitlines())) == [  # the locks of a whole build
        "?? dvc.lock", "?? pipeline/a/dvc.lock", "?? pipeline/a/reports/.gitignore",
        "?? pipeline/suite/.gitignore", "?? pipeline/suite/dvc.lock", "?? reports/.gitignore",
    ]  # fmt: skip
