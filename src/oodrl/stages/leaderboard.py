"""The leaderboard stage: every environment's results → the suite's cross-environment report."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params


def run(params: Params, root: Path, out_dir: Path) -> None:
    from oodrl.report.leaderboard import run_leaderboard
    from oodrl.suite import PIPELINE_DIRS

    results = {env: root / d / "reports" / "results.yaml" for env, d in PIPELINE_DIRS.items()}
    m = params.metrics
    run_leaderboard(results, out_dir, n_boot=m.n_boot, ci=m.ci, seed=params.seed)
