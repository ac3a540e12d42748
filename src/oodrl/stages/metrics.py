"""The metrics stage: every detector's cells -> results.yaml, sweep_results.yaml, metrics.json,
tables.md (SPEC §23: a merge; what the results hold, and how they are computed:
`oodrl.metrics.results`, `oodrl.metrics.cells`)."""

from __future__ import annotations

import json
from pathlib import Path

from oodrl.config import Params
from oodrl.io import yamlio
from oodrl.io.fileio import atomic_write_text


def run_metrics(
    params: Params,
    cells_dir: Path,
    results_path: Path,
    sweep_path: Path,
    metrics_path: Path,
    tables_path: Path,
) -> None:
    from oodrl.metrics.cells import read_all_cells
    from oodrl.metrics.results import assemble_results

    cells = read_all_cells(params, cells_dir)
    write_results(
        params,
        assemble_results(params, [(c.detector, (c.records, c.sweep, c.modes)) for c in cells]),
        results_path,
        sweep_path,
        metrics_path,
        tables_path,
    )


def write_results(
    params: Params,
    computed,
    results_path: Path,
    sweep_path: Path,
    metrics_path: Path,
    tables_path: Path,
) -> None:
    """Write the metrics stage's four files from its `Results`."""
    from oodrl.metrics.stamp import protocol_stamp
    from oodrl.report.tables import metrics_json, render_tables

    stamp = protocol_stamp(params)  # SPEC §15: the leaderboard refuses to mix protocols
    results = {**stamp, **computed.results_document()}
    sweep = {**stamp, **computed.sweep_document()}
    atomic_write_text(results_path, yamlio.dump(results))
    atomic_write_text(sweep_path, yamlio.dump(sweep))
    atomic_write_text(
        metrics_path, json.dumps(metrics_json(results), indent=2, sort_keys=True) + "\n"
    )
    atomic_write_text(tables_path, render_tables(results, sweep))
