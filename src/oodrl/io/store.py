"""Zarr v3 stores of trajectory sets and score arrays, and fitted-detector files (SPEC §9).

Each store is one file: a Zarr v3 hierarchy packed in an uncompressed ZIP archive (zarr's
`ZipStore` reads it; open one with `zarr.open_group(zarr.storage.ZipStore(path, mode="r"))`).
A directory store has a few directories and files per array, and DVC walks every one of them
for every stage that reads or writes the store, on every `dvc repro`, `dvc status` and
`dvc exp run`: one file per store is one file-state lookup.

Every store is written to a temporary sibling path and renamed into place, so a killed
stage never leaves a half-written store. Arrays are sharded (one ZIP entry per array), zstd
compressed, and every array's SHA-256 is recorded in the group attributes: a truncated or
tampered store is detected on read instead of silently yielding fill values. Nothing
time- or host-dependent is written (ZIP entries in sorted order with a fixed date), so the
same data gives byte-identical stores.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
import warnings
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from oodrl.core.trajectory import STEP_FIELDS, TrajectorySet
from oodrl.errors import StoreError

TRAJECTORY_FORMAT = "oodrl-trajectories"
SWEEP_FORMAT = "oodrl-sweep"
SCORES_FORMAT = "oodrl-scores"
DETECTOR_FORMAT = "oodrl-detector"
FORMAT_VERSION = 1

_SET_ARRAYS = (*STEP_FIELDS, "episode_index", "seeds", "labels")


def canonical(value: Any) -> Any:
    """JSON-ready, key-sorted, numpy-free copy of attributes (stable bytes on disk)."""
    if isinstance(value, Mapping):
        return {str(k): canonical(value[k]) for k in sorted(value, key=str)}
    if isinstance(value, list | tuple):
        return [canonical(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def _digest(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def _write_arrays(group, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> None:
    import zarr
    from zarr.codecs import ZstdCodec

    checksums = {}
    for name in sorted(arrays):
        data = np.ascontiguousarray(arrays[name])
        zarr.create_array(
            group.store,
            name=f"{group.path}/{name}" if group.path else name,
            data=data,
            # One shard file per array holding one chunk: stages read whole arrays, and
            # per-episode inner chunks made every read about 4x slower.
            chunks=data.shape,
            shards=data.shape,
            compressors=ZstdCodec(level=3, checksum=True),
            zarr_format=3,
        )
        checksums[name] = _digest(data)
    group.attrs.update(canonical({**attrs, "checksums": checksums}))


def write_store(path: Path, groups: Mapping[str, tuple[Mapping[str, np.ndarray], Mapping]]) -> None:
    """Write `{group path ('' = root): (arrays, attrs)}` atomically to the file `path`."""
    import zarr

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Temporary siblings left by a killed earlier run are removed first.
    for stale in path.parent.glob(f".{path.name}.tmp-*"):
        _remove(stale)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    packed = path.with_name(f"{tmp.name}.zip")
    try:
        root = zarr.open_group(str(tmp), mode="w", zarr_format=3)
        for name in sorted(groups):
            arrays, attrs = groups[name]
            group = root if name == "" else root.require_group(name)
            _write_arrays(group, arrays, attrs)
        _pack(tmp, packed)
        if path.is_dir():  # a directory store written by an earlier version
            shutil.rmtree(path)
        os.replace(packed, path)
    finally:
        _remove(tmp)
        _remove(packed)


# A fixed date and mode: ZipFile would stamp each entry with the time it was written.
_ENTRY_DATE = (1980, 1, 1, 0, 0, 0)
_ENTRY_MODE = 0o100644 << 16
_UNIX = 3


def _pack(directory: Path, archive: Path) -> None:
    """The files under `directory` as an uncompressed ZIP whose bytes depend on them only."""
    names = sorted(p.relative_to(directory).as_posix() for p in directory.rglob("*") if p.is_file())
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_STORED) as out:
        for name in names:
            entry = zipfile.ZipInfo(name, _ENTRY_DATE)
            entry.external_attr = _ENTRY_MODE
            entry.create_system = _UNIX
            out.writestr(entry, (directory / name).read_bytes())


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def restore_hint(path: Path | str, stage: str | None) -> str:
    """How to mend a missing or broken output: the one hint every error message uses (SPEC §22).

    A committed output is restored, never recomputed: `dvc checkout` copies its bytes from the
    cache in a second (the outputs a failed stage deleted come back with it), `dvc pull` fetches
    them where this cache lacks them. Rebuilding comes last, for an output no cache holds: `-s`
    re-runs that stage alone (plain `-f` would force every upstream stage too, train_policy
    included: 13 minutes, and it overwrites the committed policy).
    """
    target = project_path(Path(path))
    rebuild = f"`dvc repro -s -f {stage_address(stage)}`" if stage else "the stage that writes it"
    return (
        f"restore it with `dvc checkout --force {target}` (`dvc pull {target}` where this cache "
        f"lacks it); only if no cache holds it, rebuild it with {rebuild}"
    )


def _project_root(here: Path) -> Path:
    return next((d for d in (here, *here.parents) if (d / ".dvc").is_dir()), here)


def project_path(path: Path) -> str:
    """`path` as DVC names it from the repository root (a stage runs in its pipeline's
    directory, maybe pipeline/<env>); as given when it lies outside the repository."""
    here = Path.cwd()
    absolute = path if path.is_absolute() else here / path
    try:
        return absolute.relative_to(_project_root(here)).as_posix()
    except ValueError:
        return path.as_posix()


def stage_address(stage: str) -> str:
    """`stage` ('collect_eval', or 'detectors/<d>/dvc.yaml:fit') as DVC names it from the
    repository root: a stage command runs in its pipeline's directory, maybe pipeline/<env>."""
    here = Path.cwd()
    root = _project_root(here)
    if root == here:
        return stage
    file, _, name = stage.rpartition(":")
    return f"{here.relative_to(root).as_posix()}/{file or 'dvc.yaml'}:{name}"


def _open_group(path: Path, expected_format: str, stage: str | None):
    """The root group and the open ZipStore (close it once the arrays are read)."""
    import zarr
    from zarr.storage import ZipStore

    path = Path(path)
    if path.is_dir():
        raise StoreError(
            f"{path}: a directory store from an older oodrl (stores are now single ZIP "
            f"files); {restore_hint(path, stage)}."
        )
    if not path.is_file():
        raise StoreError(f"{path}: store is missing; {restore_hint(path, stage)}.")
    try:
        store = ZipStore(path, mode="r")
        root = zarr.open_group(store, mode="r", zarr_format=3)
        found = root.attrs.get("format")
    except Exception as error:  # zipfile and zarr raise many kinds on damaged files
        raise StoreError(
            f"{path}: unreadable store ({error}); {restore_hint(path, stage)}."
        ) from None
    if found != expected_format:
        store.close()
        raise StoreError(
            f"{path}: not an {expected_format} store (format {found!r}); "
            f"{restore_hint(path, stage)}."
        )
    return root, store


def _read_arrays(group, path: Path, stage: str | None) -> dict[str, np.ndarray]:
    checksums = dict(group.attrs.get("checksums", {}))
    arrays = {}
    for name, digest in checksums.items():
        try:
            data = np.asarray(group[name][...])
        except Exception as error:
            raise StoreError(
                f"{path}: array '{group.path}/{name}' is unreadable ({error}); "
                f"{restore_hint(path, stage)}."
            ) from None
        if _digest(data) != digest:
            raise StoreError(
                f"{path}: array '{group.path}/{name}' is truncated or corrupt (checksum "
                f"mismatch); {restore_hint(path, stage)}."
            )
        arrays[name] = data
    return arrays


def read_store(
    path: Path, expected_format: str, stage: str | None = None
) -> dict[str, tuple[dict[str, np.ndarray], dict]]:
    """Read every group of a store written by `write_store`, verifying checksums."""
    root, store = _open_group(path, expected_format, stage)
    try:
        groups = {"": root}
        for name, group in root.groups():
            groups[name] = group
        return {
            name: (
                _read_arrays(group, Path(path), stage),
                json.loads(json.dumps(dict(group.attrs))),
            )
            for name, group in sorted(groups.items())
        }
    finally:
        store.close()


# -- trajectory sets ---------------------------------------------------------------------------
def _set_arrays(tset: TrajectorySet) -> dict[str, np.ndarray]:
    return {n: getattr(tset, n) for n in _SET_ARRAYS if getattr(tset, n) is not None}


def _set_from(arrays: dict[str, np.ndarray], attrs: dict) -> TrajectorySet:
    attrs = {k: v for k, v in attrs.items() if k not in ("checksums", "format", "version")}
    fields = {n: arrays[n] for n in _SET_ARRAYS if n in arrays}
    return TrajectorySet(**fields, attrs=attrs)


def write_trajectories(path: Path, tset: TrajectorySet) -> None:
    attrs = {**tset.attrs, "format": TRAJECTORY_FORMAT, "version": FORMAT_VERSION}
    write_store(path, {"": (_set_arrays(tset), attrs)})


def read_trajectories(path: Path, stage: str | None = None) -> TrajectorySet:
    arrays, attrs = read_store(path, TRAJECTORY_FORMAT, stage)[""]
    return _set_from(arrays, attrs)


def severity_key(severity: float) -> str:
    """Group name of one sweep severity: 'severity_0.4'."""
    return f"severity_{float(severity)!r}"


def write_sweep(path: Path, sets: Mapping[float, TrajectorySet], attrs: Mapping[str, Any]) -> None:
    """One group per severity, so a sweep over the grid is one store (one DVC output)."""
    severities = sorted(float(s) for s in sets)
    groups = {
        "": (
            {},
            {**attrs, "format": SWEEP_FORMAT, "version": FORMAT_VERSION, "severities": severities},
        ),
    }
    for severity in severities:
        tset = sets[severity]
        groups[severity_key(severity)] = (_set_arrays(tset), dict(tset.attrs))
    write_store(path, groups)


def read_sweep(path: Path, stage: str | None = None) -> dict[float, TrajectorySet]:
    groups = read_store(path, SWEEP_FORMAT, stage)
    return {float(s): _set_from(*groups[severity_key(s)]) for s in groups[""][1]["severities"]}


def read_tier_sets(path: Path, stage: str | None = None) -> tuple[dict[float, TrajectorySet], dict]:
    """A tier store (written as a sweep by collect_tiers): its sets by severity, and its root
    attributes (tiers: tier -> severity, unreachable tiers, mode)."""
    groups = read_store(path, SWEEP_FORMAT, stage)
    attrs = groups[""][1]
    return {float(s): _set_from(*groups[severity_key(s)]) for s in attrs["severities"]}, attrs


# -- score arrays ------------------------------------------------------------------------------
def write_scores(
    path: Path, groups: Mapping[str, Mapping[str, np.ndarray]], attrs: Mapping[str, Any]
) -> None:
    """Scores of one detector on one or more trajectory sets: group name -> arrays (N, T)."""
    tree = {"": ({}, {**attrs, "format": SCORES_FORMAT, "version": FORMAT_VERSION})}
    for name, arrays in groups.items():
        tree[name] = (dict(arrays), {})
    write_store(path, tree)


def read_scores(
    path: Path, stage: str | None = None
) -> tuple[dict[str, dict[str, np.ndarray]], dict]:
    groups = read_store(path, SCORES_FORMAT, stage)
    root_attrs = {k: v for k, v in groups[""][1].items() if k not in ("checksums",)}
    return {name: arrays for name, (arrays, _) in groups.items() if name}, root_attrs


# -- fitted detectors --------------------------------------------------------------------------
def save_detector(path: Path, detector, name: str, params: Mapping[str, Any]) -> None:
    """Pickle a fitted detector with the versions and params that made it."""
    from oodrl.io.fileio import atomic_write_bytes, library_versions

    record = {
        "format": DETECTOR_FORMAT,
        "name": name,
        "params": dict(params),
        "versions": library_versions(),
        "detector": detector,
    }
    atomic_write_bytes(path, pickle.dumps(record, protocol=5))


def load_detector(path: Path, stage: str | None):
    """Load a pickle written by `save_detector` (only ever from the pipeline's own paths).

    A plugin detector's pickle names its module beside params.yaml, which the `oodrl` command
    finds only with the project directory on sys.path, so it is added first.
    """
    from oodrl.io.fileio import library_versions
    from oodrl.registry import add_project_dir_to_path

    path = Path(path)
    hint = restore_hint(path, stage)
    if not path.is_file():
        raise StoreError(f"{path}: fitted detector is missing; {hint}.")
    add_project_dir_to_path()
    try:
        record = pickle.loads(path.read_bytes())
    except Exception as error:  # any unpickling failure means a corrupt or foreign file
        raise StoreError(f"{path}: not a readable oodrl detector ({error}); {hint}.") from None
    if not isinstance(record, dict) or record.get("format") != DETECTOR_FORMAT:
        raise StoreError(f"{path}: not an oodrl detector file; {hint}.")
    saved, current = record["versions"], library_versions()
    changed = [f"{k} {saved[k]} -> {current.get(k)}" for k in saved if saved[k] != current.get(k)]
    if changed:
        warnings.warn(
            f"{path} was written with other versions ({', '.join(changed)}); refit it with "
            f"`dvc repro -s -f {stage_address(stage) if stage else 'fit'}`.",
            stacklevel=2,
        )
    return record["detector"]
