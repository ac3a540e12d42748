"""A DVC remote at fault (issue 55): a fresh clone restores the suite over HTTP from a remote
that serves one object corrupt, truncated, or hangs up mid-object. `oodrl suite run` fails in
one line naming the project, the object (its path and hash), the remote and the failure, and
keeps nothing corrupt: the cache holds only objects whose hash is their name, the checkout is
as it was, the remote's files too. Once the remote is repaired, the same command completes.

The suite is the smallest of its shape (as tests/test_readonly_remote.py): the root's DVC
project, pipeline/a and the leaderboard's, built and pushed to a directory remote by a lab."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from faulty_remote import FaultyRemote, cache_mismatches, object_hash
from tiny_suite import dvc, dvc_project, git

pytestmark = pytest.mark.slow

ROOT = """\
  build:
    cmd: mkdir -p reports && echo root > reports/results.yaml
    outs:
      - reports/results.yaml
"""
PIPELINE = """\
  build:
    cmd: mkdir -p reports && echo pipeline a, a line long enough to cut > reports/results.yaml
    outs:
      - reports/results.yaml
"""
LEADERBOARD = """\
  leaderboard:
    cmd: (echo leaderboard; cat ../a/reports/results.yaml) > leaderboard.txt
    deps:
      - ../a/reports/results.yaml
    outs:
      - leaderboard.txt
"""
OUTPUTS = ("reports/results.yaml", "pipeline/a/reports/results.yaml",
           "pipeline/suite/leaderboard.txt")  # fmt: skip
#: The object the remote fails: pipeline/a's results, which only pipeline/a's task restores.
FAULTY = "pipeline/a/reports/results.yaml"


def _listing(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in directory.rglob("*")
            if p.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def published(tmp_path_factory) -> tuple[Path, Path]:
    """A lab's checkout built (`dvc repro` of each project in turn, what `oodrl suite run`'s
    locks equal) and committed, and its directory remote (every output pushed)."""
    lab = tmp_path_factory.mktemp("published")
    repo, remote = lab / "repo", lab / "remote"
    dvc_project(repo, None, ROOT)
    dvc_project(repo / "pipeline" / "a", "../../../.dvc/cache", PIPELINE)
    dvc_project(repo / "pipeline" / "suite", "../../../.dvc/cache", LEADERBOARD)
    git(repo, "init", "-q")
    git(repo, "add", "-A")
    git(repo, "commit", "-q", "-m", "a tiny suite")
    remote.mkdir()
    for project in (repo, repo / "pipeline" / "a", repo / "pipeline" / "suite"):  # as a lab
        dvc(project, "remote", "add", "--local", "-d", "lab", str(remote))
        dvc(project, "repro", "-q")
        dvc(project, "push", "-q")
    git(repo, "add", "-A")
    git(repo, "commit", "-q", "-m", "built")
    return repo, remote


def _suite_run(clone: Path, scratch: Path) -> subprocess.CompletedProcess:
    command = [str(Path(sys.executable).with_name("oodrl")), "suite", "run", "--root", str(clone)]
    environment = {k: v for k, v in os.environ.items() if k != "OODRL_DEBUG"}
    return subprocess.run(command, env={**environment, "TMPDIR": str(scratch)},
                          capture_output=True, text=True, timeout=300)  # fmt: skip


#: Each fault, and how the line names it ({size}: the object's size in the lock).
FAULTS = (
    ("flip", "corrupt: {size} bytes that hash to "),
    ("cut", "truncated: {half} of its {size} bytes arrived"),
    ("drop", "the connection broke mid-object (ClientPayloadError"),
)


def test_a_faulty_remote_is_named_nothing_corrupt_is_kept_and_a_retry_completes(
    published, tmp_path
):
    """The three faults one after the other on one clone (each run fails the same way, the
    checkout untouched), then the remote repaired: the same command completes."""
    lab, directory = published
    served = _listing(directory)
    oid = object_hash(lab / FAULTY)
    size = (lab / FAULTY).stat().st_size
    remote = FaultyRemote(directory, {oid})
    try:
        clone = tmp_path / "clone"
        git(lab.parent, "clone", "-q", str(lab), str(clone))
        dvc(clone, "remote", "add", "--local", "-d", "pub", remote.url)
        status = git(clone, "status", "--porcelain", "--untracked-files=all")
        scratch = tmp_path / "tmp"
        scratch.mkdir()
        cache = clone / ".dvc" / "cache"
        for mode, failure in FAULTS:
            remote.mode = mode
            done = _suite_run(clone, scratch)
            assert done.returncode == 1, (mode, done.stderr)
            assert "Traceback" not in done.stderr + done.stdout
            errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
            assert len(errors) == 1 and done.stderr.splitlines()[-1] == errors[0], done.stderr
            line = errors[0]
            assert line.startswith("error: pipeline/a: DVC remote 'pub' "), line
            assert (f"({remote.url}) did not deliver reports/results.yaml intact (object {oid}, "
                    f"{remote.url}files/md5/{oid[:2]}/{oid[2:]}): ") in line  # fmt: skip
            assert failure.format(size=size, half=size // 2) in line, line
            assert "nothing of it was kept" in line and "internal error" not in line
            # Nothing corrupt kept, nothing half-written: the cache's objects all hash to
            # their names and the faulty one is absent; the checkout and the remote are as
            # they were; no temporary folder is left.
            assert cache_mismatches(cache) == []
            assert not (cache / "files" / "md5" / oid[:2] / oid[2:]).exists()
            assert git(clone, "status", "--porcelain", "--untracked-files=all") == status
            assert not (clone / FAULTY).exists()
            assert _listing(directory) == served
            assert sorted(scratch.iterdir()) == []

        remote.mode = "ok"  # the remote repaired: the same command completes
        done = _suite_run(clone, scratch)
        assert done.returncode == 0, done.stderr
        assert {path: (clone / path).read_bytes() for path in OUTPUTS} == {
            path: (lab / path).read_bytes() for path in OUTPUTS
        }
        assert cache_mismatches(cache) == []
        assert git(clone, "status", "--porcelain", "--untracked-files=all") == status
    finally:
        remote.close()
