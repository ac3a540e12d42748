"""The leaderboard stage: every (environment, policy)'s results → the suite's leaderboard v2."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from oodrl.config import Params

if TYPE_CHECKING:
    from oodrl.metrics.leaderboard import Board
    from oodrl.report.leaderboard import ResultsPaths

#: A pipeline's results at the headline severity (always there), relative to its directory; its
#: results at the impact tiers (where the pipeline scores them): `tier_results_path`.
HEADLINE_RESULTS = Path("reports/results.yaml")


def results_files(root: Path) -> dict[tuple[str, str], list[Path]]:
    """(environment, policy) → the results files the leaderboard reads: each run's pipeline
    (`oodrl.suite.environments.suite_runs`)."""
    from oodrl.metrics.tier_results import tier_results_path
    from oodrl.suite.environments import suite_runs

    files = {}
    for run, directory in suite_runs().items():
        tiers = tier_results_path(root / directory)
        files[run] = [
            root / directory / HEADLINE_RESULTS,
            *([tiers] if tiers.is_file() else []),
        ]
    return files


def run(params: Params, root: Path, out_dir: Path) -> None:
    """The suite's leaderboard: during a change of protocol (SPEC §26) it ranks the runs at the
    newest version among them (the target, once one is rebuilt) and lists the others as
    pending, never ranking two versions together."""
    from oodrl.report.leaderboard import newest_runs

    m = params.metrics
    ranked, pending = newest_runs(results_files(root))
    run_leaderboard(ranked, out_dir, n_boot=m.n_boot, ci=m.ci, seed=params.seed, pending=pending)


def run_leaderboard(
    results: ResultsPaths,
    out_dir: Path,
    n_boot: int,
    ci: float,
    seed: int,
    pending: Mapping[tuple[str, str], int] | None = None,
) -> Board:
    """Write leaderboard.md, leaderboard.yaml, metrics.json, leaderboard.png and the page's
    leaderboard.json and leaderboard.html into out_dir; `pending`, runs left out for results of
    an older protocol (run -> its version), are named in each."""
    import json

    from oodrl.io import yamlio
    from oodrl.io.fileio import atomic_write_text
    from oodrl.metrics.leaderboard import build_board
    from oodrl.report import leaderboard as report
    from oodrl.report.leaderboard_page import page_data, page_html, page_json

    inputs = report.read_inputs(results)
    board = build_board(inputs.cells, n_boot=n_boot, ci=ci, seed=seed)
    versions = report.Versions(inputs.protocol_version, len(results), dict(pending or {}))
    extras = {
        "protocol_version": inputs.protocol_version,
        "alpha": inputs.alpha,
        "minimum_detectable_impact": inputs.minimum_detectable_impact,
        "uncertified": inputs.uncertified,
        "versions": versions,
    }
    out_dir = Path(out_dir)
    markdown = report.markdown(board, **extras, unverified=inputs.unverified)
    atomic_write_text(out_dir / "leaderboard.md", markdown)
    mapping = report.board_mapping(board, **extras)
    atomic_write_text(out_dir / "leaderboard.yaml", yamlio.dump(mapping))
    text = json.dumps(report.metrics_json(board), indent=2, sort_keys=True) + "\n"
    atomic_write_text(out_dir / "metrics.json", text)
    report.plot(board, out_dir / "leaderboard.png", inputs.alpha)
    data = page_data(inputs, board, n_boot=n_boot, ci=ci, seed=seed, versions=versions)
    atomic_write_text(out_dir / "leaderboard.json", page_json(data))
    atomic_write_text(out_dir / "leaderboard.html", page_html(data))
    return board
