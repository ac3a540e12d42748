"""`oodrl suite run` (SPEC §16, §26): every pipeline of the suite that is not current, in
parallel, then the leaderboard once every pipeline is current.

Which pipelines are current is decided from git alone (`oodrl.suite.migration.project_states`:
the committed locks against this commit's code stamps and params, the results' protocol stamps),
not from `dvc status`, which reads outputs: a fresh clone with an empty cache has none, and a
current pipeline is skipped without restoring or recomputing anything (`dvc pull` restores it
when wanted). A pending pipeline (results of an older protocol) is built; so is a stale one
(any other mismatch, e.g. a knob committed without its relock), except with `--commit`, which
builds a migration's pending pipelines and nothing else. With `--commit` the head commits each
pipeline's locks and results as soon as it has restored them, one commit a pipeline, and the
leaderboard once every pipeline is current: a run stopped at any point resumes in any clone,
having lost only the pipelines in progress.

Each pipeline is a DVC project of its own (the root, `pipeline/<env>/`), all keeping outputs and
run-cache in the root's cache. DVC refuses two `dvc repro` in one workspace, so each pipeline is
built by a task in its own clone of the head's commit. What a task computed reaches the head in
two parts: the task returns its project's dvc.lock files and the outputs DVC does not cache, and
the cache (shared, or the remote) holds every other output, which the head checks out (outputs
are byte-identical on any machine, SPEC §14). The head does so for each project as soon as its
task is done, while the other tasks run, and after the last one runs the leaderboard: the
checkout ends with the dvc.lock files a serial run writes. The tasks also push DVC's run-cache,
so that any machine's `dvc repro` restores their stages instead of running them.

Three ways to share, chosen by what is configured:
- a DVC remote (the root project's default remote, at any config level): each task pulls,
  runs `dvc repro --pull` and `dvc push --run-cache`; the head pulls. The remote reaches every
  project and every node through a DVC *system*-level config file in a temporary directory
  (DVC_SYSTEM_CONFIG_DIR), so no file of the checkout or of its projects is edited. On Ray this
  is the only way (the nodes share nothing else).
- none, with local workers: the clones use the head's cache directory itself (each clone's
  git-ignored .dvc/config.local), so one machine needs no remote and nothing is copied twice.
- a read-only remote (an HTTP(S) URL, which DVC reads but a static server cannot write, or one
  that refuses the probe write): the clones pull from it into the head's cache and push nothing;
  what it lacks is built locally. On Ray it is refused (the nodes would share nothing). One
  that refuses every object the pipelines to build need (HTTP 401, 403), or holds none of
  them, is named before any task starts and the run stops there, unless `--build-missing`
  asks to build everything here (`oodrl.suite.remote_check.unserved`): DVC reads a refusal as
  a missing object, and the whole suite would be rebuilt from scratch in silence.

With a remote a task first pulls what the remote has (`dvc pull --allow-missing`), then runs
`dvc repro --pull`. Not `dvc repro --pull --allow-missing`, DVC's own "fetch what is unchanged,
run what changed": it skips, without pulling, a stage whose outputs are missing but otherwise
current, and forgives a missing dep only when its path is absent, so a stage that must run
after a skipped one would read inputs never pulled. One `dvc pull` is also faster than
DVC's pull per stage. `dvc pull --allow-missing` passes over a remote that does not answer, so
a remote is checked before any task starts (`_check_remote`). Without a remote a task first
checks out what the shared cache has (`dvc checkout --allow-missing`), for the same reason:
`dvc repro` restores a current stage whose outputs a fresh clone lacks one stage at a time,
rewriting dvc.lock after each, and `oodrl suite try`'s results stages sit below every
detector's stages (docs/performance.md, "`oodrl suite try` at protocol 5").
"""

from __future__ import annotations

import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import closing, contextmanager, suppress
from dataclasses import dataclass, replace
from pathlib import Path

from oodrl.errors import ConfigError, OodrlError
from oodrl.suite.pipeline import suite_pipelines
from oodrl.suite.scratch import (
    DEAD_TASK_FOLDER,
    DVC_CONFIG_FOLDER,
    TASK_FOLDER,
    remove_dead,
    remove_dead_runs,
    working_folder,
)

#: A task whose node dies runs again on another node up to this many times.
RAY_MAX_RETRIES = 3
#: Seconds a Ray head has to answer the handshake of `_check_reachable`.
RAY_HANDSHAKE_S = 10
#: Seconds an HTTP remote has to answer (`_check_answers`).
REMOTE_ANSWER_S = 10
#: Seconds an interrupted git or DVC process has to stop on its own (Ctrl-C) before it is killed.
STOP_GRACE_S = 10


#: A task's clone and a run's DVC config live in temporary folders named with their process's
#: pid (`oodrl.suite.scratch`: TASK_FOLDER, DVC_CONFIG_FOLDER): a run killed (SIGKILL, a crash)
#: or a task killed with its node leaves them, and the next run or task on that machine removes
#: them, whichever verb it is.
def remove_dead_task_folders() -> None:
    """Remove the temporary folders killed runs left on this machine. Called where this process
    has none of its own yet (a run's start, a Ray task's start, `oodrl new`'s): local tasks are
    threads of one process, and `remove_dead` takes a folder of this process's pid for a reused
    pid's."""
    remove_dead(Path(tempfile.gettempdir()), DEAD_TASK_FOLDER)


#: A project's provenance and stage times, written by its render stage when it runs; git ignores
#: it. A task brings it back with the locks, so the head's `_longest_first` knows each
#: pipeline's last build.
RUN_META = Path("reports") / "run_meta.yaml"


class SuiteRunError(OodrlError):
    """A pipeline's task, the DVC remote or the Ray cluster failed; the checkout is untouched."""


@dataclass(frozen=True)
class PipelineRun:
    """One pipeline built by one task: how long, where, and which stages ran (not restored);
    then how long the head took to restore it into the checkout."""

    pipeline: str
    seconds: float
    node: str
    ran: tuple[str, ...]
    files: dict[str, bytes]
    restore_seconds: float = 0.0


@dataclass(frozen=True)
class SuiteRun:
    """The tasks; what the head ran (restoring the projects, the leaderboard); how long it all
    took, how long the head went on after the last task, and the leaderboard project's time."""

    pipelines: tuple[PipelineRun, ...]
    head_ran: tuple[str, ...]
    seconds: float
    head_seconds: float = 0.0
    leaderboard_seconds: float = 0.0


@dataclass(frozen=True)
class Remote:
    """The DVC remote every project and node uses: its name and options (paths resolved)."""

    name: str
    options: dict[str, str]
    writable: bool = True


# -- one task: one pipeline in its own clone ----------------------------------------------------
def build_pipeline(
    bundle: bytes,
    commit: str,
    pipeline: str,
    remote: Remote | None,
    shared_cache: str | None,
    targets: Mapping[str, Sequence[str]] | None = None,
) -> tuple[float, tuple[str, ...], dict[str, bytes]]:
    """Clone `commit` from a git bundle, `dvc repro` the pipeline's project there (pulling what
    the remote has), push its outputs and run-cache to a writable remote; the seconds taken, the
    stages that ran and the `checkout_files` of the built project. With `targets`, only the
    stages `targets[pipeline]` names and what they depend on (`oodrl suite try`): DVC restores
    an upstream stage whose lock is current from the cache, and builds one that is missing.

    The clone is a temporary directory that goes with the task. A task killed with its node
    leaves nothing in the head's checkout; the remote and the cache receive whole objects only
    (written aside, then renamed) and a run-cache entry only once its stage has finished."""
    start = time.perf_counter()
    with working_folder(TASK_FOLDER) as scratch, _dvc_config(remote) as env:
        clone = Path(scratch) / "repo"
        (Path(scratch) / "head.bundle").write_bytes(bundle)
        _run(Path(scratch), env, "git", "clone", "-q", "--no-checkout", "head.bundle", "repo")
        _run(clone, env, "git", "-c", "advice.detachedHead=false", "checkout", "-q", commit)
        project = clone / pipeline
        if shared_cache:
            _run(project, env, "dvc", "cache", "dir", "--local", shared_cache)
        restore_outputs(project, env, remote)
        chosen = tuple(targets[pipeline]) if targets is not None else ()
        done = _from_remote(project, env, remote, "repro", *(["--pull"] if remote else []),
                            *chosen)  # fmt: skip
        if remote and remote.writable:
            _push(project, env)
        files = checkout_files(project)
    return time.perf_counter() - start, ran_stages(done.stdout), files


def restore_outputs(project: Path, env: dict[str, str], remote: Remote | None) -> None:
    """Put in a fresh clone's project, in one go, what the remote has of its outputs, or without
    a remote what the cache has, before `dvc repro` (why: the module's docstring)."""
    if remote:
        _from_remote(project, env, remote, "pull", "--allow-missing", "-q", check=True)
    else:
        _run(project, env, "dvc", "checkout", "--allow-missing", "-q")


def _from_remote(
    project: Path, env: dict[str, str], remote: Remote | None, *args: str, check: bool = False
) -> subprocess.CompletedProcess:
    """A DVC command that may fetch from the remote; where it fails (or always, with `check`:
    `dvc pull --allow-missing` passes over an object that arrived corrupt in silence), an object
    the remote failed to deliver intact is named instead (`oodrl.suite.remote_check`)."""
    from oodrl.suite.remote_check import bad_object

    def named() -> str | None:
        environment = {**task_environment(Path(_git_root(project))), **env}
        return bad_object(project, environment, remote, _spawn)

    try:
        done = _run(project, env, "dvc", *args)
    except SuiteRunError:
        if remote is not None and not _STOPPING.is_set() and (bad := named()):
            raise SuiteRunError(bad) from None
        raise
    if remote is not None and check and (bad := named()):
        raise SuiteRunError(bad)
    return done


def checkout_files(project: Path) -> dict[str, bytes]:
    """What a built project holds beyond the cache, by path relative to it: the dvc.lock of each
    of its DVC files, every output DVC does not cache (metrics.json, the policy) and the
    .gitignore beside each output (`dvc repro` adds a cached output's entry, `dvc checkout` does
    not: a new stage's output would show as untracked). With these written, `dvc checkout`
    makes another checkout of the commit the built project. When the task ran render, also its
    `RUN_META` (the stage times of what this build ran)."""
    from dvc.repo import Repo

    with Repo(str(project)) as repo:
        stages = repo.index.stages
        outs = [(Path(out.fs_path), out.use_cache) for stage in stages for out in stage.outs]
        paths = {Path(stage.dvcfile.path).with_suffix(".lock") for stage in stages}
        uncached = [path for path, cached in outs if not cached]
        # An uncached directory output (a pipeline's reports/tiers) travels file by file.
        paths |= {f for path in uncached for f in ([path] if path.is_file() else path.rglob("*"))}
        paths = {path for path in paths if path.is_file()}
        paths |= {ignore for path, _ in outs if (ignore := path.parent / ".gitignore").is_file()}
    if (project / RUN_META).is_file():
        paths.add(project / RUN_META)
    return {path.relative_to(project).as_posix(): path.read_bytes() for path in sorted(paths)}


#: `dvc push --run-cache`, plus what it leaves behind: the outputs of each run-cache entry that
#: the workspace push skips (`cache: false` ones, such as metrics.json), without which another
#: machine's `dvc repro` could not restore those stages. Runs in the task's clone, on the DVC the
#: node has installed.
PUSH_RUN_CACHE = """
from dvc.repo import Repo

with Repo(".") as repo:
    entries = repo.stage_cache.push(None)
    for objects in repo.stage_cache.get_used_objs(entries).values():
        repo.cloud.push(objects)
"""


def _push(project: Path, env: dict[str, str]) -> None:
    """Push a built project's outputs and run-cache (`PUSH_RUN_CACHE`)."""
    _run(project, env, "dvc", "push", "-q")
    _run(project, env, sys.executable, "-c", PUSH_RUN_CACHE)


def ran_stages(dvc_output: str) -> tuple[str, ...]:
    """The stages whose command ran, from `dvc repro`'s output (restored ones say 'cached')."""
    return tuple(sorted(re.findall(r"^Running stage '([^']+)'", dvc_output, re.MULTILINE)))


def task_environment(repo: Path) -> dict[str, str]:
    """What stage commands run with: the repository's own code first (the commit being built,
    whatever oodrl the node has installed), one thread per library pool (why: `oodrl.parallel`),
    and the running interpreter's `oodrl` and `dvc` first on PATH."""
    from oodrl.parallel import THREAD_POOL_VARIABLES

    env = {**os.environ, **dict.fromkeys(THREAD_POOL_VARIABLES, "1"), "DVC_NO_ANALYTICS": "1"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(repo / "src"), env.get("PYTHONPATH")]))
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


@contextmanager
def _dvc_config(remote: Remote | None) -> Iterator[dict[str, str]]:
    """Environment additions making `remote` every DVC project's default remote: a system-level
    DVC config in a temporary directory (the machine's own system config copied in first)."""
    if remote is None:
        yield {}
        return
    from configobj import ConfigObj
    from dvc.dirs import system_config_dir

    with working_folder(DVC_CONFIG_FOLDER) as directory:
        config = ConfigObj(os.path.join(system_config_dir(), "config"))
        config.filename = os.path.join(directory, "config")
        config.setdefault("core", {})["remote"] = remote.name
        # verify: DVC hashes every object it fetches and keeps none whose hash is not its name
        # (it trusts an HTTP remote's bytes otherwise: oodrl.suite.remote_check).
        config[f'remote "{remote.name}"'] = {**remote.options, "verify": "true"}
        config.write()
        yield {"DVC_SYSTEM_CONFIG_DIR": directory}


def _run(cwd: Path, env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    """One git or DVC command; a failure is a SuiteRunError carrying DVC's own error line."""
    command = [sys.executable, "-m", "dvc", *args[1:]] if args[0] == "dvc" else list(args)
    repo = Path(_git_root(cwd))
    done = _spawn(command, cwd, {**task_environment(repo), **env})
    if done.returncode != 0:
        raise SuiteRunError(f"`{' '.join(args[:2])}` in {cwd.name}: {_why(done, cwd, args)}")
    return done


def _why(done: subprocess.CompletedProcess, cwd: Path, args: Sequence[str]) -> str:
    """A failed command's reason in one line: a fault of the machine it met (a full disk, a
    refused permission: `oodrl.faults`; named with the path it gives, else the file the command
    writes or the folder it ran in), else its first error line, else its last line."""
    from oodrl.faults import fault_in_output

    lines = [line.strip() for line in (done.stderr + done.stdout).splitlines() if line.strip()]
    why = next((line for line in lines if line.startswith(("ERROR", "error"))), None)
    written = [arg for arg in args[1:] if args[0] == "git" and os.path.isabs(arg)]  # a bundle
    where = written[-1] if written else str(cwd)
    return fault_in_output(done.stderr + done.stdout, where) or why or (lines or [""])[-1]


def _task_failure(pipeline: str, error: BaseException) -> SuiteRunError:
    """A task's exception as the run's one line: the pipeline, then the fault of the machine
    it met (`oodrl.faults`) or its message."""
    from oodrl.faults import machine_fault

    return SuiteRunError(f"{pipeline}: {machine_fault(error) or error}")


#: The git and DVC processes running now (`_spawn`), each with whether it leads a process group
#: of its own; whether this process passes signals on to them; whether the run was interrupted.
_PROCESSES: dict[subprocess.Popen, bool] = {}
_FORWARDING = threading.Event()
_STOPPING = threading.Event()


def _spawn(command: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run a command to its end. While signals are passed on (`_ending_processes_on_signals`),
    in a process group of its own, so that an interruption reaches DVC's stage commands too;
    once the run is interrupted, no command starts."""
    if _STOPPING.is_set():
        raise SuiteRunError("interrupted")
    own_group = _FORWARDING.is_set()
    pipe = subprocess.PIPE
    with subprocess.Popen(command, cwd=cwd, env=env, stdout=pipe, stderr=pipe, text=True,
                          start_new_session=own_group) as process:  # fmt: skip
        _PROCESSES[process] = own_group
        try:
            if _STOPPING.is_set():  # interrupted since the check above: the stop may have missed it
                _signal(process, signal.SIGTERM)
            stdout, stderr = process.communicate()
        except BaseException:  # interrupted in this thread: the command ends first
            _end(process)
            raise
        finally:
            _PROCESSES.pop(process, None)
    return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)


def _signal(process: subprocess.Popen, signum: int) -> None:
    """Signal a command, and every command it runs where it leads a group of its own."""
    with suppress(ProcessLookupError):  # it ended meanwhile
        if _PROCESSES.get(process):
            os.killpg(process.pid, signum)
        elif process.poll() is None:
            process.send_signal(signum)


def _end(process: subprocess.Popen) -> None:
    """Stop a command as Ctrl-C would, and kill it if it has not stopped in the grace time: the
    `with` blocks above it then delete its directory with nothing writing there."""
    _signal(process, signal.SIGINT)
    try:
        process.wait(timeout=STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        _signal(process, signal.SIGKILL)
        process.wait()


def _signal_all(signum: int) -> None:
    for process in list(_PROCESSES):
        _signal(process, signum)


@contextmanager
def _ending_processes_on_signals() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP end every command the run started and unwind it as Ctrl-C does
    (KeyboardInterrupt), so each scratch clone and DVC config directory goes with its `with`
    block (SPEC §22). The commands have process groups of their own, out of the terminal's reach:
    the signal is passed on to them, and SIGKILL after the grace time or at a second signal. A
    signal the caller ignores (nohup's SIGHUP) stays ignored, and the caller's own handler
    (`oodrl.cli.main`'s, which names the signal) still runs."""
    _STOPPING.clear()
    if threading.current_thread() is not threading.main_thread():  # only it can take signals
        yield
        return
    previous: dict[int, object] = {}
    deadline = threading.Timer(STOP_GRACE_S, _signal_all, [signal.SIGKILL])
    deadline.daemon = True

    def stop(signum: int, frame: object) -> None:
        if _STOPPING.is_set():  # a second signal: already unwinding, let the cleanup finish
            _signal_all(signal.SIGKILL)
            return
        _STOPPING.set()
        _signal_all(signum)
        deadline.start()
        if callable(handler := previous[signum]):
            handler(signum, frame)
        raise KeyboardInterrupt

    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            previous[signum] = signal.signal(signum, stop)
    _FORWARDING.set()
    try:
        yield
    finally:
        deadline.cancel()
        _FORWARDING.clear()
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)


def _git_root(path: Path) -> str:
    for candidate in [path, *path.parents]:
        if (candidate / ".git").exists():
            return str(candidate)
    return str(path)


# -- the head ------------------------------------------------------------------------------------
def run_suite(
    root: Path,
    workers: int = 2,
    ray_address: str | None = None,
    echo: Callable[[str], None] = print,
    *,
    only: Sequence[str] | None = None,
    max_hours: float | None = None,
    commit: bool = False,
    build_missing: bool = False,
) -> SuiteRun:
    """Build the pipelines of the suite that are not current (local workers, or Ray tasks), then
    the leaderboard once every pipeline is current (SPEC §26). `only` names the pipelines to
    build; `max_hours` stops starting pipelines once their last build time would pass it;
    `commit` commits each pipeline as soon as it is built; `build_missing` goes on where a
    read-only remote holds nothing the pipelines to build need (`remote_check.unserved`)."""
    root = root.resolve()
    start = time.perf_counter()
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1. Got {workers} instead.")
    if max_hours is not None and not max_hours > 0:
        raise ConfigError(f"--max-hours must be > 0. Got {max_hours} instead.")
    if max_hours is not None and ray_address is not None:
        raise ConfigError("--max-hours decides when a local worker starts a pipeline; with "
                          "--ray every task starts at once: pick them with --only.")  # fmt: skip
    pipelines = suite_pipelines(root)
    chosen = _chosen(pipelines, only)
    from oodrl.suite.checkout_lock import checkout_lock

    with checkout_lock(root, "suite run"):
        if commit:
            _refuse_uncommittable(root)
        remove_dead_runs(root)
        plan = _Plan(pipelines, chosen, max_hours * 3600 if max_hours else None, commit,
                     build_missing)  # fmt: skip
        with _ending_processes_on_signals():
            return _build_suite(root, workers, ray_address, echo, start, plan)


@dataclass(frozen=True)
class _Plan:
    """What a run is asked to build: the suite's pipelines, those it may build (`--only`), its
    budget in seconds, whether it commits each, whether it builds without a serving remote."""

    pipelines: list[str]
    chosen: list[str]
    budget_s: float | None
    commit: bool
    build_missing: bool


def _chosen(pipelines: list[str], only: Sequence[str] | None) -> list[str]:
    """The pipelines `--only` names (all without it); an unknown name is one line."""
    if only is None:
        return pipelines
    names = [os.path.normpath(name.strip()) for name in only if name.strip()]
    unknown = [name for name in names if name not in pipelines]
    if unknown or not names:
        raise ConfigError(f"--only {','.join(unknown) or repr('')}: not a pipeline of the suite; "
                          f"its pipelines: {', '.join(pipelines)} (the leaderboard is built "
                          f"once every one is current).")  # fmt: skip
    return [pipeline for pipeline in pipelines if pipeline in names]


def _refuse_uncommittable(root: Path) -> None:
    """--commit commits on the checkout's branch, one commit per pipeline holding its locks and
    results alone: refused in one line, before anything runs, where git could not do so
    cleanly: an operation in progress, a detached HEAD, an uncommitted change of a tracked
    file, no committer identity."""

    def git(*args: str) -> subprocess.CompletedProcess:
        return _spawn(["git", *args], root, dict(os.environ))

    git_dir = root / git("rev-parse", "--git-dir").stdout.strip()
    operations = {"MERGE_HEAD": "a merge", "rebase-merge": "a rebase", "rebase-apply": "a rebase",
                  "CHERRY_PICK_HEAD": "a cherry-pick", "REVERT_HEAD": "a revert"}  # fmt: skip
    for name, operation in operations.items():
        if (git_dir / name).exists():
            raise ConfigError(f"--commit: {root} is in the middle of {operation}; conclude it or "
                              f"abort it first, then run again.")  # fmt: skip
    if git("symbolic-ref", "-q", "HEAD").returncode != 0:
        raise ConfigError(f"--commit: {root} has a detached HEAD; --commit commits on a branch: "
                          f"`git switch -c NAME` (or switch to one) first.")  # fmt: skip
    changed = git("status", "--porcelain", "--untracked-files=no").stdout.splitlines()
    if changed:
        paths = [line[3:] for line in changed]
        raise ConfigError(f"--commit: {', '.join(paths[:3])}{' …' if len(paths) > 3 else ''}: "
                          f"uncommitted; each commit holds one pipeline's locks and results "
                          f"alone, so commit (or revert) these first.")  # fmt: skip
    if git("var", "GIT_COMMITTER_IDENT").returncode != 0:
        raise ConfigError("--commit: git has no committer identity here; set user.name and "
                          "user.email (`git config`), then run again.")  # fmt: skip


def _build_suite(
    root: Path,
    workers: int,
    ray_address: str | None,
    echo: Callable[[str], None],
    start: float,
    plan: _Plan,
) -> SuiteRun:
    from oodrl.suite.migration import project_states, target_version
    from oodrl.suite.pipeline import SUITE_DIR

    pipelines = plan.pipelines
    projects = [*pipelines, SUITE_DIR.as_posix()]
    # A word at once (importing DVC and asking the remote take seconds), then the remote and
    # Ray: refused in seconds, before anything else.
    echo(f"suite: {len(projects)} projects; checking the DVC remote"
         f"{' and the Ray head' if ray_address is not None else ''} first")  # fmt: skip
    if ray_address is not None:
        _check_reachable(ray_address)
    remote = default_remote(root)
    read_only = _check_remote(root, remote) if remote is not None else None
    if ray_address is not None and remote is None:
        raise ConfigError("--ray: the nodes share stages through a DVC remote and none is "
                          "configured; add one every node can reach (docs/how-to/remotes.md), "
                          "e.g. `dvc remote add -d lab s3://bucket/oodrl`.")  # fmt: skip
    if ray_address is not None and read_only:
        raise ConfigError(f"--ray: the nodes share stages through a DVC remote and "
                          f"{remote.name!r} is read-only ({read_only}); give them one they can "
                          f"write (docs/how-to/remotes.md), or build on this machine with "
                          f"--workers.")  # fmt: skip
    if read_only:
        remote = replace(remote, writable=False)
        echo(f"suite: remote {remote.name!r} ({remote.options.get('url')}) is read-only "
             f"({read_only}): restoring from it, building what it lacks locally, pushing "
             f"nothing")  # fmt: skip
    # From the committed files alone (SPEC §26): nothing is restored or recomputed to know that
    # a pipeline is current, so a fresh clone with an empty cache decides in seconds.
    states = {state.project: state for state in project_states(root, pipelines)}
    echo(_states_line(states))
    todo = [pipeline for pipeline in pipelines if states[pipeline].status != "current"]
    stale = [pipeline for pipeline in todo if states[pipeline].status == "stale"]
    if plan.commit and stale:  # what --commit would commit is a migration's step, nothing else
        first, more = states[stale[0]], " …" if stale[3:] else ""
        raise ConfigError(f"{', '.join(stale[:3])}{more}: stale, not pending a protocol change "
                          f"({first.project}: {_why_stale(first)}); --commit builds and commits "
                          f"pending pipelines only: relock as the change needs, or run without "
                          f"--commit.")  # fmt: skip
    building = [pipeline for pipeline in todo if pipeline in plan.chosen]
    version = target_version()  # the version the states above were judged against
    if not todo and _up_to_date(root / SUITE_DIR):
        echo(f"suite: all {len(projects)} projects are up to date; nothing to run")
        return SuiteRun((), (), time.perf_counter() - start)
    if todo and not building:
        echo(f"suite: nothing to build among {', '.join(plan.chosen)}; still to build: "
             f"{', '.join(todo)}")  # fmt: skip
        return SuiteRun((), (), time.perf_counter() - start)
    if read_only:  # whether it holds what is to build is asked once that is known
        _check_serves(root, remote, building, plan.build_missing, echo)
    shared_cache = None if ray_address else _cache_dir(root, projects)
    _refuse_uncommitted_inputs(root, projects)
    if building and len(building) < len(pipelines):
        by_only = f" ({len(todo) - len(building)} left by --only)" if building != todo else ""
        echo(f"suite: {len(pipelines) - len(todo)} of {len(pipelines)} pipelines are up to "
             f"date; building the other {len(building)}{by_only}")  # fmt: skip
    recorded = _recorded_builds(root) if plan.budget_s is not None or plan.commit else {}
    job = {
        "bundle": _bundle(root) if building else b"",
        "commit": _run(root, {}, "git", "rev-parse", "HEAD").stdout.strip(),
        "remote": remote,
        "shared_cache": shared_cache,
    }
    not_started: list[str] = []
    if ray_address is None:
        may_start = _budget(root, building, recorded, plan.budget_s, start, not_started)
        tasks_of = _local_tasks(root, building, job, workers, echo, may_start, recorded)
    else:
        tasks_of = _ray_tasks(root, building, job, ray_address, echo, recorded)
    runs: list[PipelineRun] = []
    head_ran: list[str] = []
    last_task_ended = start
    leaderboard_seconds = 0.0
    # closing: an interruption or a failure while the head restores stops the tasks now.
    with closing(tasks_of) as tasks, _dvc_config(remote) as env:
        # Restored (and committed) as each task ends, while the others run: projects are
        # separate DVC workspaces. A later failure leaves the projects restored so far
        # consistent (each one's locks and outputs are those of a finished `dvc repro`), the
        # others untouched; with --commit, those restored so far committed.
        for built in tasks:
            last_task_ended = time.perf_counter()
            restored = restore_project(root, built, remote, env)
            runs.append(replace(built, files={}, restore_seconds=restored))
            if plan.commit:
                _commit_project(root, built.pipeline, built.files,
                                f"suite run: {built.pipeline} built at protocol {version} in "
                                f"{built.seconds:.0f} s")  # fmt: skip
            echo(f"suite: {built.pipeline} done{', committed' if plan.commit else ''}; "
                 f"{len(runs)} of {len(building)} done, "
                 f"{len(building) - len(runs) - len(not_started)} to do, "
                 f"{_clock(time.perf_counter() - start)} elapsed")  # fmt: skip
        left = [pipeline for pipeline in todo if pipeline not in {r.pipeline for r in runs}]
        if not left:  # every pipeline current: the leaderboard ranks them all
            began = time.perf_counter()
            done = _from_remote(root / SUITE_DIR, env, remote, "repro",
                                *(["--pull"] if remote else []))  # fmt: skip
            head_ran = [f"{SUITE_DIR.as_posix()}:{stage}" for stage in ran_stages(done.stdout)]
            leaderboard_seconds = time.perf_counter() - began
            if remote and remote.writable:  # as a task pushes its project: a clone restores it
                _push(root / SUITE_DIR, env)
            if plan.commit:
                _commit_project(root, SUITE_DIR.as_posix(), checkout_files(root / SUITE_DIR),
                                f"suite run: {SUITE_DIR.as_posix()} (the leaderboard) built at "
                                f"protocol {version}, every pipeline current")  # fmt: skip
    end = time.perf_counter()
    after = end - last_task_ended
    if left:
        budget = f"--max-hours {plan.budget_s / 3600:g} reached; " if not_started else ""
        echo(f"suite: {budget}{len(left)} pipelines left for another run: {', '.join(left)}; "
             f"the leaderboard is built once every one is current")  # fmt: skip
    echo(f"suite: done in {end - start:.1f} s, {after:.1f} s of them after the last task; "
         f"the head ran {', '.join(head_ran) or 'nothing'}")  # fmt: skip
    return SuiteRun(tuple(runs), tuple(head_ran), end - start, after, leaderboard_seconds)


def _states_line(states: Mapping) -> str:
    """Where the pipelines stand, in one line: how many are current, then the pending ones with
    the version they were built at and the stale ones with their first reason."""
    current = sum(state.status == "current" for state in states.values())
    parts = [f"suite: from git, {current} of {len(states)} pipelines current"]
    pending = [f"{s.project} (protocol {s.built_version})" for s in states.values()
               if s.status == "pending"]  # fmt: skip
    stale = [f"{s.project} ({_why_stale(s)})" for s in states.values() if s.status == "stale"]
    parts += [f"pending: {', '.join(pending)}"] if pending else []
    parts += [f"stale: {', '.join(stale)}"] if stale else []
    return "; ".join(parts)


def _why_stale(state) -> str:
    """A stale pipeline's first reason, and how many more."""
    more = len(state.reasons) - 1
    return f"{state.reasons[0] if state.reasons else 'stale'}{f'; {more} more' if more > 0 else ''}"


def _clock(seconds: float) -> str:
    minutes, second = divmod(int(seconds), 60)
    return f"{minutes // 60}:{minutes % 60:02d}:{second:02d}"


#: The subject of the commit `--commit` makes for a pipeline: the next run reads each
#: pipeline's last build time from it (a fresh clone has no reports/run_meta.yaml).
COMMIT_SUBJECT = re.compile(r"^suite run: (\S+) built at protocol \d+ in (\d+) s$")


def _commit_project(root: Path, project: str, files: Mapping[str, bytes], message: str) -> None:
    """Commit a restored project's files that git does not ignore (its locks, the results DVC
    does not cache, the .gitignore files beside its outputs), those paths alone, and the removal
    of the files it no longer writes (`superseded_outputs`)."""
    paths = sorted(os.path.normpath(os.path.join(project, name)) for name in files)
    env = dict(os.environ)
    ignored = _spawn(["git", "check-ignore", "--", *paths], root, env).stdout.splitlines()
    paths = [path for path in paths if path not in set(ignored)]
    _run(root, {}, "git", "add", "--", *paths)
    if superseded := superseded_outputs(root, project, files):
        _run(root, {}, "git", "rm", "-q", "--", *superseded)  # staged: committed with the rest
        paths = sorted([*paths, *superseded])
    if _spawn(["git", "diff", "--cached", "--quiet", "--", *paths], root, env).returncode == 0:
        return  # built as committed: nothing to commit
    _run(root, {}, "git", "commit", "-q", "-m", message, "--", *paths)


def superseded_outputs(root: Path, project: str, files: Mapping[str, bytes]) -> list[str]:
    """The git-tracked files that a project's committed locks (HEAD's version of each dvc.lock
    among `files`) record as outputs and that its build no longer writes: a protocol that
    renames an output (protocol 5's reports/tier_results.json for protocol 4's .yaml) leaves no
    file of the previous version beside the new one, for a reader to find. Paths from `root`."""
    from oodrl.io import yamlio

    env = dict(os.environ)
    written = {os.path.normpath(os.path.join(project, name)) for name in files}
    recorded = set()
    for name in files:
        if os.path.basename(name) != "dvc.lock":
            continue
        lock = os.path.normpath(os.path.join(project, name))
        shown = _spawn(["git", "show", f"HEAD:{Path(lock).as_posix()}"], root, env)
        if shown.returncode != 0:  # a lock the project did not have at HEAD
            continue
        stages = (yamlio.load(shown.stdout) or {}).get("stages", {})
        recorded |= {
            os.path.normpath(os.path.join(os.path.dirname(lock), out["path"]))
            for stage in stages.values()
            for out in stage.get("outs", [])
        }
    gone = sorted(
        path for path in recorded
        if path not in written and not any(w.startswith(path + os.sep) for w in written)
    )  # fmt: skip
    if not gone:
        return []
    tracked = _spawn(["git", "ls-files", "--", *gone], root, env).stdout.splitlines()
    return sorted(set(tracked))


def _recorded_builds(root: Path) -> dict[str, float]:
    """Each pipeline's last build time that `--commit` recorded in git (COMMIT_SUBJECT)."""
    done = _spawn(["git", "log", "--format=%s", "--grep=^suite run: "], root, dict(os.environ))
    recorded: dict[str, float] = {}
    for subject in done.stdout.splitlines():  # newest first
        if (found := COMMIT_SUBJECT.match(subject)) and found[1] not in recorded:
            recorded[found[1]] = float(found[2])
    return recorded


def _budget(
    root: Path,
    pipelines: list[str],
    recorded: Mapping[str, float],
    budget_s: float | None,
    start: float,
    not_started: list[str],
) -> Callable[[str], bool]:
    """Whether a worker free now may start a pipeline: while its last build time (or, never
    built, the median of the others', else nothing) still fits in the budget; one that does not
    is left for another run, in `not_started`."""
    known = {p: s for p in pipelines if (s := _last_build_seconds(root, p, recorded)) < math.inf}
    typical = sorted(known.values())[len(known) // 2] if known else 0.0
    lock = threading.Lock()

    def may_start(pipeline: str) -> bool:
        if budget_s is None:
            return True
        fits = time.perf_counter() - start + known.get(pipeline, typical) <= budget_s
        if not fits:
            with lock:
                not_started.append(pipeline)
        return fits

    return may_start


def _last_build_seconds(root: Path, pipeline: str, recorded: Mapping[str, float]) -> float:
    """The stage wall time of the pipeline's last build in this checkout (`total_stage_wall_s`
    of its reports/run_meta.yaml), else the build time its last --commit recorded, else inf."""
    meta = _text_or_empty(root / pipeline / RUN_META)
    found = re.search(r"^total_stage_wall_s: ([0-9.]+)$", meta, re.MULTILINE)
    return float(found[1]) if found else recorded.get(pipeline, math.inf)


def restore_project(
    root: Path, built: PipelineRun, remote: Remote | None, env: dict[str, str]
) -> float:
    """A task's locks and uncached outputs written into the head's project, every other output
    checked out from the cache (pulled first from a writable remote): what `dvc repro` would
    leave, without DVC's per-stage run-cache lookups. `--force` replaces outputs as `dvc repro`
    does. The seconds it took."""
    from oodrl.io.fileio import atomic_write_bytes

    began = time.perf_counter()
    project = root / built.pipeline
    for name, content in built.files.items():
        atomic_write_bytes(project / name, content)
    if remote and remote.writable:
        try:
            _from_remote(project, env, remote, "pull", "--force", "-q")
        except SuiteRunError as error:
            raise SuiteRunError(f"{built.pipeline}: {error}") from None
    else:  # the tasks pulled into the shared cache
        _run(project, env, "dvc", "checkout", "--force", "-q")
    return time.perf_counter() - began


def _finished(echo, pipeline: str, node: str, built: tuple) -> PipelineRun:
    seconds, ran, files = built
    echo(f"finished {pipeline} in {seconds:.1f} s on {node} ({len(ran)} stages ran)")
    return PipelineRun(pipeline, seconds, node, ran, files)


def _local_tasks(
    root: Path,
    pipelines: list[str],
    job: dict,
    workers: int,
    echo,
    may_start: Callable[[str], bool] | None = None,
    recorded: Mapping[str, float] | None = None,
) -> Iterator[PipelineRun]:
    """Each pipeline's task on a local worker; `may_start` (--max-hours) can hold one back,
    `recorded` (its last build walls) orders them. `oodrl suite try` passes neither."""

    def task(pipeline: str) -> PipelineRun | None:
        if may_start is not None and not may_start(pipeline):
            return None
        echo(f"started  {pipeline}")
        return _finished(echo, pipeline, "local", build_pipeline(pipeline=pipeline, **job))

    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        order = _longest_first(root, pipelines, recorded)
        futures = {pool.submit(task, pipeline): pipeline for pipeline in order}
        for future in as_completed(futures):
            if future.exception() is not None:
                raise _task_failure(futures[future], future.exception())
            if future.result() is not None:
                yield future.result()
    finally:
        # No new pipeline starts; running ones finish (or stop: an interruption ended them).
        pool.shutdown(cancel_futures=True)


def _longest_first(
    root: Path, pipelines: list[str], recorded: Mapping[str, float] | None = None
) -> list[str]:
    """Longest first, so that a long pipeline never starts last: by its last build time
    (`_last_build_seconds`); a pipeline with none (never built here) counts as the longest.
    Ties keep the suite's order."""
    known = recorded or {}
    return sorted(pipelines, key=lambda pipeline: -_last_build_seconds(root, pipeline, known))


def _text_or_empty(path: Path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        return ""


def _ray_tasks(
    root: Path, pipelines: list[str], job: dict, address: str, echo, recorded: Mapping[str, float]
) -> Iterator[PipelineRun]:
    import ray

    ray.init(address=address, log_to_driver=False, logging_level="ERROR")
    try:
        remote_build = ray.remote(num_cpus=1, max_retries=RAY_MAX_RETRIES)(_ray_build)
        shared = {**job, "bundle": ray.put(job["bundle"])}
        names = {}
        for pipeline in _longest_first(root, pipelines, recorded):
            echo(f"started  {pipeline}")
            names[remote_build.remote(pipeline=pipeline, **shared)] = pipeline
        pending = list(names)
        while pending:
            (ready,), pending = ray.wait(pending, num_returns=1)
            try:
                *built, node = ray.get(ready)
            except ray.exceptions.RayError as error:
                for ref in pending:
                    ray.cancel(ref, force=True)
                cause = getattr(error, "cause", None)
                raise _task_failure(names[ready], cause or error) from None
            yield _finished(echo, names[ready], node, tuple(built))
    finally:
        ray.shutdown()


def _ray_build(**job) -> tuple[float, tuple[str, ...], dict[str, bytes], str]:
    import ray

    remove_dead_task_folders()
    return *build_pipeline(**job), ray.get_runtime_context().get_node_id()


#: What `ray.init` asks a head first, its GCS (the cluster's ID), and one request more. In a
#: process of its own: Ray's C++ client retries and logs on its own, so the process's timeout
#: bounds it and its captured output keeps the error one line. Ray's own timeouts shortened so
#: that a refusal says why rather than running out of RAY_HANDSHAKE_S.
PROBE_GCS = """
import sys
from ray._raylet import GcsClient
GcsClient(address=sys.argv[1]).internal_kv_get(b"oodrl-suite-probe", None, timeout=3)
"""
PROBE_ENV = {"RAY_gcs_rpc_server_connect_timeout_s": "2", "RAY_py_gcs_connect_timeout_s": "3"}


def _check_reachable(address: str) -> None:
    """An address nothing answers at, or something other than Ray does (TCP alone passes an
    HTTP server, then `ray.init` hangs for minutes), is one line in seconds."""
    match = re.fullmatch(r"(ray://)?([^:/]+):(\d+)", address)
    if match is None:
        raise ConfigError(f"--ray: {address!r} is not HOST:PORT (the address `ray start "
                          f"--head` prints, e.g. 10.0.0.5:6379).")  # fmt: skip
    import importlib.util

    if importlib.util.find_spec("ray") is None:
        raise ConfigError("--ray needs Ray, which is not installed: pip install 'oodrl[ray]'.")
    try:
        socket.create_connection((match[2], int(match[3])), timeout=5).close()
    except OSError as error:
        raise SuiteRunError(f"--ray: no Ray cluster answers at {address} "
                            f"({error.strerror or error}).") from None  # fmt: skip
    if match[1]:  # a Ray Client server (ray://): `ray.init` handshakes with its own timeout
        return
    command = [sys.executable, "-c", PROBE_GCS, f"{match[2]}:{match[3]}"]
    try:
        done = subprocess.run(command, env={**os.environ, **PROBE_ENV}, capture_output=True,
                              timeout=RAY_HANDSHAKE_S)  # fmt: skip
        answered = done.returncode == 0
    except subprocess.TimeoutExpired:
        answered = False
    if not answered:
        raise SuiteRunError(f"--ray: {address} accepts connections but does not answer as a Ray "
                            f"head (GCS handshake, {RAY_HANDSHAKE_S} s); give the address `ray "
                            f"start --head` prints, e.g. 10.0.0.5:6379.")  # fmt: skip


def _up_to_date(project: Path) -> bool:
    """Whether `dvc repro` of a project would run nothing (every lock and output current)."""
    command = [sys.executable, "-m", "dvc", "status", "--quiet"]
    return _spawn(command, project, task_environment(Path(_git_root(project)))).returncode == 0


def _refuse_uncommitted_inputs(root: Path, projects: list[str]) -> None:
    """The tasks build the head's commit, so an uncommitted edit of a tracked input (code,
    params, a DVC file) would be missing there. Locks and DVC outputs may differ: they are
    what the run rewrites."""
    changed = _run(root, {}, "git", "diff", "--name-only", "HEAD").stdout.splitlines()
    inputs = [path for path in changed if Path(path).name != "dvc.lock"]
    if inputs:
        outputs = set().union(*(_dvc_outputs(root, root / project) for project in projects))
        inputs = [path for path in inputs if path not in outputs]
    if inputs:
        raise ConfigError(f"{', '.join(inputs[:3])}{' …' if len(inputs) > 3 else ''}: "
                          f"uncommitted; the workers build the head's commit, so commit (or "
                          f"revert) these first.")  # fmt: skip


def _dvc_outputs(root: Path, project: Path) -> set[str]:
    """Every output path of a project's stages, relative to the repository root."""
    from dvc.repo import Repo

    with Repo(str(project)) as repo:
        paths = (Path(out.fs_path) for stage in repo.index.stages for out in stage.outs)
        return {path.relative_to(root).as_posix() for path in paths}


def default_remote(root: Path) -> Remote | None:
    """The root project's default DVC remote (any config level), or None."""
    from dvc.repo import Repo

    with Repo(str(root)) as repo:
        name = repo.config["core"].get("remote")
        if not name:
            return None
        return Remote(name, {key: str(value) for key, value in repo.config["remote"][name].items()})


def _cache_dir(root: Path, projects: list[str]) -> str:
    """The DVC cache local tasks fill: the root's (SUBREPO_FILES), which every project must use
    too, since the head checks each project out of its own. An environment project's generated
    .dvc/config names the root's .dvc/cache, which a root cache moved by config (`dvc cache dir
    --local`) is not: refused in one line before any task."""
    from dvc.config import Config

    shared = _run(root, {}, "dvc", "cache", "dir").stdout.strip()
    for project in projects:
        dvc_dir = root / project / ".dvc"
        own = Path(Config(dvc_dir=str(dvc_dir))["cache"].get("dir") or dvc_dir / "cache")
        if own.resolve() != Path(shared).resolve():
            raise ConfigError(
                f"{project} uses the DVC cache {own}, the root {shared}; local workers fill the "
                f"root's and each project is checked out of its own. Give every project the "
                f"root's (`dvc cache dir --local {shared}` in its directory) or keep the root's "
                f"in .dvc/cache."
            )
    return shared


def _check_remote(root: Path, remote: Remote) -> str | None:
    """None for a remote the run can write; why it is read-only otherwise: an HTTP(S) URL (DVC
    pushes there by POST, which a static server or a bucket's HTTPS view refuses), or a remote
    that refuses the probe write. One that does not answer, or does not exist, is an error."""
    if remote.options.get("url", "").split("://")[0].lower() in ("http", "https"):
        _check_answers(remote)
        return "HTTP"
    return _check_writable(root, remote)


def _check_answers(remote: Remote) -> None:
    """Any HTTP answer at the remote's URL passes (a bucket's HTTPS view answers 403 or 404 at
    its top); none is one line, where `dvc pull --allow-missing` would pass over it in silence
    and every stage would run."""
    import urllib.error
    import urllib.request

    from oodrl.suite.remote_check import ssl_context

    url = remote.options["url"]
    context = ssl_context(remote.options)
    try:
        request = urllib.request.Request(url, method="HEAD")
        urllib.request.urlopen(request, timeout=REMOTE_ANSWER_S, context=context).close()
    except urllib.error.HTTPError:
        pass  # it answered
    except OSError as error:  # URLError, a timeout
        why = getattr(error, "reason", None) or error
        raise SuiteRunError(f"DVC remote {remote.name!r} ({url}) does not answer: "
                            f"{why}") from None  # fmt: skip


def _check_serves(
    root: Path, remote: Remote, pipelines: list[str], build_missing: bool, echo
) -> None:
    """A read-only remote that refuses, or holds none of, what the pipelines to build need
    (`oodrl.suite.remote_check.unserved`) is one line before any stage runs; with
    `build_missing` the line is said and the build goes on here."""
    from oodrl.suite.remote_check import unserved

    why = unserved(root, remote, pipelines, REMOTE_ANSWER_S)
    if why is None:
        return
    if not build_missing:
        raise SuiteRunError(f"{why}; or pass --build-missing to build what it lacks here, from "
                            f"scratch.")  # fmt: skip
    echo(f"suite: {why}; building what it lacks here (--build-missing)")


def _check_writable(root: Path, remote: Remote) -> str | None:
    """Write and delete a probe file at the remote's top: None if it can, DVC's reason if the
    write is refused (a permission: the remote is read-only). Any other failure is one line
    before any task starts, not after each has run. The check creates nothing: a directory
    remote that does not exist is refused (a typo in its URL would otherwise become a new,
    empty remote that the whole suite builds into), as a bucket that does not exist is."""
    import errno
    import uuid

    from dvc.repo import Repo

    missing = None
    try:
        with Repo(str(root)) as repo:
            target = repo.cloud.get_remote(remote.name)
            if target.fs.protocol == "local" and not os.path.isdir(target.path):
                missing = target.path
            else:
                probe = target.fs.join(target.path, f"oodrl-suite-probe-{uuid.uuid4().hex}")
                target.fs.pipe_file(probe, b"")
                target.fs.rm_file(probe)
    except Exception as error:  # noqa: BLE001 - any failure, whatever the filesystem raises
        why = str(error).splitlines()[0] if str(error) else type(error).__name__
        if isinstance(error, PermissionError) or getattr(error, "errno", None) == errno.EROFS:
            return f"it refuses a write: {why}"
        raise SuiteRunError(f"DVC remote {remote.name!r} ({remote.options.get('url')}) "
                            f"fails a probe write: {why}") from None  # fmt: skip
    if missing is not None:
        what = "is not a directory" if os.path.exists(missing) else "does not exist"
        raise SuiteRunError(f"DVC remote {remote.name!r}: {missing} {what}; create the "
                            f"directory yourself, or fix the remote's URL (`dvc remote modify "
                            f"{remote.name} url DIR`); oodrl creates no remote.")  # fmt: skip
    return None


def _bundle(root: Path) -> bytes:
    """The head's commit and its history in one file: a task on any node clones from it."""
    with working_folder(TASK_FOLDER) as scratch:
        path = Path(scratch) / "head.bundle"
        _run(root, {}, "git", "bundle", "create", "-q", str(path), "HEAD")
        return path.read_bytes()
