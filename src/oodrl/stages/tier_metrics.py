"""The tier_metrics stage: every detector's cells and the faults' impact documents ->
reports/tier_results.json and reports/tiers/ (tables.md, impact_curves.png); a merge (SPEC
§23). What they hold and how: `oodrl.metrics.tiers`, `oodrl.metrics.cells`."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from oodrl.config import Params
from oodrl.io.fileio import atomic_write_text


def run_tier_metrics(
    params: Params, cells_dir: Path, impact_dir: Path, results_path: Path, report_dir: Path
) -> None:
    from oodrl.metrics.cells import read_all_cells
    from oodrl.metrics.tiers import assemble_tier_results

    records = [r for cells in read_all_cells(params, cells_dir) for r in cells.tier_records]
    document = assemble_tier_results(params, records, Path(impact_dir))
    write_tier_results(params, document, impact_dir, results_path, report_dir)


def write_tier_results(
    params: Params, document: Mapping[str, Any], impact_dir: Path, results_path: Path,
    report_dir: Path,
) -> None:  # fmt: skip
    """Write the tier_metrics stage's files from the tier results document."""
    from oodrl.metrics.tier_results import tier_results_text
    from oodrl.metrics.tiers import impact_document, tier_tables
    from oodrl.report.impact import plot_impact_curves

    impact = impact_document(params, Path(impact_dir))
    atomic_write_text(results_path, tier_results_text(document))
    Path(report_dir).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(report_dir) / "tables.md", tier_tables(document, impact))
    plot_impact_curves(impact, Path(report_dir) / "impact_curves.png")
