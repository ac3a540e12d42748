"""Faults of the machine named as faults (issue 55, SPEC §22): a full disk and a read-only
filesystem, real ones (a small tmpfs mounted for the test: skipped, with the reason, where this
machine lets no test mount one), met by a stage verb writing its store and by `oodrl suite run`'s
git and DVC processes. Each: exit 1, one line naming the path and what to do (never "internal
error ... a bug"), no traceback, and nothing half-written: the output absent, the project's
files as they were, no temporary folder left."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from tiny_suite import git, one_pipeline_suite

from oodrl.faults import FAULTS, fault_in_output, machine_fault

OODRL = str(Path(sys.executable).with_name("oodrl"))


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in directory.rglob("*")
            if p.is_file() and ".git" not in p.parts}  # fmt: skip


def _mount(target: Path, options: str) -> None:
    """A tmpfs at `target` (as root, or through passwordless sudo); skip the test otherwise."""
    reasons = []
    for prefix in ([], ["sudo", "-n"]):
        if prefix and shutil.which("sudo") is None:
            continue
        done = subprocess.run([*prefix, "mount", "-t", "tmpfs", "-o", options, "tmpfs",
                               str(target)], capture_output=True, text=True)  # fmt: skip
        if done.returncode == 0:
            return
        reasons.append(" ".join(done.stderr.split()) or f"exit {done.returncode}")
    pytest.skip(f"a real full or read-only disk needs a tmpfs mount, which this machine refuses "
                f"({'; '.join(reasons)})")  # fmt: skip


def _unmount(target: Path) -> None:
    for prefix in ([], ["sudo", "-n"]):
        if subprocess.run([*prefix, "umount", str(target)], capture_output=True).returncode == 0:
            return


@contextlib.contextmanager
def _tmpfs(target: Path, options: str) -> Iterator[Path]:
    """A tmpfs mounted at `target` (made here) while the block runs."""
    target.mkdir()
    _mount(target, options)
    try:
        yield target
    finally:
        _unmount(target)


@pytest.fixture
def full_disk(tmp_path) -> Path:
    """A 64 KiB filesystem with no space left (a filler file took it), writable by anyone."""
    with _tmpfs(tmp_path / "disk", "size=64k,mode=1777") as disk:
        with open(disk / "filler", "wb", buffering=0) as filler, pytest.raises(OSError) as full:
            while True:
                filler.write(b"\0" * 4096)
        assert full.value.errno == errno.ENOSPC
        (disk / "data").mkdir()  # a folder takes no block of a tmpfs
        yield disk


@pytest.fixture
def read_only_disk(tmp_path) -> Path:
    with _tmpfs(tmp_path / "ro", "size=64k,ro") as disk:
        yield disk


@pytest.fixture(scope="module")
def project(tmp_path_factory, repo_root) -> Path:
    """A pipeline's working directory at CI params and the committed policy."""
    root = tmp_path_factory.mktemp("project")
    done = subprocess.run([OODRL, "check-params", str(repo_root / "ci/params.yaml"), "--merged",
                           str(root / "params.yaml")], capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stderr
    (root / "models").mkdir()
    shutil.copy(repo_root / "models/policy.pt", root / "models/policy.pt")
    return root


def _one_line(done: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and done.stderr.splitlines()[-1] == errors[0], done.stderr
    assert done.returncode == 1, (done.returncode, done.stderr)
    assert "internal error" not in errors[0] and "a bug" not in errors[0], errors[0]
    return errors[0]


def _oodrl(*args: str, cwd: Path, **env: str) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "OODRL_DEBUG"} | env
    return subprocess.run([OODRL, *args], cwd=cwd, env=environment, capture_output=True,
                          text=True, timeout=300)  # fmt: skip


def test_a_stage_on_a_full_disk_names_the_path_and_leaves_no_store(project, full_disk):
    before = _snapshot(project)
    out = full_disk / "data" / "eval.zarr"
    done = _oodrl("collect-eval", "--policy", "models/policy.pt", "--out", str(out), cwd=project)
    line = _one_line(done)
    assert line.startswith(f"error: {full_disk / 'data'}/"), line  # the file it was writing
    assert "no space left; free space on that filesystem" in line, line
    assert list((full_disk / "data").iterdir()) == []  # no store, no temporary one
    assert _snapshot(project) == before


def test_a_stage_on_a_read_only_filesystem_names_it(project, read_only_disk):
    before = _snapshot(project)
    out = read_only_disk / "data" / "id.zarr"
    done = _oodrl("collect-id", "--policy", "models/policy.pt", "--out", str(out), cwd=project)
    line = _one_line(done)
    assert line.startswith(f"error: {read_only_disk}/"), line
    assert "read-only filesystem" in line, line
    assert list(read_only_disk.iterdir()) == []
    assert _snapshot(project) == before


def test_suite_run_with_its_temporary_folder_on_a_full_disk(tmp_path, full_disk):
    """The run's git bundle and clones go to the temporary directory: with 8 KiB left there, git
    fails, or the task's copy of the bundle does where git's own fitted (either, from run to
    run: a full test run under load saw the second), and the run says so in one line, naming
    the folder; the checkout is as it was."""
    repo = tmp_path / "repo"
    one_pipeline_suite(repo, "mkdir -p reports && echo x > reports/results.yaml")
    before = _snapshot(repo)
    scratch = full_disk / "data"
    filler = full_disk / "filler"
    os.truncate(filler, filler.stat().st_size - 8192)  # Python's probe of TMPDIR must pass
    done = _oodrl("suite", "run", "--root", str(repo), cwd=tmp_path, TMPDIR=str(scratch))
    line = _one_line(done)
    where = rf"`git (bundle|clone)` in |{re.escape(str(scratch))}/oodrl-suite-[^/]+/head\.bundle: "
    assert re.match(rf"error: (pipeline/a: |\.: )?({where})", line), line
    assert f": {scratch}/oodrl-suite-" in line, line
    assert "no space left; free space on that filesystem" in line, line
    assert list(scratch.iterdir()) == []
    assert {k: v for k, v in _snapshot(repo).items() if "/tmp/" not in f"/{k}"} == {
        k: v for k, v in before.items() if "/tmp/" not in f"/{k}"
    }
    assert git(repo, "status", "--porcelain", "--untracked-files=all") == ""


# -- the rule itself, on exceptions and on other processes' words ------------------------------
@pytest.mark.parametrize("number", sorted(FAULTS), ids=errno.errorcode.get)
def test_every_fault_is_named_with_its_path_and_what_to_do(number):
    error = OSError(number, os.strerror(number), "/data/x.zarr")
    line = machine_fault(error)
    assert line == f"/data/x.zarr: {FAULTS[number]}"
    wrapped = RuntimeError("a library's own words")
    wrapped.__cause__ = error
    assert machine_fault(wrapped) == line
    said = f"ERROR: unexpected error - [Errno {number}] {os.strerror(number)}: '/data/x.zarr'"
    assert fault_in_output(said) == line


def test_other_errors_are_no_fault_of_the_machine():
    assert machine_fault(FileNotFoundError(errno.ENOENT, "No such file", "x")) is None
    assert machine_fault(ValueError("x")) is None
    assert fault_in_output("ERROR: failed to reproduce 'build'") is None
    assert fault_in_output("fatal: write error: No space left on device", "/tmp/b") == (
        f"/tmp/b: {FAULTS[errno.ENOSPC]}"
    )
