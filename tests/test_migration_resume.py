"""A migration's run killed and resumed (SPEC §26): in a clone of the lab (tests/migration_lab.py:
the two-environment suite built at this protocol, then the protocol bumped with every pipeline
pending), `oodrl suite run --commit` builds and commits a pipeline at a time; killed (SIGKILL)
after its first commit, it resumes in a fresh clone with an empty DVC cache, builds only what
is left, and ends where a build in one go ends, byte for byte.

Real git, DVC, processes and an HTTP server on loopback serving the lab's remote: after the
bump, the stages whose code stamps it changed (a few a pipeline) run in one go, and in two steps
split by the kill, the other outputs pulled from the remote, read-only."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from migration_lab import PIPELINES, clone, head, migration_lab, subjects, suite_run, version_of
from suite_repo import SUITE, code_env, locks

from oodrl.testing.pipeline import environment, run

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def lab(tmp_path_factory, repo_root) -> tuple[Path, Path]:
    return migration_lab(tmp_path_factory, repo_root)


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
