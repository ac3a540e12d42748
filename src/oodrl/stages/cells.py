"""The cells stage: one detector's score stores (and the faults' impact documents) ->
cells/<detector>.json, its part of the results (SPEC §23; the file and why merging the cells keeps
every byte: `oodrl.metrics.cells`)."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params
from oodrl.errors import ContractError
from oodrl.metrics.cells import DetectorCells, write_cells


def detector_cells(
    params: Params, scores_dir: Path, impact_dir: Path | None, detector: str
) -> DetectorCells:
    """`detector`'s cells from its own score stores (`scores_dir/<detector>/`) and the faults'
    impact documents (`impact_dir`, the tiers' verification): no other detector's scores are
    read. Without `impact_dir` (a pipeline of recorded data has no impact tiers, SPEC §18) it has
    no tier records."""
    from oodrl.metrics.results import _detector_results
    from oodrl.metrics.tiers import detector_records

    if detector not in params.benchmark.detectors:
        raise ContractError(
            f"Detector {detector!r} is not in benchmark.detectors "
            f"({', '.join(params.benchmark.detectors)})."
        )
    records, sweep, modes = _detector_results(params, Path(scores_dir), detector)
    tier_records = (
        []
        if impact_dir is None
        else detector_records(params, Path(scores_dir), Path(impact_dir), detector)
    )
    return DetectorCells(detector, records, sweep, modes, tier_records)


def run_cells(
    params: Params, detector: str, scores_dir: Path, impact_dir: Path | None, out: Path
) -> None:
    write_cells(detector_cells(params, scores_dir, impact_dir, detector), out)
