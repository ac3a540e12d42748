"""`oodrl suite run` (SPEC §16): every pipeline of the suite in parallel, then the leaderboard.

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
  what it lacks is built locally. On Ray it is refused (the nodes would share nothing).

With a remote a task first pulls what the remote has (`dvc pull --allow-missing`), then runs
`dvc repro --pull`. Not `dvc repro --pull --allow-missing`, DVC's own "fetch what is unchanged,
run what changed": it skips, without pulling, a stage whose outputs are missing but otherwise
current, and forgives a missing dep only when its path is absent. On a fresh clone that runs
nothing (git ignores whole the directories several stages fill, `oodrl.suite.pipeline.FILLED_DIRS`,
so a clone has none of them), but once a stage reading such a directory must run (the root's
`tier_metrics` reads `data/impact`, each `impact@<fault>` writes one file in it), `--pull`
cannot fetch the directory, which is no stage's output. One `dvc pull` is also faster than
DVC's pull per stage. `dvc pull --allow-missing` passes over a remote that does not answer, so
a remote is checked before any task starts (`_check_remote`).
"""

from __future__ import annotations

import json
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


def suite_pipelines(root: Path) -> list[str]:
    """The root's pipeline (the paper's default) and every run the suite's leaderboard reads (the
    pipelines whose results its generated dvc.yaml depends on), relative to the root ('.' is the
    root's own). A pipeline `oodrl new` made, or a policy not yet in
    `oodrl.suite.environments.MORE_POLICIES`, is not the suite's: build it with `dvc repro` in its
    directory."""
    import yaml

    from oodrl.suite.pipeline import SUITE_DIR

    suite = root / SUITE_DIR / "dvc.yaml"
    if not suite.is_file():
        raise ConfigError(f"--root {root}: not an oodrl suite (no {SUITE_DIR}/dvc.yaml); pass the "
                          "repository's root, where `oodrl pipeline write` put it.")  # fmt: skip
    stage = yaml.safe_load(suite.read_text())["stages"]["leaderboard"]
    results = [Path(d) for d in stage["deps"] if d.endswith("/reports/results.yaml")]
    runs = {(root / SUITE_DIR / d).resolve().parent.parent.relative_to(root) for d in results}
    return [".", *sorted(r.as_posix() for r in runs)]


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
        if remote:  # what the remote has, in one pull (why: the module's docstring)
            _from_remote(project, env, remote, "pull", "--allow-missing", "-q", check=True)
        chosen = tuple(targets[pipeline]) if targets is not None else ()
        done = _from_remote(project, env, remote, "repro", *(["--pull"] if remote else []),
                            *chosen)  # fmt: skip
        if remote and remote.writable:
            _push(project, env)
        files = checkout_files(project)
    return time.perf_counter() - start, ran_stages(done.stdout), files


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
) -> SuiteRun:
    """Build every pipeline of the suite (local workers, or Ray tasks), then the leaderboard."""
    root = root.resolve()
    start = time.perf_counter()
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1. Got {workers} instead.")
    from oodrl.suite.checkout_lock import checkout_lock

    with checkout_lock(root, "suite run"):
        remove_dead_runs(root)
        with _ending_processes_on_signals():
            return _build_suite(root, workers, ray_address, echo, start)


def _build_suite(
    root: Path, workers: int, ray_address: str | None, echo: Callable[[str], None], start: float
) -> SuiteRun:
    from oodrl.io.fileio import atomic_write_text
    from oodrl.suite.pipeline import SUITE_DIR

    pipelines = suite_pipelines(root)
    projects = [*pipelines, SUITE_DIR.as_posix()]
    if _unchanged_since_found_current(root, projects):
        echo(f"suite: all {len(projects)} projects are up to date (no file DVC checks changed "
             f"since they were found so); nothing to run")  # fmt: skip
        return SuiteRun((), (), time.perf_counter() - start)
    # A word at once (importing DVC and asking the remote take seconds), then the remote and
    # Ray, which need no `dvc status`: refused in seconds, not after the status checks.
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
    shared_cache = None if ray_address else _cache_dir(root, projects)
    echo(f"suite: checking {len(projects)} projects with dvc status ({workers} at a time)")
    watched = _watched_files(root, projects)
    before = _signature(root, watched)  # before the checks: a change during them shows next time
    # One `dvc status` process a project, `workers` at a time: DVC's own index and output
    # checks take seconds a project (about 4 s for 198 stages), so they bound a no-op run.
    with ThreadPoolExecutor(max_workers=workers) as pool:
        current = list(pool.map(lambda project: _up_to_date(root / project), projects))
    if all(current):
        found = {"projects": projects, "paths": watched, "signature": before}
        atomic_write_text(root / FOUND_CURRENT, json.dumps(found))
        echo(f"suite: all {len(projects)} projects are up to date; nothing to run")
        return SuiteRun((), (), time.perf_counter() - start)
    _refuse_uncommitted_inputs(root, projects)
    # A current pipeline's task would clone it only to restore every stage from the cache: the
    # head's checkout already is what that task would write.
    stale = [pipeline for pipeline, ok in zip(pipelines, current, strict=False) if not ok]
    if len(stale) < len(pipelines):
        echo(f"suite: {len(pipelines) - len(stale)} of {len(pipelines)} pipelines are up to "
             f"date; building the other {len(stale)}")  # fmt: skip
    job = {
        "bundle": _bundle(root),
        "commit": _run(root, {}, "git", "rev-parse", "HEAD").stdout.strip(),
        "remote": remote,
        "shared_cache": shared_cache,
    }
    if ray_address is None:
        building = _local_tasks(root, stale, job, workers, echo)
    else:
        building = _ray_tasks(root, stale, job, ray_address, echo)
    runs: list[PipelineRun] = []
    last_task_ended = start
    # closing: an interruption or a failure while the head restores stops the tasks now.
    with closing(building) as tasks, _dvc_config(remote) as env:

        def restore(built: PipelineRun) -> float:
            return restore_project(root, built, remote, env)

        # Restored as each task ends, while the others run: projects are separate DVC
        # workspaces. A later failure leaves the projects restored so far consistent (each
        # one's locks and outputs are those of a finished `dvc repro`), the others untouched.
        for built in tasks:
            last_task_ended = time.perf_counter()
            runs.append(replace(built, files={}, restore_seconds=restore(built)))
        began = time.perf_counter()
        done = _from_remote(root / SUITE_DIR, env, remote, "repro",
                            *(["--pull"] if remote else []))  # fmt: skip
        head_ran = [f"{SUITE_DIR.as_posix()}:{stage}" for stage in ran_stages(done.stdout)]
        leaderboard_seconds = time.perf_counter() - began
        if remote and remote.writable:  # as a task pushes its project: a clone restores it
            _push(root / SUITE_DIR, env)
    end = time.perf_counter()
    after = end - last_task_ended
    echo(f"suite: done in {end - start:.1f} s, {after:.1f} s of them after the last task; "
         f"the head ran {', '.join(head_ran) or 'nothing'}")  # fmt: skip
    return SuiteRun(tuple(runs), tuple(head_ran), end - start, after, leaderboard_seconds)


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
    root: Path, pipelines: list[str], job: dict, workers: int, echo
) -> Iterator[PipelineRun]:
    def task(pipeline: str) -> PipelineRun:
        echo(f"started  {pipeline}")
        return _finished(echo, pipeline, "local", build_pipeline(pipeline=pipeline, **job))

    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        futures = {
            pool.submit(task, pipeline): pipeline for pipeline in _longest_first(root, pipelines)
        }
        for future in as_completed(futures):
            if future.exception() is not None:
                raise _task_failure(futures[future], future.exception())
            yield future.result()
    finally:
        # No new pipeline starts; running ones finish (or stop: an interruption ended them).
        pool.shutdown(cancel_futures=True)


def _longest_first(root: Path, pipelines: list[str]) -> list[str]:
    """Longest first, so that a long pipeline never starts last: by the stage wall time of its
    last build in the checkout (`total_stage_wall_s` of its reports/run_meta.yaml); a pipeline
    with none (never built here) counts as the longest. Ties keep the suite's order."""

    def last_build_seconds(pipeline: str) -> float:
        meta = root / pipeline / RUN_META
        found = re.search(r"^total_stage_wall_s: ([0-9.]+)$", _text_or_empty(meta), re.MULTILINE)
        return float(found[1]) if found else math.inf

    return sorted(pipelines, key=lambda pipeline: -last_build_seconds(pipeline))


def _text_or_empty(path: Path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        return ""


def _ray_tasks(
    root: Path, pipelines: list[str], job: dict, address: str, echo
) -> Iterator[PipelineRun]:
    import ray

    ray.init(address=address, log_to_driver=False, logging_level="ERROR")
    try:
        remote_build = ray.remote(num_cpus=1, max_retries=RAY_MAX_RETRIES)(_ray_build)
        shared = {**job, "bundle": ray.put(job["bundle"])}
        names = {}
        for pipeline in _longest_first(root, pipelines):
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


#: What the suite's projects looked like when every `dvc status` found them current.
FOUND_CURRENT = Path(".dvc", "tmp", "oodrl-suite-current.json")  # DVC's git-ignored scratch
#: A project's own files that `dvc status` reads, whatever its lock names.
DVC_FILES = ("dvc.yaml", "dvc.lock", ".dvcignore")


def _watched_files(root: Path, projects: list[str]) -> list[str]:
    """Every path whose change `dvc status` of these projects could notice, relative to `root`:
    each project's dvc.yaml, dvc.lock and .dvcignore, and every dep, params file and output its
    lock names; a directory with every file and folder inside it (a folder's mtime moves when an
    entry is added or removed). A project's locks name its paths, so while no watched file
    changes, neither does this list."""
    import yaml

    watched: set[str] = set()
    for project in projects:
        watched.update(os.path.normpath(os.path.join(project, name)) for name in DVC_FILES)
        lock_path = root / project / "dvc.lock"
        if not lock_path.exists():
            continue
        lock = yaml.load(lock_path.read_text(), Loader=yaml.CSafeLoader) or {}
        for stage in (lock.get("stages") or {}).values():
            named = [e["path"] for e in [*stage.get("deps", []), *stage.get("outs", [])]]
            for path in [*named, *stage.get("params", {})]:
                watched.update(_with_contents(root, os.path.normpath(os.path.join(project, path))))
    return sorted(watched)


def _with_contents(root: Path, path: str) -> Iterator[str]:
    yield path
    for folder, subfolders, files in os.walk(root / path):
        for name in [*subfolders, *files]:
            yield Path(folder, name).relative_to(root).as_posix()


def _signature(root: Path, paths: list[str]) -> list[list[int] | None]:
    """(size, mtime, ctime, inode) of each path, None where there is none: the identity DVC's own
    state database trusts to skip re-hashing a file, and its ctime besides."""
    signature = []
    for path in paths:
        try:
            found = os.stat(root / path)
        except FileNotFoundError:
            signature.append(None)
            continue
        signature.append([found.st_size, found.st_mtime_ns, found.st_ctime_ns, found.st_ino])
    return signature


def _unchanged_since_found_current(root: Path, projects: list[str]) -> bool:
    """Whether every `dvc status` once found these projects current and no file it reads has
    changed since: the stat of a few thousand paths instead of seconds of DVC a project. Any
    doubt (no record, another suite, one changed file) means asking DVC again."""
    try:
        found = json.loads((root / FOUND_CURRENT).read_text())
    except (FileNotFoundError, ValueError):
        return False
    return found.get("projects") == projects and found.get("signature") == _signature(
        root, found.get("paths", [])
    )


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
    import ssl
    import urllib.error
    import urllib.request

    url = remote.options["url"]
    verify = remote.options.get("ssl_verify", "true")  # DVC's option: a bool or a CA bundle
    context = ssl.create_default_context(
        cafile=None if verify.lower() in ("true", "false") else verify
    )
    if verify.lower() == "false":
        context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    try:
        request = urllib.request.Request(url, method="HEAD")
        urllib.request.urlopen(request, timeout=REMOTE_ANSWER_S, context=context).close()
    except urllib.error.HTTPError:
        pass  # it answered
    except OSError as error:  # URLError, a timeout
        why = getattr(error, "reason", None) or error
        raise SuiteRunError(f"DVC remote {remote.name!r} ({url}) does not answer: "
                            f"{why}") from None  # fmt: skip


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
