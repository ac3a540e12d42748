"""The suite's cross-environment report (SPEC §12): tables, a metrics file and two figures.

Reads each environment's ``results.yaml`` (headline records keep their per-episode matched
AUROC) and aggregates them with :func:`oodrl.metrics.leaderboard.leaderboard`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from oodrl import yamlio
from oodrl.fileio import atomic_write_text
from oodrl.metrics.leaderboard import Cell, Leaderboard, leaderboard
from oodrl.report.tables import record_injector

METRIC = "matched_auroc"


def read_cells(results: Mapping[str, Path]) -> dict[Cell, dict[str, list[float]]]:
    """(environment, anomaly) → detector → per-episode matched AUROC, from each results file."""
    from oodrl.errors import StoreError

    cells: dict[Cell, dict[str, list[float]]] = {}
    for env_id, path in results.items():
        if not Path(path).is_file():
            raise StoreError(f"{path}: results of {env_id} are missing; build its pipeline first.")
        for record in yamlio.load(Path(path).read_text())["records"]:
            if record["kind"] != "anomaly":
                continue
            episodes = record.get("episodes", {}).get(METRIC)
            if episodes is None:
                raise StoreError(
                    f"{path}: records lack per-episode {METRIC}; re-run {env_id}'s metrics stage."
                )
            cells.setdefault((env_id, record_injector(record)), {})[record["detector"]] = episodes
    return cells


def board_mapping(board: Leaderboard) -> dict[str, Any]:
    """Everything the leaderboard computed, as plain data (sorted keys when dumped)."""
    return {
        "metric": METRIC,
        "n_cells": board.n_cells,
        "environments": list(board.environments),
        "table": {d: {e: round(v, 6) for e, v in row.items()} for d, row in board.table.items()},
        "mean": {d: board.mean[d].as_dict() for d in board.detectors},
        "iqm": {d: board.iqm[d].as_dict() for d in board.detectors},
        "probability_of_improvement": {
            a: {b: board.improvement[(a, b)].as_dict() for b in board.detectors if b != a}
            for a in board.detectors
        },
    }


def ranked(board: Leaderboard) -> list[str]:
    """Detectors by IQM, best first (ties by name)."""
    return sorted(board.detectors, key=lambda d: (-board.iqm[d].value, d))


def markdown(board: Leaderboard) -> str:
    """The leaderboard tables in Markdown."""
    order = ranked(board)
    envs = list(board.environments)
    lines = [
        f"## Mean matched AUROC per detector and environment ({board.n_cells} cells)",
        "",
        "| detector | " + " | ".join(envs) + " | IQM [95% CI] | mean [95% CI] |",
        "|---|" + "---:|" * (len(envs) + 2),
    ]
    for d in order:
        cells = " | ".join(f"{board.table[d][e]:.3f}" for e in envs)
        iqm, mean = board.iqm[d], board.mean[d]
        lines.append(
            f"| {d} | {cells} | {iqm.value:.3f} [{iqm.ci_low:.3f}, {iqm.ci_high:.3f}] "
            f"| {mean.value:.3f} [{mean.ci_low:.3f}, {mean.ci_high:.3f}] |"
        )
    lines += [
        "",
        "IQM: mean of the middle 50% of (environment, anomaly) cell means; CIs: stratified "
        "bootstrap, episodes resampled within each cell.",
        "",
        "## Probability that the row detector beats the column detector on a random cell",
        "",
        "| | " + " | ".join(order) + " |",
        "|---|" + "---:|" * len(order),
    ]
    for a in order:
        row = ["—" if a == b else f"{board.improvement[(a, b)].value:.2f}" for b in order]
        lines.append(f"| {a} | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def metrics_json(board: Leaderboard) -> dict[str, float]:
    """The headline figures for `dvc metrics diff`: each detector's IQM and mean."""
    flat = {f"iqm.{d}": round(board.iqm[d].value, 6) for d in board.detectors}
    flat |= {f"mean.{d}": round(board.mean[d].value, 6) for d in board.detectors}
    return flat


def plot(board: Leaderboard, path: Path) -> Path:
    """IQM and mean with their CIs per detector (left); P(row beats column) (right)."""
    from oodrl.report.plots import _figure, _save

    order = ranked(board)
    figure = _figure(12, 0.45 * len(order) + 2.2)
    left, right = figure.subplots(1, 2, width_ratios=(1, 1.1))
    for offset, (label, values) in enumerate((("IQM", board.iqm), ("mean", board.mean))):
        y = [i + 0.18 * (offset * 2 - 1) for i in range(len(order))]
        x = [values[d].value for d in order]
        error = [
            [values[d].value - values[d].ci_low for d in order],
            [values[d].ci_high - values[d].value for d in order],
        ]
        left.errorbar(x, y, xerr=error, fmt="o", capsize=3, label=f"{label} [95% CI]")
    left.axvline(0.5, color="grey", linestyle=":", linewidth=1)
    left.set_yticks(range(len(order)), order)
    left.invert_yaxis()
    left.set_xlabel("matched AUROC over (environment, anomaly) cells (0.5 = chance)")
    left.legend(loc="lower right", fontsize="small")
    left.set_title(f"Over {board.n_cells} (environment, anomaly) cells")
    matrix = [[board.improvement[(a, b)].value if a != b else 0.5 for b in order] for a in order]
    image = right.imshow(matrix, vmin=0, vmax=1, cmap="RdBu")
    right.set_xticks(range(len(order)), order, rotation=45, ha="right")
    right.set_yticks(range(len(order)), order)
    for i, row in enumerate(matrix):
        for j, value in enumerate(row):
            if i != j:
                colour = "white" if abs(value - 0.5) > 0.3 else "black"  # readable on dark cells
                right.text(j, i, f"{value:.2f}", ha="center", va="center", color=colour)
    right.set_title("P(row beats column) on a random cell")
    figure.colorbar(image, ax=right, shrink=0.8)
    return _save(figure, path)


def run_leaderboard(
    results: Mapping[str, Path], out_dir: Path, n_boot: int, ci: float, seed: int
) -> Leaderboard:
    """Write leaderboard.md, leaderboard.yaml, metrics.json and leaderboard.png into out_dir."""
    board = leaderboard(read_cells(results), n_boot=n_boot, ci=ci, seed=seed)
    out_dir = Path(out_dir)
    atomic_write_text(out_dir / "leaderboard.md", markdown(board))
    atomic_write_text(out_dir / "leaderboard.yaml", yamlio.dump(board_mapping(board)))
    text = json.dumps(metrics_json(board), indent=2, sort_keys=True) + "\n"
    atomic_write_text(out_dir / "metrics.json", text)
    plot(board, out_dir / "leaderboard.png")
    return board
