"""Folders a process works in that a kill leaves behind (SIGKILL, a lost Ray node, a crash):
each is named with its process's pid, and the next run removes those whose process is gone.

`oodrl new` stages a pipeline in `pipeline/.NAME.new-<pid>`; `oodrl suite run` works in
`oodrl-suite-<pid>-*` and `oodrl-dvc-config-<pid>-*` in the temporary directory, `oodrl suite
try` in `oodrl-try-<pid>-*` too. Each of the three verbs removes the dead ones of all of them at
its start (`remove_dead_runs`), and a Ray task those on its node.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

#: The temporary folders of a task (its clone), of a run's DVC config and of `oodrl suite try`'s
#: staging clone, in the temporary directory, named with their process's pid.
TASK_FOLDER, DVC_CONFIG_FOLDER, TRY_FOLDER = "oodrl-suite-", "oodrl-dvc-config-", "oodrl-try-"
DEAD_TASK_FOLDER = re.compile(
    rf"(?:{TASK_FOLDER}|{DVC_CONFIG_FOLDER}|{TRY_FOLDER})(?P<pid>[0-9]+)-\w+"
)
#: The staging folder of `pipeline/NAME` while `oodrl new` (process `pid`) makes it.
STAGING_PATTERN = re.compile(r"\.(?P<name>[a-z][a-z0-9_]*)\.new-(?P<pid>[0-9]+)")


def remove_dead_runs(root: Path | None = None) -> None:
    """Remove what runs killed on this machine left: their folders in the temporary directory
    and, with the checkout's `root`, `oodrl new`'s staging folders in its pipeline/. Called where
    this process has none of its own yet (a verb's start, a Ray task's)."""
    remove_dead(Path(tempfile.gettempdir()), DEAD_TASK_FOLDER)
    if root is not None:
        from oodrl.suite.pipeline import ENVIRONMENTS_DIR

        if (root / ENVIRONMENTS_DIR).is_dir():
            remove_dead(root / ENVIRONMENTS_DIR, STAGING_PATTERN)


def working_folder(prefix: str) -> tempfile.TemporaryDirectory:
    """A temporary folder named `<prefix><pid>-*`, removed when the `with` block ends, and by
    `remove_dead` once this process is gone without removing it."""
    return tempfile.TemporaryDirectory(prefix=f"{prefix}{os.getpid()}-")


def remove_dead(parent: Path, pattern: re.Pattern) -> None:
    """Remove the folders in `parent` whose names `pattern` matches (its group `pid`) when that
    process is gone, or is this one (its pid reused). A live process's folder is left to it;
    so is a folder another user owns."""
    for path in parent.iterdir():
        match = pattern.fullmatch(path.name)
        if not match or not path.is_dir() or path.stat().st_uid != os.getuid():
            continue
        pid = int(match["pid"])
        if pid == os.getpid() or not alive(pid):
            shutil.rmtree(path, ignore_errors=True)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)  # signal 0: only whether the process exists
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True
