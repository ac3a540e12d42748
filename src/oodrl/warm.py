"""Warm stage processes: a DVC stage's `oodrl` command forks from an interpreter that has already
imported the libraries stages use, instead of importing them anew (SPEC §12).

A stage process spends 0.3 s (the CLI, numpy, zarr) to 2 s (a PyOD detector: scikit-learn, numba,
scipy) importing before it does any work, and a pipeline runs about 300 of them. The console
entry point `main` is therefore a small client when DVC runs it (DVC sets DVC_STAGE): it hands its
argv, working directory, environment, umask, signal dispositions and standard streams (the file
descriptors themselves) to a server over a Unix socket, and exits as the stage exits. The server
forks one session per request; the session forks the stage, which takes the client's state and
runs `oodrl.cli.main`, the same code the client would have run, so its outputs are the same bytes.
A signal the client receives is passed on to the stage; if the client dies, the stage is killed.

The first stage runs in its own process and starts the server in the background. A server
serves one interpreter, one set of module search paths and one environment, the variables that
vary between the stages of a run aside (DVC_*, PER_STAGE_VARIABLES; a stage gets its own values
of every variable); the socket's name is a hash of them. It refuses to serve, and exits, once any
module file it loaded changed on disk (an edit, a reinstall), and exits after IDLE_S seconds
without a request. It never serves from a process with a second thread (fork would copy a lock
some thread holds). OODRL_WARM=0 turns all of this off; so does anything unexpected on the
client's side: it then runs the stage itself.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import socket
import sys
from pathlib import Path

#: Turns warm stages off when "0".
SWITCH_VARIABLE = "OODRL_WARM"
#: A server with no request for this long exits.
IDLE_S = 120.0
#: Imported by the server before it serves: what stage commands import (`import pyod` alone
#: takes 1.4 s: scikit-learn, numba, scipy; torch and the policy loader 2.9 s, in every stage
#: that runs the policy). oodrl.cli first: it pins the library thread pools to one thread before
#: numpy loads (`oodrl.parallel`); so pinned, importing torch starts no thread (unpinned, its
#: numpy's OpenBLAS starts its thread server), and an import that does start one keeps the
#: server from serving (below). A missing one is skipped.
PRELOADED = (
    "oodrl.cli", "oodrl.policies.load", "pyod", "pyod.models.hbos", "pyod.models.knn",
    "pyod.models.iforest", "pyod.models.lof", "pyod.models.ecod", "scipy.stats", "gymnasium",
    "zarr", "oodrl.stages.score", "oodrl.stages.collect", "oodrl.stages.fit",
    "oodrl.stages.metrics", "oodrl.stages.tier_metrics", "oodrl.stages.impact",
    "oodrl.stages.render",
)  # fmt: skip
#: Environment variables that no import reads and that change on the way to a stage (DVC runs
#: it through a shell, which sets or drops its own: a virtual environment's PS1 is exported and
#: dash drops it): a server serves every value of them (the stage gets its own values).
PER_STAGE_VARIABLES = (
    "PWD", "OLDPWD", "SHLVL", "_", "PS1", "PS2", "PS4", "IFS", "OPTIND", "PPID",
    "PYTEST_CURRENT_TEST", SWITCH_VARIABLE,
)  # fmt: skip
_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")


def main() -> None:
    """The `oodrl` console entry point: a warm stage when DVC runs it, else the CLI itself."""
    if _wanted():
        try:
            code = _run_warm()
        except OSError:
            code = None  # no server, or none that took the stage: run it here
        if code is not None:
            _exit_like(code)
    from oodrl.cli import main as cli_main

    cli_main()


def _wanted() -> bool:
    return (
        "DVC_STAGE" in os.environ
        and os.environ.get(SWITCH_VARIABLE, "1") != "0"
        and sys.platform == "linux"
        and hasattr(os, "pidfd_open")
    )


def socket_path(environ: dict[str, str] | None = None) -> Path:
    """Where the server for this interpreter (and its command-line options), search path and
    environment listens."""
    environ = dict(os.environ if environ is None else environ)
    served = {
        key: value
        for key, value in environ.items()
        if not key.startswith("DVC_") and key not in PER_STAGE_VARIABLES
    }
    # sys.path[0] is the script's folder (`oodrl`'s bin folder, or the working folder under
    # `python -m`): a stage gets its client's whole sys.path, so it does not name a server.
    interpreter = os.path.realpath(sys.executable)
    flags = [list(sys.flags), sys.warnoptions, sorted(map(str, sys._xoptions.items()))]
    identity = json.dumps([interpreter, sys.path[1:], flags, sorted(served.items())])
    name = hashlib.sha256(identity.encode()).hexdigest()[:24]
    # Not under TMPDIR: a socket's path must stay short (108 bytes), and a command's TMPDIR is
    # its own to keep clean.
    base = environ.get("XDG_RUNTIME_DIR") or "/tmp"  # noqa: S108 - a private 0700 folder in it
    return Path(base) / f"oodrl-warm-{os.getuid()}" / f"{name}.sock"


def server_pid(socket_file: Path) -> int | None:
    """The pid its lock file names for the server of `socket_file` (None when it names none)."""
    try:
        return int(Path(f"{socket_file}.lock").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def stop_servers(environ: dict[str, str] | None = None) -> int:
    """Stop the warm servers of this user (those under `environ`'s runtime folder); how many."""
    stopped = 0
    for lock in socket_path(environ).parent.glob("*.sock.lock"):
        if (pid := server_pid(lock.with_suffix(""))) is not None:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGTERM)
                stopped += 1
    return stopped


def _default_handler(signum: int):
    """What a fresh interpreter has for `signum`: KeyboardInterrupt for SIGINT, else SIG_DFL."""
    return signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL


# -- the client --------------------------------------------------------------------------------
def _run_warm() -> int | None:
    """The stage's wait status as `os.waitstatus_to_exitcode` gives it (negative: killed by
    that signal), or None when no server could run it (one is started for the next stage)."""

    path = socket_path()
    if not _private(path.parent):
        return None
    pending: list[int] = []
    stage = None

    def relay(signum: int, _frame: object) -> None:
        if stage is None:
            pending.append(signum)  # passed on once the stage runs
        else:
            os.kill(stage, signum)

    connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        connection.connect(str(path))
    except OSError:
        connection.close()
        _start_server(path)
        return None
    with connection:
        dispositions = {
            name: "ignore"
            if signal.getsignal(getattr(signal, name)) == signal.SIG_IGN
            else "default"
            for name in _SIGNALS
        }
        for name, disposition in dispositions.items():
            if disposition == "default":
                signal.signal(getattr(signal, name), relay)
        request = {
            "argv": sys.argv, "path": sys.path, "cwd": os.getcwd(), "environ": dict(os.environ),
            "umask": _umask(), "signals": dispositions,
        }  # fmt: skip
        socket.send_fds(connection, [json.dumps(request).encode() + b"\n"], [0, 1, 2])
        replies = connection.makefile("rb")
        first = json.loads(replies.readline() or b"{}")
        if "pid" not in first:
            if first.get("stale"):
                _start_server(path)
            for name, disposition in dispositions.items():
                if disposition == "default":
                    signum = getattr(signal, name)
                    signal.signal(signum, _default_handler(signum))
            if pending:  # interrupted before any stage began: nothing was written
                return -pending[0]
            return None
        stage = first["pid"]  # from here on, a signal to this process is one to the stage
        for signum in pending:
            os.kill(stage, signum)
        try:
            last = replies.readline()
        except OSError:
            last = b""  # the stage has begun: never run it a second time
    if not last:
        raise SystemExit("error: the warm stage server went away while the stage ran")
    return int(json.loads(last)["status"])


def _private(folder: Path) -> bool:
    """Whether the sockets' folder is this user's alone (or absent: the server makes it so).
    Another user's server would be handed this process's files and its stage."""
    try:
        status = folder.stat()
    except FileNotFoundError:
        return True
    return status.st_uid == os.getuid() and not status.st_mode & 0o077


def _exit_like(code: int) -> None:
    """Exit as the stage did: with its code, or killed by its signal."""

    if code >= 0:
        sys.exit(code)
    signal.signal(-code, signal.SIG_DFL)
    os.kill(os.getpid(), -code)
    sys.exit(128 - code)  # not reached unless the signal is blocked


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _start_server(path: Path) -> None:
    import subprocess

    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    subprocess.Popen(  # noqa: S603 - this interpreter, this module
        [sys.executable, "-m", "oodrl.warm", str(path)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        close_fds=True, start_new_session=True, cwd="/",
    )  # fmt: skip


# -- the server --------------------------------------------------------------------------------
def serve(path: Path) -> None:
    """Listen at `path` until idle or stale; one forked session per request."""
    import fcntl
    import importlib

    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    # Opened without truncating: the file may name the server that holds the lock.
    lock = open(f"{path}.lock", "a")  # noqa: SIM115 - held for the server's life
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return  # another server for this path is starting or serving
    lock.truncate(0)
    lock.write(f"{os.getpid()}\n")  # who serves here (tests stop their servers by it)
    lock.flush()
    for module in PRELOADED:
        # An optional library that is missing: the stages that use it import it themselves.
        with contextlib.suppress(Exception):
            importlib.import_module(module)
    if len(os.listdir("/proc/self/task")) > 1:
        return  # an import started a thread: forking could copy a lock it holds
    loaded = _module_files()
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # sessions are reaped by the kernel
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # stopped: remove the socket
    path.unlink(missing_ok=True)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen(64)
    listener.settimeout(IDLE_S)
    try:
        while True:
            try:
                connection, _ = listener.accept()
            except TimeoutError:
                return
            with connection:
                connection.settimeout(None)
                if _module_files() != loaded:
                    # Give the path up first: the client starts the next server at once.
                    listener.close()
                    _give_up(path, lock)
                    connection.sendall(b'{"stale": true}\n')
                    return
                if os.fork() == 0:
                    listener.close()
                    _session(connection)  # never returns
    finally:
        listener.close()
        if not lock.closed:
            _give_up(path, lock)


def _give_up(path: Path, lock) -> None:
    """Remove the socket and the lock file, then release the lock. (A server that opened the
    lock file before it went may still take the lock: it then serves from a socket nobody
    finds until it idles out, which wastes a process and nothing else.)"""
    path.unlink(missing_ok=True)
    Path(f"{path}.lock").unlink(missing_ok=True)
    lock.close()


def _module_files() -> dict[str, tuple[int, int, int]]:
    """(inode, size, mtime) of every file a loaded module came from."""
    files = {}
    for module in list(sys.modules.values()):
        name = getattr(module, "__file__", None)
        if name:
            try:
                status = os.stat(name)
            except OSError:
                status = None
            files[name] = status and (status.st_ino, status.st_size, status.st_mtime_ns)
    return files


def _session(connection: socket.socket) -> None:
    """Receive one request, fork its stage, report its wait status; kill it if the client dies."""
    import select

    code = 1
    try:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        message, fds, _, _ = socket.recv_fds(connection, 1 << 16, 3)
        while message and not message.endswith(b"\n"):  # a stream: the request may come in parts
            if not (more := connection.recv(1 << 16)):
                break  # the client went away: json.loads fails and the session ends
            message += more
        request = json.loads(message)
        stage = os.fork()
        if stage == 0:
            connection.close()
            _stage(request, fds)  # never returns
        for fd in fds:
            os.close(fd)
        connection.sendall(json.dumps({"pid": stage}).encode() + b"\n")
        watcher = os.pidfd_open(stage)
        ready, _, _ = select.select([watcher, connection], [], [])
        if watcher not in ready:  # the client is gone: so is the stage
            os.kill(stage, signal.SIGKILL)
        _, status = os.waitpid(stage, 0)
        connection.sendall(
            json.dumps({"status": os.waitstatus_to_exitcode(status)}).encode() + b"\n"
        )
        code = 0
    finally:
        os._exit(code)


def _stage(request: dict, fds: list[int]) -> None:
    """Become the client's stage process and run the CLI."""
    import atexit
    import threading

    from oodrl.parallel import THREAD_POOL_VARIABLES

    code = 1
    try:
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
            os.close(fd)
        os.chdir(request["cwd"])
        os.umask(request["umask"])
        os.environ.clear()
        os.environ.update(request["environ"])
        for variable in THREAD_POOL_VARIABLES:  # as importing oodrl.cli sets them
            os.environ.setdefault(variable, "1")
        for name, disposition in request["signals"].items():
            signum = getattr(signal, name)
            handler = signal.SIG_IGN if disposition == "ignore" else _default_handler(signum)
            signal.signal(signum, handler)
        sys.stdin = io.TextIOWrapper(io.FileIO(0, "r", closefd=False), encoding=sys.stdin.encoding)
        sys.stdout = _text_stream(1, "strict")
        sys.stderr = _text_stream(2, "backslashreplace")
        sys.argv = list(request["argv"])
        sys.path[:] = request["path"]
        try:
            from oodrl.cli import main as cli_main

            cli_main()
            code = 0
        except SystemExit as done:
            code = _exit_code(done.code)
        threading._shutdown()  # what interpreter exit does: join threads, then atexit
        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError):
                stream.flush()
    finally:
        os._exit(code)


def _text_stream(fd: int, errors: str) -> io.TextIOWrapper:
    interactive = os.isatty(fd)
    raw = io.FileIO(fd, "w", closefd=False)
    buffered = io.BufferedWriter(raw)
    # As a fresh interpreter has them: stderr line-buffered always, stdout on a terminal only.
    return io.TextIOWrapper(
        buffered, encoding=sys.__stdout__.encoding if sys.__stdout__ else "utf-8",
        errors=errors, line_buffering=interactive or fd == 2,
    )  # fmt: skip


def _exit_code(code: object) -> int:
    """`sys.exit`'s argument as the interpreter turns it into an exit status."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code & 0xFF
    print(code, file=sys.stderr)
    return 1


if __name__ == "__main__":
    serve(Path(sys.argv[1]))
