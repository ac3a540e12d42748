"""`oodrl suite try` against hostile inputs (SPEC §22): parameters that are not KEY=VALUE, a
name that cannot be a params key or a directory, no suite at --root, no workers, and a run
ended by SIGTERM while the pipelines build. Each is one line, and the checkout is as it was."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from hostile_cli import OODRL, assert_one_line_error, oodrl
from suite_repo import head_commit, two_environment_suite


@pytest.fixture(scope="module")
def suite(repo_root, tmp_path_factory) -> Path:
    """The tiny suite (CartPole and the leaderboard), not built."""
    dest = tmp_path_factory.mktemp("try") / "repo"
    return two_environment_suite(repo_root, head_commit(repo_root), dest)


def _checkout(repo: Path) -> dict[str, bytes]:
    """Every file outside git's and DVC's own directories (a task may add cache objects)."""
    return {
        path.relative_to(repo).as_posix(): path.read_bytes()
        for path in sorted(repo.rglob("*"))
        if path.is_file() and not {".git", ".dvc"} & set(path.relative_to(repo).parts)
    }


HBOS = ("--class", "pyod.models.hbos:HBOS")


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["hbos", *HBOS, "n_bins"], ["'n_bins': a detector parameter is KEY=VALUE"]),
        (["hbos", *HBOS, "n_bins=1", "n_bins=2"], ["n_bins: given twice"]),
        (["hbos", *HBOS, "class=x:Y"], ["name the class with --class"]),
        (["hbos", *HBOS, "--features", "state", "features=action"], ["given both"]),
        (["hbos", *HBOS, "tol=[1,"], ["the value is not YAML"]),
        (["../hbos", *HBOS], ["NAME '../hbos': letters, digits and underscores"]),
        (["hbos", *HBOS, "--workers", "0"], ["--workers must be >= 1. Got 0 instead."]),
    ],
    ids=["no-equals", "twice", "class", "features-twice", "not-yaml", "name", "workers"],
)
def test_a_refused_argument_is_one_line_and_changes_nothing(suite, args, needles):
    before = _checkout(suite)
    done = oodrl("suite", "try", *args, "--root", str(suite), cwd=suite)
    assert_one_line_error(done, 2, *needles)
    assert done.stdout == ""  # refused before the contract check began
    assert _checkout(suite) == before


def test_a_root_that_is_no_suite_is_one_line(tmp_path):
    done = oodrl("suite", "try", "hbos", *HBOS, "--root", str(tmp_path), cwd=tmp_path)
    assert_one_line_error(done, 2, "not an oodrl suite")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_sigterm_while_the_pipelines_build_leaves_the_checkout_as_it_was(suite):
    """Stopped once its task builds CartPole (here from scratch): no params, DVC file, lock or
    result reaches the checkout, which changes only once every pipeline has been built."""
    before = _checkout(suite)
    args = ["suite", "try", "hbos", *HBOS, "--features", "state"]
    environment = {k: v for k, v in os.environ.items() if k != "OODRL_DEBUG"}
    process = subprocess.Popen([OODRL, *args], cwd=suite, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=environment)  # fmt: skip
    printed = []
    for line in process.stdout:  # click flushes every line
        printed.append(line)
        if line.startswith("started"):
            break
    assert printed and printed[-1].startswith("started"), (printed, process.stderr.read())
    time.sleep(3)  # the task's clone is building
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=120)
    done = subprocess.CompletedProcess(args, process.returncode, "".join(printed) + stdout, stderr)
    assert_one_line_error(done, 128 + signal.SIGTERM, "interrupted (SIGTERM)")
    assert _checkout(suite) == before
    status = subprocess.run(["git", "status", "--porcelain"], cwd=suite, capture_output=True,
                            text=True, check=True)  # fmt: skip
    assert status.stdout == ""
