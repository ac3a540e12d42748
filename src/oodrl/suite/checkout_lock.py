"""One run per checkout: `oodrl suite run`, `oodrl suite try` and `oodrl new` each hold an
exclusive lock on the checkout while they run, and a second one refuses at once, in one line
naming the running one's pid and command (SPEC §22).

The lock is `fcntl.flock` on `.dvc/tmp/oodrl-run.lock` of the checkout (DVC's own scratch, which
git ignores), or on `.git/oodrl-run.lock` where the checkout has no DVC project at its top. The
kernel releases it when the process ends, however it ends (SIGKILL, a crash, a lost machine), so
a killed run never blocks the next; the file itself stays and means nothing. It holds the pid and
the command of the process that last took the lock, for the refusal to name. The lock's file is
opened non-inheritable (Python's default), so the git, DVC and stage processes a run starts do
not hold it after their parent is gone.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from oodrl.errors import OodrlError

LOCK_NAME = "oodrl-run.lock"

#: The locks this process holds, by path, with how many `with` blocks hold each: a verb that
#: runs another's code in the same process (one `oodrl` process) takes its checkout once.
_HELD: dict[Path, int] = {}
_HELD_LOCK = threading.Lock()


class CheckoutBusy(OodrlError):
    """Another oodrl run holds the checkout."""


def lock_path(root: Path) -> Path | None:
    """The lock file of the checkout holding `root`: in its top's .dvc/tmp, or .git; None where
    `root` is in no git checkout and holds no DVC project (nothing is shared to guard)."""
    root = root.resolve()
    top = next((p for p in [root, *root.parents] if (p / ".git").exists()), None)
    for base in filter(None, (top, root)):
        if (base / ".dvc").is_dir():
            return base / ".dvc" / "tmp" / LOCK_NAME
    if top is not None and (top / ".git").is_dir():
        return top / ".git" / LOCK_NAME
    return None


@contextmanager
def checkout_lock(root: Path, verb: str) -> Iterator[None]:
    """Hold the checkout of `root` for `oodrl VERB` while the block runs; refuse at once with
    CheckoutBusy (exit 1) when another process holds it."""
    path = lock_path(root)
    if path is None:
        yield
        return
    with _HELD_LOCK:
        if _HELD.get(path):
            _HELD[path] += 1
            held_here = True
        else:
            held_here = False
    if held_here:
        try:
            yield
        finally:
            with _HELD_LOCK:
                _HELD[path] -= 1
        return
    import fcntl

    path.parent.mkdir(exist_ok=True)
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CheckoutBusy(
                f"{_checkout(path)}: another oodrl run is using this checkout "
                f"({_holder(descriptor)}); `oodrl {verb}` runs one at a time per checkout: wait "
                f"for it to end, or stop it, or use another clone."
            ) from None
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, f"{os.getpid()}\n{_command()}\n".encode(), 0)
        with _HELD_LOCK:
            _HELD[path] = 1
        try:
            yield
        finally:
            with _HELD_LOCK:
                del _HELD[path]
    finally:
        os.close(descriptor)  # releases the lock


def _checkout(path: Path) -> str:
    return str(path.parent.parent.parent if path.parent.name == "tmp" else path.parent.parent)


def _command() -> str:
    """This process's command line as a user would read it: `oodrl suite run --workers 2`."""
    words = [Path(sys.argv[0]).name if sys.argv else "python", *sys.argv[1:]]
    return " ".join(words).replace("\n", " ")


def _holder(descriptor: int) -> str:
    """`pid N: COMMAND` from the lock file; the holder writes it just after taking the lock, so
    a refusal in that instant may find it empty: a few reads, 50 ms apart."""
    import time

    for _ in range(20):
        text = os.pread(descriptor, 4096, 0).decode(errors="replace")
        pid, _, command = text.partition("\n")
        if pid.strip().isdigit() and command.strip():
            return f"pid {pid.strip()}: {command.strip()}"
        time.sleep(0.05)
    return "its pid not yet written"
