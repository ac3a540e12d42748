"""What every stage shares: timings, versions, detector pickles."""

from __future__ import annotations

import json
import pickle
import re
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from oodrl.errors import StoreError
from oodrl.fileio import atomic_write_bytes, library_versions
from oodrl.store import rerun_hint

#: Side channel for per-stage wall times; deliberately not a DVC output (timings differ per run).
TIMINGS_DIR = Path(".oodrl") / "timings"
DETECTOR_FORMAT = "oodrl-detector"


@contextmanager
def timed_stage(name: str) -> Iterator[dict[str, Any]]:
    """Record the stage's wall time under .oodrl/timings for run_meta.yaml; the stage may add
    timings of its own to the record it is given (the fit stage: `detector` and `fit_s`)."""
    start = time.perf_counter()
    record: dict[str, Any] = {"stage": name}
    yield record
    TIMINGS_DIR.mkdir(parents=True, exist_ok=True)
    record["wall_s"] = round(time.perf_counter() - start, 3)
    file_name = re.sub(r"[^\w.-]+", "_", name)  # a stage's DVC address holds / : @
    (TIMINGS_DIR / f"{file_name}.json").write_text(json.dumps(record))


def save_detector(path: Path, detector, name: str, params: dict[str, Any]) -> None:
    """Pickle a fitted detector with the versions and params that made it."""
    record = {
        "format": DETECTOR_FORMAT,
        "name": name,
        "params": params,
        "versions": library_versions(),
        "detector": detector,
    }
    atomic_write_bytes(path, pickle.dumps(record, protocol=5))


def load_detector(path: Path, stage: str):
    """Load a pickle written by `save_detector` (only ever from the pipeline's own paths)."""
    hint = rerun_hint(stage)
    if not path.is_file():
        raise StoreError(f"{path}: fitted detector is missing; {hint}.")
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
            f"{path} was written with other versions ({', '.join(changed)}); {hint} to refit.",
            stacklevel=2,
        )
    return record["detector"]
