"""Repositories of the suite's shape at their smallest, for the `oodrl suite run` tests: git and
DVC run as a user runs them, and DVC projects written as `dvc init --subdir` and `oodrl pipeline
write` leave them (one-line stages, so building one takes about a second)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from oodrl.metrics.stamp import PROTOCOL_VERSION

DVC_GITIGNORE = "/config.local\n/tmp\n/cache\n"
#: What a tiny stage appends to the reports/results.yaml it wrote: the top-level stamp line of
#: this code's protocol (oodrl.metrics.stamp), so that a built project reads as current
#: (oodrl.suite.migration.project_states), not as pending at the unstamped protocol 1.
STAMP = f"echo protocol_version: {PROTOCOL_VERSION} >> reports/results.yaml"


def git(repo: Path, *args: str) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@localhost",
           "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@localhost"}  # fmt: skip
    done = subprocess.run(["git", *args], cwd=repo, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return done.stdout


def dvc(repo: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "dvc", *args]
    done = subprocess.run(command, cwd=repo, capture_output=True, text=True)
    assert done.returncode == 0 or not check, done.stderr
    return done


def dvc_project(directory: Path, cache: str | None, stages: str) -> None:
    """A DVC project (what `dvc init --subdir` and `oodrl pipeline write` leave) with `stages`."""
    (directory / ".dvc").mkdir(parents=True)
    cache_section = f"[cache]\n    dir = {cache}\n" if cache else ""
    (directory / ".dvc" / "config").write_text(f"[core]\n    analytics = false\n{cache_section}")
    (directory / ".dvc" / ".gitignore").write_text(DVC_GITIGNORE)
    (directory / "dvc.yaml").write_text(f"stages:\n{stages}")


def one_pipeline_suite(repo: Path, command: str, *, stamped: bool = False) -> Path:
    """The root and pipeline/a, each a stage running `command` that writes
    reports/results.yaml, and the leaderboard reading a's, committed. `stamped`: the stages
    then append the STAMP line, so that a built project is current to `oodrl suite run`;
    unstamped, its results read as protocol 1, pending, and every run builds it again."""
    cmd = json.dumps(f"{command} && {STAMP}" if stamped else command)  # a YAML scalar
    build = f"  build:\n    cmd: {cmd}\n    outs:\n      - reports/results.yaml\n"
    dvc_project(repo, None, build)
    dvc_project(repo / "pipeline" / "a", "../../../.dvc/cache", build)
    leaderboard = ("  leaderboard:\n    cmd: cat ../a/reports/results.yaml > leaderboard.txt\n"
                   "    deps:\n      - ../a/reports/results.yaml\n"
                   "    outs:\n      - leaderboard.txt\n")  # fmt: skip
    dvc_project(repo / "pipeline" / "suite", "../../../.dvc/cache", leaderboard)
    git(repo, "init", "-q")
    git(repo, "add", "-A")
    git(repo, "commit", "-q", "-m", "a tiny suite")
    return repo


def assert_checking_line_then_the_error(output: str) -> None:
    """What a refused `oodrl suite run` prints: the line saying what it checks first, then its
    one error line (SPEC §22)."""
    lines = output.splitlines()
    assert len(lines) == 2 and lines[0].startswith("suite: ") and lines[1].startswith("error: "), (
        output
    )
