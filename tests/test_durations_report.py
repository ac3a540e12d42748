"""benchmarks/test_durations.py, which CI prints after the tests, on the junit file of a real
pytest run of a tiny project: tests in two modules, one in a class, one failing, one whose time
is all in its fixture's setup and teardown."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from benchmark_scripts import load_benchmark

SLOW = """
import time
import pytest

@pytest.fixture
def slow_fixture():
    time.sleep(0.2)
    yield
    time.sleep(0.2)

def test_in_setup(slow_fixture):
    pass

class TestGroup:
    def test_quick(self):
        pass
"""
QUICK = """
def test_passes():
    pass

def test_fails():
    assert False
"""


def test_report_of_a_real_junit_file(tmp_path: Path, capsys):
    project = tmp_path / "project"
    (project / "tests" / "sub").mkdir(parents=True)
    (project / "pytest.ini").write_text("[pytest]\n")  # its own rootdir, not this repository's
    (project / "tests" / "test_slow.py").write_text(SLOW)
    (project / "tests" / "sub" / "test_quick.py").write_text(QUICK)
    junit = tmp_path / "junit.xml"
    # Its own run only: no CI options, no installed plugins (their imports cost seconds).
    env = {k: v for k, v in os.environ.items() if k != "PYTEST_ADDOPTS"}
    env["PYTEST_DISABLE_PLUGIN_AUTOLOAD"] = "1"
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q",
         f"--junitxml={junit}", "tests"],
        cwd=project, env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 1, done.stdout  # the failing test is reported, not dropped

    script = load_benchmark("test_durations")
    rows = script.durations(junit)
    by_test = {(module, name): seconds for module, name, seconds in rows}
    assert set(by_test) == {
        ("tests/test_slow.py", "test_in_setup"),
        ("tests/test_slow.py", "test_quick"),  # its class is not a module
        ("tests/sub/test_quick.py", "test_passes"),
        ("tests/sub/test_quick.py", "test_fails"),
    }
    # Setup and teardown count: the test's own call does nothing.
    assert by_test[("tests/test_slow.py", "test_in_setup")] >= 0.4

    assert script.main([str(junit), "--top", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "Slowest 2 tests (setup + call + teardown, seconds):"
    assert lines[1].endswith("tests/test_slow.py::test_in_setup")  # the slowest first
    table = lines[lines.index("") + 2 :]
    assert table[0].split()[:2] == ["tests/test_slow.py", "2"]  # the costliest module first
    assert table[1].split()[:2] == ["tests/sub/test_quick.py", "2"]
    assert table[-1].split()[:2] == ["total", "4"]
    assert script.main([str(tmp_path / "missing.xml")]) == 1
