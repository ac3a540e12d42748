"""SPEC §22's one rule, over every CLI verb: a usage error is one line and exit 2, an error
oodrl did not expect is one line and exit 1 (its traceback only with OODRL_DEBUG=1), a fault of
the machine (a full disk, a refused permission, a read-only filesystem, too many open files) is
one line naming the path and what to do and exit 1, and a signal unwinds with one line and exit
128 + its number."""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import time

import pytest
import typer.main
from hostile_cli import OODRL, assert_one_line_error, oodrl

from oodrl import cli
from oodrl.cli import app
from oodrl.faults import FAULTS


def _verbs(group, prefix=()) -> list[tuple[str, ...]]:
    """Every leaf command of the app, as the words a user types (`pipeline check`)."""
    found = []
    for name, command in sorted(group.commands.items()):
        words = (*prefix, name)
        found += _verbs(command, words) if hasattr(command, "commands") else [words]
    return found


VERBS = _verbs(typer.main.get_command(app))


def test_the_app_has_every_verb_the_spec_names():
    assert {("check-params",), ("monitor",), ("new",), ("suite", "run"), ("fit",)} <= set(VERBS)


@pytest.mark.parametrize("verb", VERBS, ids=" ".join)
def test_an_unknown_option_is_one_line_and_exit_2(verb, tmp_path):
    done = oodrl(*verb, "--no-such-option", cwd=tmp_path)
    assert_one_line_error(done, 2, "--no-such-option", f"oodrl {' '.join(verb)} --help")
    assert list(tmp_path.iterdir()) == []


def test_an_unknown_verb_is_one_line_and_exit_2(tmp_path):
    assert_one_line_error(oodrl("colect-id", cwd=tmp_path), 2, "colect-id")


def test_a_missing_option_value_is_one_line_and_exit_2(tmp_path):
    assert_one_line_error(oodrl("monitor", "--detector", cwd=tmp_path), 2, "--detector")


def test_an_out_of_range_value_is_one_line_and_exit_2(tmp_path):
    assert_one_line_error(
        oodrl("evaluate-policy", "--episodes", "0", cwd=tmp_path), 2, "--episodes"
    )


BOOM = """
import sys
from oodrl import cli
@cli.app.command("boom")
def boom():
    raise RuntimeError("first line\\nsecond line")
sys.argv = ["oodrl", "boom"]
cli.main()
"""


def _boom(debug: bool, tmp_path) -> subprocess.CompletedProcess:
    env = {"OODRL_DEBUG": "1"} if debug else {}
    environment = {k: v for k, v in os.environ.items() if k != "OODRL_DEBUG"} | env
    return subprocess.run([sys.executable, "-c", BOOM], cwd=tmp_path, env=environment,
                          capture_output=True, text=True, check=False)  # fmt: skip


def test_an_unexpected_error_is_one_line_and_exit_1(tmp_path):
    line = assert_one_line_error(_boom(False, tmp_path), 1, "RuntimeError", "OODRL_DEBUG=1")
    assert "first line second line" in line


def test_oodrl_debug_shows_the_traceback(tmp_path):
    done = _boom(True, tmp_path)
    assert done.returncode != 0 and "Traceback" in done.stderr and "RuntimeError" in done.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT], ids=str)
def test_a_signal_is_one_line_and_its_exit_code(sig, tmp_path, repo_root):
    """A long command (6,000 CartPole episodes, about 40 s here) stopped by a signal once it has
    started them. 600 episodes finished inside the 4 s wait on a faster machine: the command must
    outlast the wait by a wide margin, and the test says so if it did not."""
    policy = repo_root / "pipeline/cartpole/models/policy.pt"
    args = ["evaluate-policy", "--env", "CartPole-v1", "--policy", str(policy),
            "--episodes", "6000"]  # fmt: skip
    process = subprocess.Popen(
        [OODRL, *args], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    time.sleep(4)  # past the imports: the episodes are running
    assert process.poll() is None, f"the command ended before the signal: {process.communicate()}"
    process.send_signal(sig)
    stdout, stderr = process.communicate(timeout=60)
    done = subprocess.CompletedProcess(args, process.returncode, stdout, stderr)
    assert_one_line_error(done, 128 + sig.value, f"interrupted ({sig.name})")


# -- faults of the machine (issue 55) -------------------------------------------------------------
def _registered(typer_app) -> list:
    """Every command's registration (its callback), in the app and its groups."""
    found = list(typer_app.registered_commands)
    for group in typer_app.registered_groups:
        found += _registered(group.typer_instance)
    return found


def _required_args(verb: tuple[str, ...]) -> list[str]:
    """A value for each required argument and option of a verb (all take text; the callback
    that would read them is replaced)."""
    command = typer.main.get_command(app)
    for word in verb:
        command = command.commands[word]
    args: list[str] = []
    for param in command.params:
        if not param.required:
            continue
        args += [param.opts[0], "x"] if param.param_type_name == "option" else ["x"]
    return args


#: The faults, one a verb in turn: every verb meets one, every fault several verbs.
MACHINE_FAULTS = sorted(FAULTS)


@pytest.mark.parametrize("verb", VERBS, ids=" ".join)
def test_a_fault_of_the_machine_is_one_line_naming_the_path_and_exit_1(
    verb, tmp_path, monkeypatch, capsys
):
    """Whatever a verb is doing when the disk fills or a write is refused, the OSError that
    reaches the entry point is named with its path and what to do: exit 1, not an internal error
    (SPEC §22). The verb's own function is replaced by one raising that OSError, as a write of
    it would, so that every verb is checked in milliseconds; tests/faults/ meet real ones."""
    number = MACHINE_FAULTS[VERBS.index(verb) % len(MACHINE_FAULTS)]
    path = str(tmp_path / "out" / "store.zarr")

    def failing(function):
        @functools.wraps(function)
        def write(*args, **kwargs):
            raise OSError(number, os.strerror(number), path)

        return write

    for info in _registered(app):
        monkeypatch.setattr(info, "callback", failing(info.callback))
    monkeypatch.setattr(sys, "argv", ["oodrl", *verb, *_required_args(verb)])
    monkeypatch.delenv("OODRL_DEBUG", raising=False)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    hook = sys.unraisablehook
    try:
        with pytest.raises(SystemExit) as ended:
            cli.main()
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        sys.unraisablehook = hook
    out, err = capsys.readouterr()
    assert ended.value.code == 1, err
    assert err == f"error: {path}: {FAULTS[number]}\n", err
    assert "Traceback" not in out + err and not (tmp_path / "out").exists()
