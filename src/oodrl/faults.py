"""Faults of the machine named as faults (SPEC §22): an `OSError` of a full disk, a refused
permission, a read-only filesystem or too many open files is no bug of oodrl, and its one line
says so, names the path and what to do about it.

`oodrl.cli.main` asks `machine_fault` about every exception a command lets out; `oodrl suite
run` asks `fault_in_output` about the output of a git, DVC or stage process that failed.
Imports nothing but the standard library: the entry point reaches it on every error.
"""

from __future__ import annotations

import errno
import os
import re

_NO_SPACE = "no space left; free space on that filesystem (`df -h` shows it), then run again"
_QUOTA = "disk quota exceeded; free space within the quota or raise it, then run again"
_PERMISSION = ("permission denied; check the permissions of that path and of the folders above "
               "it (`ls -ld`), or run as a user who may write there")  # fmt: skip
_READ_ONLY = ("read-only filesystem; run where the outputs can be written, or remount it "
              "read-write")  # fmt: skip
_OPEN_FILES = ("too many open files; raise the limit (`ulimit -n 65536` in the shell that runs "
               "oodrl) or run fewer workers")  # fmt: skip

#: errno → what it means and what to do, for the faults of the machine a lab meets.
FAULTS: dict[int, str] = {
    errno.ENOSPC: _NO_SPACE,
    errno.EDQUOT: _QUOTA,
    errno.EACCES: _PERMISSION,
    errno.EPERM: (
        "operation not permitted; check the owner and permissions of that path (`ls -ld`)"
    ),  # fmt: skip
    errno.EROFS: _READ_ONLY,
    errno.EMFILE: _OPEN_FILES,
    errno.ENFILE: (
        "the system's table of open files is full; close programs holding many "
        "files or raise fs.file-max, then run again"
    ),  # fmt: skip
}


def machine_fault(error: BaseException) -> str | None:
    """The one line (without `error: `) for an exception caused by a fault of the machine: the
    first `OSError` with one of `FAULTS`' errnos among it and its causes; None for any other
    exception (a bug: the caller says so)."""
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno in FAULTS:
            path = current.filename
            if path is None:  # a write() names no file: the one the code was writing
                path = _path_being_written(current)
            return fault_line(current.errno, path, current.filename2)
        current = current.__cause__ or current.__context__
    return None


#: The names a function's path or open file goes by, in the code that fails a write without
#: naming the file (`f.write(data)`: Python's OSError then has no filename).
_PATH_NAMES = ("path", "filename", "file", "tmp_path", "tmp", "dst", "dest", "target", "f", "fh")


def _path_being_written(error: BaseException) -> str | None:
    """The path in the innermost frame of `error`'s traceback that holds one under a usual name
    (a path, or an open file's name), or None."""
    frames = []
    traceback = error.__traceback__
    while traceback is not None:
        frames.append(traceback.tb_frame)
        traceback = traceback.tb_next
    for frame in reversed(frames):
        for name in _PATH_NAMES:
            value = frame.f_locals.get(name)
            value = getattr(value, "name", value) if hasattr(value, "write") else value
            if isinstance(value, str | os.PathLike) and str(value) and not str(value).isdigit():
                return os.fspath(value)
    return None


def fault_line(number: int, path: object = None, path2: object = None) -> str:
    """`PATH: what it is; what to do` (the path where the error names one)."""
    where = ", ".join(os.fsdecode(p) if isinstance(p, bytes) else str(p)
                      for p in (path, path2) if p not in (None, ""))  # fmt: skip
    return f"{where}: {FAULTS[number]}" if where else FAULTS[number]


#: How Python (and DVC, which prints Python's words) writes an OSError: `[Errno 28] No space left
#: on device: '/data/x'`, the path quoted where there is one.
_ERRNO = re.compile(
    r"\[Errno (?P<number>\d+)\][^:'\"\n]*(?::\s*(?P<quote>['\"])(?P<path>.+?)(?P=quote))?"
)
#: The C library's words for the faults, as a tool that is not Python prints them (git: `fatal:
#: could not write 'x': No space left on device`).
_WORDS = {os.strerror(number): number for number in FAULTS}


def fault_in_output(text: str, where: str | None = None) -> str | None:
    """The one line for the first machine fault another process reported in `text`, or None.
    `where`: the path to name when the process named none (what it was writing, or where it
    ran: a path on the filesystem at fault)."""
    for match in _ERRNO.finditer(text):
        number = int(match["number"])
        if number in FAULTS:
            return fault_line(number, match["path"] or where)
    for line in text.splitlines():
        for words, number in _WORDS.items():
            if words in line:
                quoted = re.search(r"['\"]([^'\"]+)['\"]", line)
                return fault_line(number, quoted[1] if quoted else where)
    return None
