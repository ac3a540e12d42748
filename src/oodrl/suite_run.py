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

Two ways to share, chosen by what is configured:
- a DVC remote (the root project's default remote, at any config level): each task runs
  `dvc repro --pull` and `dvc push --run-cache`; the head pulls. The remote reaches every project
  and every node through a DVC *system*-level config file in a temporary directory
  (DVC_SYSTEM_CONFIG_DIR), so no file of the checkout or of its projects is edited. On Ray this
  is the only way (the nodes share nothing else).
- none, with local workers: the clones use the head's cache directory itself (each clone's
  git-ignored .dvc/config.local), so one machine needs no remote and nothing is copied twice.
"""

from __future__ import annotations

import json
import math
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from oodrl.errors import ConfigError, OodrlError

#: A task whose node dies runs again on another node up to this many times.
RAY_MAX_RETRIES = 3


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


def suite_pipelines(root: Path) -> list[str]:
    """The root's pipeline (the paper's default) and every run the suite's leaderboard reads (the
    pipelines whose results its generated dvc.yaml depends on), relative to the root ('.' is the
    root's own). A pipeline `oodrl new` made, or a policy not yet in `oodrl.suite.MORE_POLICIES`,
    is not the suite's: build it with `dvc repro` in its directory."""
    import yaml

    from oodrl.pipeline import SUITE_DIR

    stage = yaml.safe_load((root / SUITE_DIR / "dvc.yaml").read_text())["stages"]["leaderboard"]
    results = [Path(d) for d in stage["deps"] if d.endswith("/reports/results.yaml")]
    runs = {(root / SUITE_DIR / d).resolve().parent.parent.relative_to(root) for d in results}
    return [".", *sorted(r.as_posix() for r in runs)]


# -- one task: one pipeline in its own clone ----------------------------------------------------
def build_pipeline(
    bundle: bytes, commit: str, pipeline: str, remote: Remote | None, shared_cache: str | None
) -> tuple[float, tuple[str, ...], dict[str, bytes]]:
    """Clone `commit` from a git bundle, `dvc repro` the pipeline's project there (pulling what
    the remote has), push its outputs and run-cache; the seconds taken, the stages that ran and
    the `checkout_files` of the built project.

    The clone is a temporary directory that goes with the task. A task killed with its node
    leaves nothing in the head's checkout; the remote and the cache receive whole objects only
    (written aside, then renamed) and a run-cache entry only once its stage has finished."""
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="oodrl-suite-") as scratch, _dvc_config(remote) as env:
        clone = Path(scratch) / "repo"
        (Path(scratch) / "head.bundle").write_bytes(bundle)
        _run(Path(scratch), env, "git", "clone", "-q", "--no-checkout", "head.bundle", "repo")
        _run(clone, env, "git", "-c", "advice.detachedHead=false", "checkout", "-q", commit)
        project = clone / pipeline
        if shared_cache:
            _run(project, env, "dvc", "cache", "dir", "--local", shared_cache)
        done = _run(project, env, "dvc", "repro", *(["--pull"] if remote else []))
        if remote:
            _run(project, env, "dvc", "push", "-q")
            _run(project, env, sys.executable, "-c", PUSH_RUN_CACHE)
        files = checkout_files(project)
    return time.perf_counter() - start, ran_stages(done.stdout), files


def checkout_files(project: Path) -> dict[str, bytes]:
    """What a built project holds beyond the cache, by path relative to it: the dvc.lock of each
    of its DVC files and every output DVC does not cache (metrics.json, the policy). With these
    written, `dvc checkout` makes another checkout of the commit the built project."""
    from dvc.repo import Repo

    with Repo(str(project)) as repo:
        stages = repo.index.stages
        paths = {Path(stage.dvcfile.path).with_suffix(".lock") for stage in stages}
        paths |= {Path(out.fs_path) for stage in stages for out in stage.outs if not out.use_cache}
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

    with tempfile.TemporaryDirectory(prefix="oodrl-dvc-config-") as directory:
        config = ConfigObj(os.path.join(system_config_dir(), "config"))
        config.filename = os.path.join(directory, "config")
        config.setdefault("core", {})["remote"] = remote.name
        config[f'remote "{remote.name}"'] = remote.options
        config.write()
        yield {"DVC_SYSTEM_CONFIG_DIR": directory}


def _run(cwd: Path, env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    """One git or DVC command; a failure is a SuiteRunError carrying DVC's own error line."""
    command = [sys.executable, "-m", "dvc", *args[1:]] if args[0] == "dvc" else list(args)
    repo = Path(_git_root(cwd))
    environment = {**task_environment(repo), **env}
    done = subprocess.run(command, cwd=cwd, env=environment, capture_output=True, text=True)
    if done.returncode != 0:
        lines = [line.strip() for line in (done.stderr + done.stdout).splitlines() if line.strip()]
        why = next((line for line in lines if line.startswith(("ERROR", "error"))), None)
        raise SuiteRunError(f"`{' '.join(args[:2])}` in {cwd.name}: {why or (lines or [''])[-1]}")
    return done


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
    if ray_address is not None:
        _check_reachable(ray_address)
    from oodrl.fileio import atomic_write_bytes, atomic_write_text
    from oodrl.pipeline import SUITE_DIR

    pipelines = suite_pipelines(root)
    projects = [*pipelines, SUITE_DIR.as_posix()]
    if _unchanged_since_found_current(root, projects):
        echo(f"suite: all {len(projects)} projects are up to date (no file DVC checks changed "
             f"since they were found so); nothing to run")  # fmt: skip
        return SuiteRun((), (), time.perf_counter() - start)
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
    remote = default_remote(root)
    if remote is not None:
        _check_writable(root, remote)
    if ray_address is not None and remote is None:
        raise ConfigError("--ray: the nodes share stages through a DVC remote and none is "
                          "configured; add one every node can reach (README: a shared DVC "
                          "remote), e.g. `dvc remote add -d lab s3://bucket/oodrl`.")  # fmt: skip
    job = {
        "bundle": _bundle(root),
        "commit": _run(root, {}, "git", "rev-parse", "HEAD").stdout.strip(),
        "remote": remote,
        "shared_cache": None if ray_address else _cache_dir(root),
    }
    if ray_address is None:
        tasks = _local_tasks(root, pipelines, job, workers, echo)
    else:
        tasks = _ray_tasks(root, pipelines, job, ray_address, echo)
    runs: list[PipelineRun] = []
    last_task_ended = start
    with _dvc_config(remote) as env:

        def restore(built: PipelineRun) -> float:
            """The task's locks and uncached outputs written, every other output checked out
            from the cache (pulled first from a remote): what `dvc repro` would leave, without
            DVC's per-stage run-cache lookups. `--force` replaces outputs as `dvc repro` does."""
            began = time.perf_counter()
            project = root / built.pipeline
            for name, content in built.files.items():
                atomic_write_bytes(project / name, content)
            _run(project, env, "dvc", "pull" if remote else "checkout", "--force", "-q")
            return time.perf_counter() - began

        # Restored as each task ends, while the others run: projects are separate DVC
        # workspaces. A later failure leaves the projects restored so far consistent (each
        # one's locks and outputs are those of a finished `dvc repro`), the others untouched.
        for built in tasks:
            last_task_ended = time.perf_counter()
            runs.append(replace(built, files={}, restore_seconds=restore(built)))
        began = time.perf_counter()
        done = _run(root / SUITE_DIR, env, "dvc", "repro", *(["--pull"] if remote else []))
        head_ran = [f"{SUITE_DIR.as_posix()}:{stage}" for stage in ran_stages(done.stdout)]
        leaderboard_seconds = time.perf_counter() - began
    end = time.perf_counter()
    after = end - last_task_ended
    echo(f"suite: done in {end - start:.1f} s, {after:.1f} s of them after the last task; "
         f"the head ran {', '.join(head_ran) or 'nothing'}")  # fmt: skip
    return SuiteRun(tuple(runs), tuple(head_ran), end - start, after, leaderboard_seconds)


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

    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = {
            pool.submit(task, pipeline): pipeline for pipeline in _longest_first(root, pipelines)
        }
        for future in as_completed(futures):
            if future.exception() is not None:
                for pending in futures:
                    pending.cancel()  # no new pipeline starts; running ones finish
                raise SuiteRunError(f"{futures[future]}: {future.exception()}")
            yield future.result()


def _longest_first(root: Path, pipelines: list[str]) -> list[str]:
    """Longest first, so that a long pipeline never starts last: by the stage wall time of its
    last build in the checkout (`total_stage_wall_s` of its reports/run_meta.yaml); a pipeline
    with none (never built here) counts as the longest. Ties keep the suite's order."""

    def last_build_seconds(pipeline: str) -> float:
        meta = root / pipeline / "reports" / "run_meta.yaml"
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
                raise SuiteRunError(f"{names[ready]}: {cause or error}") from None
            yield _finished(echo, names[ready], node, tuple(built))
    finally:
        ray.shutdown()


def _ray_build(**job) -> tuple[float, tuple[str, ...], dict[str, bytes], str]:
    import ray

    return *build_pipeline(**job), ray.get_runtime_context().get_node_id()


def _check_reachable(address: str) -> None:
    """An address nothing answers at is one line now, not a minute of Ray's own retries."""
    match = re.fullmatch(r"(?:ray://)?([^:/]+):(\d+)", address)
    if match is None:
        raise ConfigError(f"--ray: {address!r} is not HOST:PORT (the address `ray start "
                          f"--head` prints, e.g. 10.0.0.5:6379).")  # fmt: skip
    try:
        socket.create_connection((match[1], int(match[2])), timeout=5).close()
    except OSError as error:
        raise SuiteRunError(f"--ray: no Ray cluster answers at {address} "
                            f"({error.strerror or error}).") from None  # fmt: skip


def _up_to_date(project: Path) -> bool:
    """Whether `dvc repro` of a project would run nothing (every lock and output current)."""
    command = [sys.executable, "-m", "dvc", "status", "--quiet"]
    env = task_environment(Path(_git_root(project)))
    return subprocess.run(command, cwd=project, env=env, capture_output=True).returncode == 0


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


def _cache_dir(root: Path) -> str:
    """The DVC cache every project of the checkout uses (the root's, SUBREPO_FILES)."""
    return _run(root, {}, "dvc", "cache", "dir").stdout.strip()


def _check_writable(root: Path, remote: Remote) -> None:
    """A remote that refuses is one line before any task starts, not after each has run:
    write and delete a probe file at its top. (A directory remote may not exist yet: DVC
    makes it on the first push; a bucket is never created.)"""
    import uuid

    from dvc.repo import Repo

    try:
        with Repo(str(root)) as repo:
            target = repo.cloud.get_remote(remote.name)
            if target.fs.protocol == "local":
                target.fs.makedirs(target.path, exist_ok=True)
            probe = target.fs.join(target.path, f"oodrl-suite-probe-{uuid.uuid4().hex}")
            target.fs.pipe_file(probe, b"")
            target.fs.rm_file(probe)
    except Exception as error:  # noqa: BLE001 - any refusal, whatever the filesystem raises
        why = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise SuiteRunError(f"DVC remote {remote.name!r} ({remote.options.get('url')}) "
                            f"refuses a write: {why}") from None  # fmt: skip


def _bundle(root: Path) -> bytes:
    """The head's commit and its history in one file: a task on any node clones from it."""
    with tempfile.TemporaryDirectory(prefix="oodrl-suite-") as scratch:
        path = Path(scratch) / "head.bundle"
        _run(root, {}, "git", "bundle", "create", "-q", str(path), "HEAD")
        return path.read_bytes()
