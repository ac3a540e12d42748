"""The leaderboard stage: every (environment, policy)'s results → the suite's leaderboard v2."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params

#: A pipeline's results at the headline severity (always there) and at the impact tiers
#: (where the pipeline scores them), relative to its directory.
HEADLINE_RESULTS = Path("reports/results.yaml")
TIER_RESULTS = Path("reports/tier_results.yaml")


def results_files(root: Path) -> dict[tuple[str, str], list[Path]]:
    """(environment, policy) → the results files the leaderboard reads: each run's pipeline
    (`oodrl.suite.suite_runs`)."""
    from oodrl.suite import suite_runs

    files = {}
    for run, directory in suite_runs().items():
        tiers = root / directory / TIER_RESULTS
        files[run] = [
            root / directory / HEADLINE_RESULTS,
            *([tiers] if tiers.is_file() else []),
        ]
    return files


def run(params: Params, root: Path, out_dir: Path) -> None:
    from oodrl.report.leaderboard import run_leaderboard

    m = params.metrics
    run_leaderboard(results_files(root), out_dir, n_boot=m.n_boot, ci=m.ci, seed=params.seed)
