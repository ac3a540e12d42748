"""One detector's cells, and their merge (protocol 4's stage split, SPEC §23).

A per-detector stage, `cells`, computes only that detector's cells
(`oodrl.stages.cells.detector_cells`: its
results records, its sweep summaries and its tier records) from its own scores,
`scores/<detector>/`, and the shared impact documents, and writes them to a file of its own
(`write_cells`); the environment's `metrics` and `tier_metrics` stages merge every detector's
cells (`read_all_cells`, then `oodrl.metrics.results.assemble_results` and
`oodrl.metrics.tiers.assemble_tier_results`) into the files people read —
reports/results.yaml, sweep_results.yaml, metrics.json, tables.md, tier_results.json and
reports/tiers/ — byte for byte as one computation over every detector's scores writes them
(`oodrl.metrics.results.compute_results`; tests/metrics/test_cells.py). Adding a detector
computes nothing of the others.

Why the split keeps every byte:

- The bootstraps share no random stream across detectors. Every summary of both stages is
  `oodrl.metrics.aggregate.summarise(..., seed=params.seed)`, whose replicates come from a fresh
  `numpy.random.default_rng(seed)` per metric (`oodrl.metrics.bootstrap.bootstrap_indices`): the
  draws depend only on (seed, N, n_boot), never on which detectors, cells or metrics were
  summarised before. The null baseline is computed per detector from its own clean scores
  (`results._null_summary`), the operating points and their Clopper-Pearson intervals have no
  randomness, and the per-stream threshold comes from the detector's own calibration streams.
  So `results._detector_results` and `tiers.detector_records`, called here one detector at a
  time exactly as `compute_results` / `compute_tier_results` call them in `ordered_map`, give
  the same numbers, and both assemble them with the same functions (`assemble_results`,
  `assemble_tier_results`).
- What is global across detectors is done in the merge, with today's functions or today's
  assembly steps: the records' sort, the injectors' modes (`dict.update` in detector order), the
  sweep's insertion order (injector, then severity as the first detector lists it, then
  detector: `render_tables` follows it), `nominal_false_alarms` and the uncertified detectors
  (from params alone), the protocol stamp (the hash of all params), the tier results' false-alarm
  audit (`tiers._false_alarm_audit`), impact summaries and minimum detectable impacts
  (`tiers._minimum_detectable_impact`, per (detector, fault) from the merged records), and every
  table and figure (the best-per-anomaly ranks and the headline means need all detectors).
- YAML anchors: results.yaml writes the summary that a detector's null records of both modes
  share as one anchor (`ResultRecord.as_dict`). `read_cells` gives a detector's null records
  one summary object again, so the object graph — and so the YAML — is today's. (The tier
  results are JSON, which has no anchors: a shared object is written where it appears.)

The cells file is JSON (`write_cells`): canonical text that holds no time, host or path; every
value of a cell is a str, int, float, bool, None, list or dict, which JSON keeps exactly (floats
by their shortest repr, ints apart from floats). Two things JSON lacks are encoded: a dict whose
keys are not all strings (a detection curve's int K, a sweep's float severity) as
`{"__items__": [[key, value], ...]}`, and the null records' shared summary, written with the
first of them only and shared again on reading. A value of any other type (a tuple, a numpy
scalar) and any other object met twice are refused rather than changed on the way.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from oodrl.config import Params
from oodrl.errors import ContractError, StoreError
from oodrl.metrics.results import ResultRecord, Summary

#: The cells file's format name and version (`write_cells`).
CELLS_FORMAT = "oodrl-cells"
CELLS_VERSION = 1
#: The key that marks a dict with non-string keys in a cells file.
ITEMS = "__items__"
#: What a null record but the first of a detector holds for its summary: the first's.
NULL_METRICS = "same as the first null record's"
_SCALARS = (bool, int, float, str)
_KEYS = (str, int, float)


@dataclass(frozen=True)
class DetectorCells:
    """Everything the metrics and tier_metrics stages compute for one detector.

    `records`, `sweep` and `modes` as `oodrl.metrics.results._detector_results` returns them
    (the anomaly records in injector order, then the null records, one per mode; the sweep
    summaries by (injector, severity) in injector, then severity order; each injector's mode);
    `tier_records` as `oodrl.metrics.tiers.detector_records` returns them.
    """

    detector: str
    records: list[ResultRecord]
    sweep: dict[tuple[str, float], Summary]
    modes: dict[str, str]
    tier_records: list[dict[str, Any]]


# -- the cells file ----------------------------------------------------------------------------
def _encode(value: Any, where: str, seen: set[int]) -> Any:
    """A JSON-exact copy of `value` (see the module's docstring), or ContractError.

    `seen`: the ids of the lists and dicts encoded so far. A container met twice is refused:
    YAML writes a shared object once, as an anchor, and a cells file would part it.
    """
    # Exact types: a subclass (numpy.float64 is a float) would not come back as itself.
    if value is None or type(value) in _SCALARS:
        return value
    if type(value) in (list, dict):
        if id(value) in seen:
            raise ContractError(
                f"{where}: an object shared between cells ({value!r:.60}) cannot be written "
                f"to a cells file; results files write it once, as a YAML anchor."
            )
        seen.add(id(value))
    if type(value) is list:
        return [_encode(v, where, seen) for v in value]
    if type(value) is dict:
        if all(type(k) is str for k in value):
            if ITEMS in value:
                raise ContractError(f"{where}: a key {ITEMS!r} cannot be written to a cells file.")
            return {k: _encode(v, where, seen) for k, v in value.items()}
        for key in value:
            if type(key) not in _KEYS:
                raise ContractError(
                    f"{where}: a dict key {key!r} cannot be written to a cells file exactly."
                )
        return {ITEMS: [[k, _encode(v, where, seen)] for k, v in value.items()]}
    raise ContractError(
        f"{where}: a {type(value).__name__} ({value!r}) cannot be written to a cells file "
        f"exactly; cells hold str, int, float, bool, None, lists and dicts."
    )


def _decode(value: Any) -> Any:
    if isinstance(value, list):
        return [_decode(v) for v in value]
    if isinstance(value, dict):
        if set(value) == {ITEMS}:
            return {key: _decode(v) for key, v in value[ITEMS]}
        return {k: _decode(v) for k, v in value.items()}
    return value


def cells_text(cells: DetectorCells) -> str:
    """The cells file's text: the same cells always give the same text."""
    where = f"cells of {cells.detector}"
    for injector, severity in cells.sweep:
        if type(injector) is not str or type(severity) is not float:
            raise ContractError(f"{where}: sweep key {(injector, severity)!r} is not (str, float).")
    # The one sharing results files hold: a detector's null records (one per mode) share one
    # summary (`_detector_results`), which results.yaml writes as an anchor. It is written
    # once and restored by `parse_cells`; any other shared object is refused by `_encode`.
    nulls = [r for r in cells.records if r.kind == "null"]
    if any(r.metrics is not nulls[0].metrics for r in nulls):
        raise ContractError(f"{where}: the null records do not share one summary.")
    seen: set[int] = set()
    records = []
    for index, record in enumerate(cells.records):
        data = record.as_dict()
        if record.kind == "null" and record is not nulls[0]:
            data["metrics"] = NULL_METRICS
        records.append(_encode(data, f"{where}, record {index}", seen))
    document = {
        "format": CELLS_FORMAT,
        "version": CELLS_VERSION,
        "detector": cells.detector,
        "records": records,
        # (injector, severity) keys, in their order: a list of [injector, severity, summary].
        "sweep": [[i, s, _encode(v, where, seen)] for (i, s), v in cells.sweep.items()],
        "modes": _encode(cells.modes, where, seen),
        "tier_records": _encode(cells.tier_records, where, seen),
    }
    return json.dumps(document, indent=1, ensure_ascii=True, allow_nan=True) + "\n"


def write_cells(cells: DetectorCells, path: Path) -> None:
    """Write `cells` to `path` (JSON, atomically)."""
    from oodrl.io.fileio import atomic_write_text

    atomic_write_text(Path(path), cells_text(cells))


def _record(data: dict[str, Any]) -> ResultRecord:
    return ResultRecord(**{"episodes": None, **data})


def parse_cells(text: str, source: str = "cells") -> DetectorCells:
    """Cells from the text `cells_text` wrote."""
    try:
        document = json.loads(text)
    except ValueError as error:
        raise StoreError(f"{source}: not a cells file ({error}).") from None
    if not isinstance(document, dict) or document.get("format") != CELLS_FORMAT:
        raise StoreError(f"{source}: not an {CELLS_FORMAT} file.")
    if document.get("version") != CELLS_VERSION:
        raise StoreError(
            f"{source}: cells version {document.get('version')!r}; this oodrl reads version "
            f"{CELLS_VERSION}: re-run the detector's cells stage."
        )
    records = [_record(_decode(r)) for r in document["records"]]
    # The null records' one summary, written with the first of them (`cells_text`).
    nulls = [r for r in records if r.kind == "null"]
    if any(r.metrics != NULL_METRICS for r in nulls[1:]) or (
        nulls and nulls[0].metrics == NULL_METRICS
    ):
        raise StoreError(f"{source}: damaged null records.")
    records = [replace(r, metrics=nulls[0].metrics) if r.kind == "null" else r for r in records]
    sweep = {(i, s): _decode(summary) for i, s, summary in document["sweep"]}
    return DetectorCells(
        document["detector"], records, sweep, _decode(document["modes"]),
        _decode(document["tier_records"]),
    )  # fmt: skip


def read_cells(path: Path) -> DetectorCells:
    """Cells as `write_cells` wrote them."""
    path = Path(path)
    if not path.is_file():
        raise StoreError(f"{path}: missing; re-run the detector's cells stage.")
    return parse_cells(path.read_text(), str(path))


# -- every detector's cells -------------------------------------------------------------------
def ordered_cells(
    params: Params, cells_by_detector: Mapping[str, DetectorCells]
) -> list[DetectorCells]:
    """The cells in benchmark.detectors order: one per detector params list, no other."""
    detectors = list(params.benchmark.detectors)
    missing = [d for d in detectors if d not in cells_by_detector]
    extra = sorted(set(cells_by_detector) - set(detectors))
    if missing or extra:
        raise ContractError(
            "The merge needs the cells of exactly benchmark.detectors; "
            + "; ".join(
                part
                for part in (
                    f"missing: {', '.join(missing)}" if missing else "",
                    f"not in benchmark.detectors: {', '.join(extra)}" if extra else "",
                )
                if part
            )
            + "."
        )
    for name in detectors:
        if cells_by_detector[name].detector != name:
            raise ContractError(
                f"The cells given for {name!r} are {cells_by_detector[name].detector!r}'s."
            )
    return [cells_by_detector[d] for d in detectors]


def read_all_cells(params: Params, cells_dir: Path) -> list[DetectorCells]:
    """The cells files `cells_dir/<detector>.json` of exactly benchmark.detectors, in its order."""
    cells = {d: read_cells(cells_path(cells_dir, d)) for d in params.benchmark.detectors}
    return ordered_cells(params, cells)


def cells_path(cells_dir: Path, detector: str) -> Path:
    """Where a detector's cells file lives: `cells_dir/<detector>.json`."""
    return Path(cells_dir) / f"{detector}.json"
