"""The metrics stage: score stores -> results.yaml, sweep_results.yaml, metrics.json, tables.md.

What the results hold, and how they are computed: `oodrl.metrics.results`.
"""

from __future__ import annotations

import json
from pathlib import Path

from oodrl.config import Params
from oodrl.io import yamlio
from oodrl.io.fileio import atomic_write_text


def run_metrics(
    params: Params,
    scores_dir: Path,
    results_path: Path,
    sweep_path: Path,
    metrics_path: Path,
    tables_path: Path,
) -> None:
    from oodrl.metrics.results import compute_results
    from oodrl.metrics.stamp import protocol_stamp
    from oodrl.report.tables import metrics_json, render_tables

    computed = compute_results(params, scores_dir)
    stamp = protocol_stamp(params)  # SPEC §15: the leaderboard refuses to mix protocols
    results = {**stamp, **computed.results_document()}
    sweep = {**stamp, **computed.sweep_document()}
    atomic_write_text(results_path, yamlio.dump(results))
    atomic_write_text(sweep_path, yamlio.dump(sweep))
    atomic_write_text(
        metrics_path, json.dumps(metrics_json(results), indent=2, sort_keys=True) + "\n"
    )
    atomic_write_text(tables_path, render_tables(results, sweep))
