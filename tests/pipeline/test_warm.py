"""Warm stage processes (`oodrl.warm`): a stage forked from a server that preloaded the stage
libraries writes the same bytes as a cold one, exits as it would, takes the client's signals,
dies with its client, and a server whose modules changed on disk serves no more."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import DETECTORS, INJECTORS, detector_stages, python_path

from oodrl.testing.pipeline import edit_params, environment, lock_hashes, repro, run
from oodrl.warm import server_pid

# Loaded by every Python process of the test (PYTHONPATH), the server included: at exit each
# records its argv, whether it ran the CLI (a warm command's client does not) and whether its
# parent is a warm server's session (a process of `python -m oodrl.warm`).
TRACE = """
import atexit, json, os, sys


def _record():
    path = os.path.join(os.environ["OODRL_WARM_TRACE"], f"{os.getpid()}.json")
    with open(path, "w") as out:
        with open(f"/proc/{os.getppid()}/cmdline", "rb") as parent:
            warm = b"oodrl.warm" in parent.read()
        json.dump({"argv": sys.argv[1:], "ran": "oodrl.cli" in sys.modules, "warm": warm}, out)


atexit.register(_record)
"""


@pytest.fixture
def warm_env(tmp_path):
    """An environment whose stage commands get a warm server of their own (stopped after)."""
    trace = tmp_path / "trace"
    trace.mkdir()
    (trace / "sitecustomize.py").write_text(TRACE)
    env = {
        "DVC_STAGE": "test", "OODRL_WARM": "1", "OODRL_WARM_TRACE": str(trace),
        "PYTHONPATH": python_path(trace),
    }  # fmt: skip
    yield env
    if (pid := _server(env)) is not None:
        _stop(pid)


def _socket(env: dict[str, str]) -> Path:
    """The server's socket for the `oodrl` command run under `env` (its interpreter and path)."""
    where = "from oodrl.warm import socket_path; print(socket_path())"
    done = subprocess.run([sys.executable, "-c", where], env=environment(env), capture_output=True,
                          text=True, check=True)  # fmt: skip
    return Path(done.stdout.strip())


def _server(env: dict[str, str]) -> int | None:
    """The pid of the live server for `env`, if one serves."""
    socket_file = _socket(env)
    pid = server_pid(socket_file)
    return pid if pid is not None and _alive(pid) and socket_file.exists() else None


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except OSError:
        return False


def _stop(pid: int) -> None:
    os.kill(pid, signal.SIGTERM)
    _gone(pid)


def _gone(pid: int) -> None:
    deadline = time.monotonic() + 10
    while _alive(pid):
        assert time.monotonic() < deadline, f"process {pid} did not exit"
        time.sleep(0.05)


def _warmed(repo: Path, env: dict[str, str]) -> int:
    """Start the server for `env` (the first command runs cold) and wait until it serves."""
    run(repo, "oodrl", "--version", env=env)
    deadline = time.monotonic() + 120  # preloading scikit-learn, numba, scipy on a loaded machine
    while (pid := _server(env)) is None:
        assert time.monotonic() < deadline, "no warm server came up"
        time.sleep(0.1)
    return pid


def _records(env: dict[str, str], *argv: str) -> list[bool]:
    """Whether each traced process that ran a command whose argv contains `argv` ran warm."""
    records = [json.loads(p.read_text()) for p in Path(env["OODRL_WARM_TRACE"]).glob("*.json")]
    return [r["warm"] for r in records if r["ran"] and all(a in r["argv"] for a in argv)]


def test_a_command_under_dvc_runs_in_the_warm_server(tmp_path, warm_env):
    repo = tmp_path  # --version reads nothing of a pipeline: no copy of it
    first = run(repo, "oodrl", "--version", env=warm_env).stdout
    server = _warmed(repo, warm_env)
    # It serves with torch loaded (the policy's stages fork it ready: 2.9 s each otherwise).
    assert "libtorch_cpu" in Path(f"/proc/{server}/maps").read_text()
    second = run(repo, "oodrl", "--version", env=warm_env)
    assert second.stdout == first and second.stdout.startswith("oodrl ")
    assert second.stderr == ""
    assert sorted(_records(warm_env, "--version")) == [False, False, True]  # cold, cold, warm
    cold = run(repo, "oodrl", "--version", env={**warm_env, "OODRL_WARM": "0"})
    assert cold.stdout == first and sorted(_records(warm_env, "--version")).count(False) == 3


def test_warm_stages_write_the_same_bytes_as_cold_ones(repo, warm_env):
    before = lock_hashes(repo)
    _warmed(repo, warm_env)
    stages = [
        *detector_stages(DETECTORS[0]), f"collect_ood@{INJECTORS[0]}", "tier_metrics", "metrics",
    ]  # fmt: skip
    ran = repro(repo, "-f", "-s", *stages, env=warm_env)
    assert sorted(ran) == sorted(stages)
    assert lock_hashes(repo) == before
    # score_clean, score and score_variants (SPEC §23: a stage per kind of set).
    assert _records(warm_env, "score", DETECTORS[0]) == [True] * 3
    assert _records(warm_env, "metrics") and all(_records(warm_env, "metrics"))


def test_a_warm_error_is_the_same_line_and_exit_code(repo, warm_env):
    _warmed(repo, warm_env)
    command = ["oodrl", "score", "no_such_detector", "--model", "x.pkl", "--eval",
               "data/eval.zarr", "--scores", "x"]  # fmt: skip
    warm = run(repo, *command, check=False, env=warm_env)
    cold = run(repo, *command, check=False, env={**warm_env, "OODRL_WARM": "0"})
    outcome = [(d.returncode, d.stdout, d.stderr) for d in (warm, cold)]
    assert outcome[0] == outcome[1]
    assert warm.returncode == 2 and warm.stderr.count("\n") == 1
    assert _records(warm_env, "no_such_detector") in ([True, False], [False, True])


def _collecting(repo: Path, env: dict[str, str]) -> tuple[subprocess.Popen, Path]:
    """`oodrl collect-id` on a set large enough to be caught while it writes its store."""
    edit_params(repo, lambda p: p["data"].update(n_id=400))
    store = repo / "data" / "id.zarr"
    store.unlink()  # as DVC does before it runs a stage
    process = subprocess.Popen(
        ["oodrl", "collect-id", "--policy", "models/policy.pt", "--out", "data/id.zarr"],
        cwd=repo, env=environment(env), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while not list(store.parent.glob(".id.zarr.tmp-*")):
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the stage never began its store"
        time.sleep(0.01)
    return process, store


def test_a_signal_to_the_client_interrupts_the_warm_stage(repo, warm_env):
    _warmed(repo, warm_env)
    process, store = _collecting(repo, warm_env)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 128 + signal.SIGTERM
    assert stderr == "error: interrupted (SIGTERM)\n"
    assert not store.exists() and not list(store.parent.glob(".id.zarr.tmp-*"))
    assert _records(warm_env, "collect-id") == [True]


def _stages_of(server: int) -> list[int]:
    """The stage processes the server's sessions run (the server's grandchildren)."""

    def children(pid: int) -> list[int]:
        try:
            return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
        except OSError:
            return []

    return [stage for session in children(server) for stage in children(session)]


def test_a_killed_client_takes_its_warm_stage_with_it(repo, warm_env):
    server = _warmed(repo, warm_env)
    process, store = _collecting(repo, warm_env)
    assert len(_stages_of(server)) == 1
    process.send_signal(signal.SIGKILL)
    process.wait()
    deadline = time.monotonic() + 10
    while _stages_of(server):
        assert time.monotonic() < deadline, "the stage outlived its client"
        time.sleep(0.05)
    assert not store.exists()


def test_a_server_whose_modules_changed_serves_no_more(tmp_path, warm_env):
    repo = tmp_path  # --version reads nothing of a pipeline: no copy of it
    server = _warmed(repo, warm_env)
    sitecustomize = Path(warm_env["OODRL_WARM_TRACE"]) / "sitecustomize.py"
    sitecustomize.write_text(sitecustomize.read_text() + "\n# changed\n")
    done = run(repo, "oodrl", "--version", env=warm_env)
    assert done.stdout.startswith("oodrl ") and done.stderr == ""
    assert sorted(_records(warm_env, "--version")) == [False, False]  # both cold
    _gone(server)  # it exits when it finds its modules changed
    assert _warmed(repo, warm_env) != server
