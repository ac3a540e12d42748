"""Shared fixtures: the repository root, the default params as a dict, small clean sets, a
read-only HTTP server."""

from __future__ import annotations

import copy
import functools
import http.server
import os
import signal
import threading
from pathlib import Path

import pytest
import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]


def pytest_configure(config):
    """Children get the signal dispositions a terminal gives a command. Run under `nohup`, or as
    a background job of a script, pytest inherits SIGHUP or SIGINT ignored, its children would
    too, and oodrl rightly keeps an ignored signal ignored: every test sending one would fail. A
    handler (not an ignore) is reset to the default by exec, so the tests stay immune to a
    hangup while the commands they start are not."""
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(signum) is signal.SIG_IGN:
            signal.signal(signum, lambda number, frame: None)


#: Set in what each pytest-xdist worker is given when tests/scheduling.py deals the tests.
BY_MODULE = "oodrl_by_module"


def _by_module(config: pytest.Config) -> bool:
    """`-n N` without `--dist` other than load: the tests are dealt by tests/scheduling.py."""
    return config.getoption("dist", "no") == "load"


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    if not _by_module(config):
        return None
    from scheduling import module_scheduling

    return module_scheduling(config, log)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    node.workerinput[BY_MODULE] = _by_module(node.config)


def pytest_collection_modifyitems(config, items):
    """A worker collects the costliest modules first when tests/scheduling.py deals them (every
    worker collects, and all must list the tests in the same order)."""
    if getattr(config, "workerinput", {}).get(BY_MODULE):
        from scheduling import costliest_first

        costliest_first(items)


@pytest.fixture(scope="session", autouse=True)
def _sb3_logs_in_pytests_own_folder(tmp_path_factory):
    """Stable-Baselines3 makes an empty folder in the system's temporary directory for every
    model it trains quietly (SB3-<date>, its logger's default); the tests train dozens. Their
    commands inherit this, so the folders land under pytest's own temporary directory."""
    os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3-logs"))


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def _default_params() -> dict:
    return yaml.safe_load((REPO_ROOT / "params.yaml").read_text())


@pytest.fixture
def default_params(_default_params) -> dict:
    """A fresh deep copy of params.yaml that a test may edit."""
    return copy.deepcopy(_default_params)


@pytest.fixture(scope="session")
def built_repo(tmp_path_factory, repo_root, _default_params) -> Path:
    """The tests' tiny pipeline (tests/tiny_pipeline.py), built once a session; tests read it or
    copy it, never change it. `<it>/../import-trace` holds each process's imports."""
    from tiny_pipeline import build

    if not (repo_root / "models" / "policy.pt").is_file():
        pytest.skip("models/policy.pt is not committed yet")
    return build(repo_root, tmp_path_factory.mktemp("built"), _default_params)


@pytest.fixture(scope="session")
def serial_locks(tmp_path_factory, repo_root) -> dict[str, bytes]:
    """The locks a serial build of the two-environment suite writes: the build a test run makes
    once (tests/suite_repo.py serial_built_suite; test_suite_try, test_remote and the migration
    lab copy it too), which `oodrl suite run` must leave byte for byte."""
    from suite_repo import head_commit, locks, run_folder, serial_built_suite

    built, _ = serial_built_suite(repo_root, head_commit(repo_root), run_folder(tmp_path_factory))
    return locks(built)


@pytest.fixture
def fresh_suite(repo_root, tmp_path) -> Path:
    """The two-environment suite (tests/suite_repo.py), committed and not built, in a copy of
    its own."""
    from suite_repo import head_commit, two_environment_suite

    return two_environment_suite(repo_root, head_commit(repo_root), tmp_path / "repo")


@pytest.fixture(scope="session")
def heuristic_clean():
    """Eight clean LunarLander streams of T=300 from gymnasium's heuristic controller."""
    from rollout_policies import HeuristicPolicy

    from oodrl.envs.collect import collect
    from oodrl.envs.lunar_lander import LunarLanderAdapter

    return collect(LunarLanderAdapter(), HeuristicPolicy(), range(100, 108), 300)


@pytest.fixture
def serve():
    """Serve a directory read-only over HTTP on a free loopback port, from a thread: its URL."""
    servers = []

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    def start(directory: Path) -> str:
        handler = functools.partial(Quiet, directory=str(directory))
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return f"http://127.0.0.1:{server.server_address[1]}/"

    yield start
    for server in servers:
        server.shutdown()
        server.server_close()
