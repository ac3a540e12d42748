"""The leaderboard stage: every (environment, policy)'s results → the suite's leaderboard v2."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params


def run(params: Params, root: Path, out_dir: Path) -> None:
    from oodrl.metrics.leaderboard import FIRST_POLICY
    from oodrl.report.leaderboard import run_leaderboard
    from oodrl.suite import PIPELINE_DIRS

    # One committed policy per environment today: each pipeline's results are its policy "0".
    results = {
        (env, FIRST_POLICY): root / d / "reports" / "results.yaml"
        for env, d in PIPELINE_DIRS.items()
    }
    m = params.metrics
    run_leaderboard(results, out_dir, n_boot=m.n_boot, ci=m.ci, seed=params.seed)
