"""The tier_metrics stage: tier and calibration score stores, impact documents ->
reports/tier_results.yaml and reports/tiers/ (tables.md, impact_curves.png). What they hold and
how: `oodrl.metrics.tiers`."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params
from oodrl.io import yamlio
from oodrl.io.fileio import atomic_write_text


def run_tier_metrics(
    params: Params, scores_dir: Path, impact_dir: Path, results_path: Path, report_dir: Path
) -> None:
    from oodrl.metrics.tiers import compute_tier_results, impact_document, tier_tables
    from oodrl.report.impact import plot_impact_curves

    document = compute_tier_results(params, scores_dir, impact_dir)
    impact = impact_document(params, impact_dir)
    atomic_write_text(results_path, yamlio.dump(document))
    Path(report_dir).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(report_dir) / "tables.md", tier_tables(document, impact))
    plot_impact_curves(impact, Path(report_dir) / "impact_curves.png")
