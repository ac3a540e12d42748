"""Where the suite stands in a change of protocol (SPEC §26), decided from git-tracked files alone.

The target is this code's `PROTOCOL_VERSION`; a project's built version is its committed results'
stamp (reports/results.yaml). A project is

- **current**: its committed locks are what `dvc repro` would keep: every stage is in its lock with
  the command, deps, outs and params values its dvc.yaml gives, every dep's md5 is what produced it
  (another stage's out, or the file itself: a params file, a source, a committed policy), every
  git-tracked output is the file its lock records, and check_params' code stamps are what this
  commit's sources give;
- **pending**: built at an older protocol version; its locks may be stale in any way, its results
  stay, labelled with that version, until a build step rebuilds it;
- **stale**: built at the target and not current, an error the reasons name (file, stamp, key).

Nothing here runs DVC or reads a DVC output (a fresh clone has none): each dep is checked against
what the lock records for the stage that writes it, as `dvc repro --allow-missing` does. The code
stamps are computed (with the pipeline module's own writer, in a scratch directory) only when a
check_params dep differs from its lock: with every one of them unchanged, check_params' outputs are
what its lock records (they are a function of those deps and of dvc.yaml, which `oodrl pipeline
check` holds to the template), and computing them takes tens of seconds a project.
"""

from __future__ import annotations

import hashlib
import json
import os
import posixpath
import re
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from oodrl.errors import ConfigError

RESULTS = "reports/results.yaml"
CURRENT, PENDING, STALE = "current", "pending", "stale"
#: Built at no protocol version: a project without committed results.
NOT_BUILT = 0
#: A results file's stamp, a top-level key (oodrl.metrics.stamp.protocol_stamp).
_STAMP_LINE = re.compile(r"^protocol_version:[ \t]*(.*?)[ \t]*$", re.MULTILINE)
#: The reasons listed per project; more are counted.
MAX_REASONS = 5


@dataclass(frozen=True)
class ProjectState:
    """One project's place in the migration."""

    project: str  # "." or "pipeline/<env>", as oodrl.suite.run.suite_pipelines lists
    status: str  # CURRENT | PENDING | STALE
    built_version: int  # its results' protocol_version (NOT_BUILT: no results)
    reasons: tuple[str, ...] = ()  # for pending/stale: one short line each

    def line(self) -> str:
        """One line: the project, its status and built version, and why."""
        why = f": {'; '.join(self.reasons)}" if self.reasons else ""
        return f"{self.project}: {self.status} (protocol {self.built_version}){why}"


def target_version() -> int:
    from oodrl.metrics.stamp import PROTOCOL_VERSION

    return PROTOCOL_VERSION


def project_states(
    root: Path, projects: Sequence[str] | None = None, *, stamps: bool = False
) -> list[ProjectState]:
    """Each project's state (`projects`, or the suite's projects: the root and every run the
    leaderboard reads). With `stamps`, a project whose check_params deps moved has its code
    stamps computed (tens of seconds a project), so that its reasons name the stages whose code
    changed, or say that none did; without, the moved deps are the reason."""
    from oodrl.suite.pipeline import suite_pipelines

    root = Path(root).resolve()
    known = suite_pipelines(root)
    if projects is None:
        projects = known
    unknown = [p for p in projects if p not in known]
    if unknown:
        raise ConfigError(
            f"{', '.join(unknown)}: not a project of the suite; it has {', '.join(known)}."
        )
    return [_state(root, project, stamps) for project in projects]


def built_version(directory: Path) -> int:
    """The protocol version of a project's committed results (NOT_BUILT if it has none)."""
    import yaml

    from oodrl.metrics.stamp import protocol_version

    path = directory / RESULTS
    if not path.is_file():
        return NOT_BUILT
    # The stamp's top-level line alone: a results file is up to a few MB of YAML (seconds).
    found = _STAMP_LINE.search(path.read_text())
    document = {"protocol_version": yaml.safe_load(found.group(1))} if found else {}
    return protocol_version(document)


def _state(root: Path, project: str, stamps: bool) -> ProjectState:
    directory = root / project
    target = target_version()
    try:
        version = built_version(directory)
    except ValueError as error:
        return ProjectState(project, STALE, NOT_BUILT, (f"{RESULTS}: {error}",))
    if version == NOT_BUILT:
        return ProjectState(project, PENDING, version, (f"no {RESULTS}: never built",))
    if version < target:
        return ProjectState(
            project, PENDING, version, (f"{RESULTS}: protocol {version}, the target is {target}",)
        )
    if version > target:
        return ProjectState(
            project,
            STALE,
            version,
            (f"{RESULTS}: protocol {version}, newer than this code's {target}",),
        )
    reasons = _lock_reasons(root, directory, stamps)
    if len(reasons) > MAX_REASONS:
        reasons = [*reasons[:MAX_REASONS], f"and {len(reasons) - MAX_REASONS} more"]
    return ProjectState(project, STALE if reasons else CURRENT, version, tuple(reasons))


# -- the checks ---------------------------------------------------------------------------------
@dataclass
class _Stage:
    name: str
    file: str  # its dvc.yaml, from the project
    cmd: str
    deps: list[str]
    outs: dict[str, bool]  # path -> git-tracked (cache: false)
    params: dict[str, list[str]]  # params file (from the project) -> keys


def _lock_reasons(root: Path, directory: Path, stamps: bool) -> list[str]:
    from oodrl.suite.pipeline import CHECK_STAGE, CODE_STAMPS

    stages = _stages(directory)
    # A lock keeps the entries of stages its dvc.yaml no longer has (DVC rewrites only the
    # entries of the stages it runs, and its status ignores the others): so does this check.
    names = {stage.name for stage in stages}
    locked = {name: lock for name, lock in _locks(directory).items() if name in names}
    reasons: list[str] = []
    written: dict[str, str] = {}  # out path -> md5, from the locks
    for stage in stages:
        lock = locked.get(stage.name)
        if lock is None:
            reasons.append(f"{stage.file}: stage {stage.name} is not in its lock")
            continue
        for out in lock.get("outs", []):
            written[_norm(out["path"])] = out["md5"]
    check = locked.get(CHECK_STAGE, {})
    moved = [
        dep["path"]
        for dep in check.get("deps", [])
        if _file_md5(directory, dep["path"]) != dep.get("md5")
    ]
    computed: dict[str, str] | None = None
    if moved:
        # A params file first: it is what a maintainer most often edits.
        moved.sort(key=lambda path: not path.endswith((".yaml", ".yml")))
        more = f" and {len(moved) - 1} more" if len(moved) > 1 else ""
        reasons.append(f"{CHECK_STAGE}: {moved[0]}{more} changed since its lock")
        computed = _computed_stamps(directory) if stamps else None
        if computed is not None:
            locked_code = next(
                (o["md5"] for o in check.get("outs", []) if _norm(o["path"]) == CODE_STAMPS), None
            )
            if _tree_md5(computed) == locked_code:
                reasons.append("no code stamp changed with it")
    reasons += _stamp_reasons(locked, written)
    for stage in stages:
        lock = locked.get(stage.name)
        if lock is not None:
            reasons += _stage_reasons(directory, stage, lock, written, computed)
    return reasons


def _stamp_reasons(
    locked: Mapping[str, Mapping[str, Any]], written: Mapping[str, str]
) -> Iterator[str]:
    """The stamps the stages' locks depend on are check_params' outputs: every stamp is some
    stage's dep, so together they hash to the directory check_params' lock records."""
    from oodrl.suite.pipeline import CHECK_STAGE, CODE_STAMPS

    used: dict[str, str] = {}
    for name, lock in locked.items():
        for dep in lock.get("deps", []):
            path = _norm(dep["path"])
            if posixpath.dirname(path) == CODE_STAMPS and name != CHECK_STAGE:
                stamp = posixpath.basename(path)
                if used.setdefault(stamp, dep.get("md5")) != dep.get("md5"):
                    yield f"{name}: code stamp {path} is not the other stages' one"
    if CODE_STAMPS in written and _tree_md5(used) != written[CODE_STAMPS]:
        yield f"the stages' code stamps are not the ones {CHECK_STAGE} last wrote (relock them)"


def _stage_reasons(
    directory: Path,
    stage: _Stage,
    lock: Mapping[str, Any],
    written: Mapping[str, str],
    stamps: Mapping[str, str] | None,
) -> Iterator[str]:
    from oodrl.suite.pipeline import CHECK_STAGE, CODE_STAMPS

    name = stage.name
    if " ".join(str(lock.get("cmd", "")).split()) != " ".join(stage.cmd.split()):
        yield f"{name}: its command is not the locked one"
    deps = {_norm(d["path"]): d.get("md5") for d in lock.get("deps", [])}
    if set(deps) != {_norm(d) for d in stage.deps}:
        yield f"{name}: its deps are not the locked ones"
    outs = {_norm(o["path"]): o.get("md5") for o in lock.get("outs", [])}
    if set(outs) != {_norm(o) for o in stage.outs}:
        yield f"{name}: its outputs are not the locked ones"
    if name != CHECK_STAGE:  # its deps are checked above, as one
        for path, md5 in deps.items():
            if path.startswith(CODE_STAMPS + "/"):
                if stamps is not None:
                    md5_now = stamps.get(posixpath.basename(path))
                    if md5_now != md5:
                        yield f"{name}: code stamp {path} changed"
                        continue
                continue
            if path in written:
                if written[path] != md5:
                    yield f"{name}: {path} is not what its stage wrote"
                continue
            found = _dep_md5(directory, path, written)
            if found is not _UNKNOWN and found != md5:
                yield f"{name}: {path} changed" if found else f"{name}: {path} is missing"
    for path, tracked in stage.outs.items():
        if tracked and (found := _file_md5(directory, path)) != outs.get(_norm(path)):
            yield (
                f"{name}: {path} is not what its lock records"
                if found
                else f"{name}: {path} is missing"
            )
    locked_params = lock.get("params", {})
    for file, keys in stage.params.items():
        values = _params(directory, file)
        recorded = locked_params.get(file, {})
        for key in keys:
            if key not in recorded or _lookup(values, key) != recorded[key]:
                yield f"{name}: param {key} ({file}) is not the locked value"


_UNKNOWN = object()


def _dep_md5(directory: Path, path: str, written: Mapping[str, str]) -> Any:
    """A dep that no stage writes: its md5 now (None if missing), or _UNKNOWN for a directory
    that several stages fill with outputs whose files only the DVC cache lists."""
    full = directory / path
    if full.is_dir():
        inside = {p: md5 for p, md5 in written.items() if p.startswith(path + "/")}
        if inside:
            if any(md5.endswith(".dir") for md5 in inside.values()):
                return _UNKNOWN
            return _tree_md5({p[len(path) + 1 :]: md5 for p, md5 in inside.items()})
        return _dir_md5(full)
    if not full.exists():
        inside = {p: md5 for p, md5 in written.items() if p.startswith(path + "/")}
        if inside:  # a filled directory missing in a fresh clone: DVC forgives it
            return _UNKNOWN
        return None
    return _file_md5(directory, path)


def _computed_stamps(directory: Path) -> dict[str, str]:
    """Stamp file name -> md5, as check_params would write them from this commit's sources."""
    from oodrl.suite.pipeline import PARAMS_FILE, write_stamps

    with tempfile.TemporaryDirectory(prefix="oodrl-stamps-") as scratch:
        written = write_stamps(directory / "dvc.yaml", directory / PARAMS_FILE, Path(scratch))
        return {p.name: hashlib.md5(p.read_bytes()).hexdigest() for p in written}


# -- reading dvc.yaml and dvc.lock ----------------------------------------------------------------
def _pipeline_files(directory: Path) -> list[Path]:
    from oodrl.io.layout import DETECTOR_PIPELINES

    return [directory / "dvc.yaml", *sorted((directory / DETECTOR_PIPELINES).glob("*/dvc.yaml"))]


def _locks(directory: Path) -> dict[str, dict[str, Any]]:
    import yaml

    stages: dict[str, dict[str, Any]] = {}
    for path in _pipeline_files(directory):
        lock = path.with_suffix(".lock")
        if lock.is_file():
            document = yaml.load(lock.read_text(), Loader=_loader()) or {}
            for name, stage in (document.get("stages") or {}).items():
                stages[f"{path.parent.relative_to(directory).as_posix()}:{name}"] = stage
    return {_key(name): stage for name, stage in stages.items()}


def _key(name: str) -> str:
    """A stage's name in the project: `name` in its dvc.yaml, `dir:name` in another's."""
    folder, _, stage = name.partition(":")
    return stage if folder == "." else name


def _stages(directory: Path) -> list[_Stage]:
    """Every stage instance of a project's dvc.yaml files, foreach expanded, paths from the
    project's directory (a detector file's stages run there: wdir)."""
    import yaml

    found = []
    for path in _pipeline_files(directory):
        document = yaml.load(path.read_text(), Loader=_loader()) or {}
        folder = path.parent.relative_to(directory).as_posix()
        wdir = folder
        for name, spec in (document.get("stages") or {}).items():
            if "foreach" in spec:
                items = spec["foreach"]
                if isinstance(items, str):
                    items = _lookup(_params(directory, "params.yaml"), items.strip("${}"))
                bodies = [(f"{name}@{item}", spec["do"], str(item)) for item in items]
            else:
                bodies = [(name, spec, None)]
            for stage_name, body, item in bodies:
                base = posixpath.normpath(posixpath.join(wdir, body.get("wdir", ".")))

                def at(value: str, base: str = base, item: str | None = item) -> str:
                    text = value.replace("${item}", item) if item is not None else value
                    return _norm(posixpath.join(base, text))

                outs: dict[str, bool] = {}
                for kind in ("outs", "metrics", "plots"):
                    for out in body.get(kind) or []:
                        out_path, options = _entry(out)
                        outs[at(out_path)] = options.get("cache", True) is False
                params: dict[str, list[str]] = {}
                for entry in body.get("params") or []:
                    named = {"params.yaml": [entry]} if isinstance(entry, str) else entry
                    for file, keys in named.items():
                        params.setdefault(at(file), []).extend(
                            key.replace("${item}", item) if item is not None else key
                            for key in keys
                        )
                cmd = str(body["cmd"])
                found.append(
                    _Stage(
                        stage_name if folder == "." else f"{folder}:{stage_name}",
                        path.relative_to(directory).as_posix(),
                        cmd.replace("${item}", item) if item is not None else cmd,
                        [at(_entry(d)[0]) for d in body.get("deps") or []],
                        outs,
                        params,
                    )
                )
    return found


def _entry(entry: Any) -> tuple[str, dict[str, Any]]:
    if isinstance(entry, str):
        return entry, {}
    ((path, options),) = entry.items()
    return path, options or {}


def _norm(path: str) -> str:
    return posixpath.normpath(path)


def _lookup(values: Any, key: str) -> Any:
    for part in key.split("."):
        if not isinstance(values, Mapping) or part not in values:
            return _UNKNOWN
        values = values[part]
    return values


@cache
def _params_cached(path: Path, signature: tuple[int, int]) -> Any:
    import yaml

    return yaml.load(path.read_text(), Loader=_loader())


def _params(directory: Path, file: str) -> Any:
    path = (directory / file).resolve()
    if not path.is_file():
        return {}
    found = path.stat()
    return _params_cached(path, (found.st_size, found.st_mtime_ns))


@cache
def _loader():
    """PyYAML's fast loader reading floats as YAML 1.2 does (DVC's ruamel): `5e-05` is a number
    in a lock as in a params file, not the string YAML 1.1 makes of it."""
    import yaml

    class Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
        pass

    number = r"[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)(?:[eE][-+]?[0-9]+)?"
    special = r"[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)"
    floats = re.compile(rf"^(?:(?={number}$)(?=.*[.eE]){number}|{special})$")
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", floats, list("-+0123456789."))
    return Loader


# -- DVC's md5s ---------------------------------------------------------------------------------
@cache
def _md5_cached(path: Path, signature: tuple[int, int, int]) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


def _file_md5(directory: Path, path: str) -> str | None:
    """DVC's md5 of a file (of its bytes) or directory, None if there is none."""
    full = Path(os.path.normpath(directory / path))
    if full.is_dir():
        return _dir_md5(full)
    try:
        found = full.stat()
    except FileNotFoundError:
        return None
    return _md5_cached(full, (found.st_size, found.st_mtime_ns, found.st_ino))


def _dir_md5(directory: Path) -> str:
    """DVC's md5 of a directory (`<md5 of its listing>.dir`), bytecode left out as the projects'
    .dvcignore says."""
    from oodrl.suite.pipeline import BYTECODE_DIR

    files = {}
    for path in directory.rglob("*"):
        relative = path.relative_to(directory)
        if path.is_file() and BYTECODE_DIR not in relative.parts and path.suffix != ".pyc":
            files[relative.as_posix()] = _file_md5(directory, relative.as_posix())
    return _tree_md5(files)


def _tree_md5(files: Mapping[str, str | None]) -> str:
    """DVC's directory hash from relative path -> md5: md5 of the sorted JSON listing."""
    listing = [{"md5": md5, "relpath": path} for path, md5 in sorted(files.items())]
    return hashlib.md5(json.dumps(listing, sort_keys=True).encode()).hexdigest() + ".dir"


def check(root: Path, *, stamps: bool = False) -> list[ProjectState]:
    """Every project's state, or a ConfigError naming each stale project and why, one line a
    project: a migration (projects pending at an older protocol) passes, nothing else does."""
    states = project_states(root, stamps=stamps)
    stale = [state for state in states if state.status == STALE]
    if stale:
        lines = "\n".join(state.line() for state in stale)
        raise ConfigError(
            f"{len(stale)} of {len(states)} projects are stale, built at protocol "
            f"{target_version()} and not current (rebuild them: `oodrl suite run --only "
            f"{','.join(state.project for state in stale)}`; a relock alone if only check_params "
            f"moved):\n{lines}"
        )
    return states


def summary(states: Sequence[ProjectState]) -> str:
    """ "22 projects: 15 current, 7 pending at protocol 3 (target 4)"."""
    current = sum(state.status == CURRENT for state in states)
    pending = [state for state in states if state.status == PENDING]
    older = sorted({state.built_version for state in pending})
    built = [f"protocol {', '.join(str(v) for v in older if v != NOT_BUILT)}"] if any(older) else []
    built += ["never built"] if NOT_BUILT in older else []
    text = f"{len(states)} projects at target protocol {target_version()}: {current} current"
    if pending:
        text += f", {len(pending)} pending ({'; '.join(built)})"
    return text
