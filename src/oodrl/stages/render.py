"""The render stage: figures, DVC plot data, the README headline table, and run_meta.yaml."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params
from oodrl.io.fileio import atomic_write_text
from oodrl.stages.common import TIMINGS_DIR


def run_render(
    params: Params,
    results_path: Path,
    sweep_path: Path,
    scores_dir: Path,
    policy_path: Path,
    models_dir: Path,
    eval_path: Path,
    figures_dir: Path,
    plots_dir: Path,
    headline_path: Path,
    meta_path: Path,
) -> None:
    from oodrl.metrics.results import read_results_file
    from oodrl.report.figures import write_figures
    from oodrl.report.plots import write_dvc_plot_data
    from oodrl.report.provenance import write_run_meta
    from oodrl.report.tables import headline_table

    results, sweep = read_results_file(results_path), read_results_file(sweep_path)
    write_figures(params, results, sweep, scores_dir, figures_dir)
    write_dvc_plot_data(results, sweep, plots_dir)
    atomic_write_text(headline_path, headline_table(results))
    write_run_meta(params, policy_path, models_dir, eval_path, TIMINGS_DIR, meta_path)
