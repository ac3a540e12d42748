"""What every hostile-input case checks (SPEC §22): the exit code, one line on stderr that
starts with `error:`, no traceback, and nothing written or lost in the files it could touch."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

OODRL = str(Path(sys.executable).with_name("oodrl"))


def oodrl(*args: str, cwd: Path, env: dict[str, str] | None = None, timeout: float = 300):
    """The installed console script, as a user runs it (its entry point is the rule's owner)."""
    environment = {k: v for k, v in os.environ.items() if k != "OODRL_DEBUG"} | (env or {})
    return subprocess.run(
        [OODRL, *args], cwd=cwd, env=environment, capture_output=True, text=True,
        timeout=timeout, check=False,
    )  # fmt: skip


def assert_one_line_error(done: subprocess.CompletedProcess, code: int, *needles: str) -> str:
    """The error line, after checking the rule; `needles` must all appear in it."""
    lines = done.stderr.splitlines()
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1 and lines[-1] == errors[0], done.stderr
    assert done.returncode == code, (done.returncode, done.stderr)
    for needle in needles:
        assert needle in errors[0], (needle, errors[0])
    return errors[0]


def snapshot(directory: Path) -> dict[str, str]:
    """sha256 of every file under `directory` (hidden ones included): what a case may not touch."""
    return {
        path.relative_to(directory).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(directory.rglob("*"))
        if path.is_file() and not {".git", "__pycache__"} & set(path.relative_to(directory).parts)
    }
