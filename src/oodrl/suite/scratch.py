"""Folders a process works in that a kill leaves behind (SIGKILL, a lost Ray node, a crash):
each is named with its process's pid, and the next run removes those whose process is gone.

`oodrl new` stages a pipeline in `pipeline/.NAME.new-<pid>`; `oodrl suite run` works in
`oodrl-suite-<pid>-*` and `oodrl-dvc-config-<pid>-*` in the temporary directory.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path


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
