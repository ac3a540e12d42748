"""Load the committed suite's leaderboard and plot one tier's ranking with its CIs.

    python examples/leaderboard_ranking.py [--tier mild] [--metric detection_rate@100] [--out DIR]

No stage runs: the leaderboard is tracked by git (pipeline/suite/reports/leaderboard.json).
The ranking is the leaderboard's interquartile mean over (environment, policy, fault) cells with
its stratified-bootstrap 95% CI, its mean beside it; the table below is each environment's mean
over its faults (each fault's mean over the policies), computed here from the leaderboard's
cells as the leaderboard's own table (leaderboard.md) computes it.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402

import oodrl  # noqa: E402

SUITE = Path(__file__).resolve().parents[1] / "pipeline" / "suite"


def interval(row) -> str:
    return f"{row.value:.3f} [{row.ci_low:.3f}, {row.ci_high:.3f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tier", default="mild")
    parser.add_argument("--metric", default="detection_rate@100")
    parser.add_argument("--out", type=Path, default=None, help="folder of the PNG (default: a "
                        "new temporary folder)")  # fmt: skip
    args = parser.parse_args()

    ranking = oodrl.load_results(SUITE, kind="ranking")
    overall = ranking[(ranking.tier == args.tier) & (ranking.metric == args.metric)
                      & ranking.env.isna()]  # fmt: skip
    rows = overall[overall.statistic == "iqm"].sort_values("value")
    if rows.empty:
        choices = ranking[ranking.env.isna()][["tier", "metric"]].drop_duplicates()
        raise SystemExit(
            f"error: no ranking of {args.metric} at tier {args.tier}. Allowed: "
            + ", ".join(f"{t}/{m}" for t, m in choices.itertuples(index=False))
        )

    figure, axes = plt.subplots(figsize=(7, 1 + 0.32 * len(rows)))
    errors = [rows.value - rows.ci_low, rows.ci_high - rows.value]
    axes.errorbar(rows.value, rows.detector, xerr=errors, fmt="o", capsize=3)
    axes.set_xlabel(f"{args.metric}: IQM over cells [95% CI]")
    axes.set_title(f"oodrl leaderboard, {args.tier} tier")
    axes.grid(axis="x", alpha=0.3)
    figure.tight_layout()
    out = args.out or Path(tempfile.mkdtemp(prefix="oodrl-ranking-"))
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"ranking_{args.tier}_{args.metric.replace('@', '_at_')}.png"
    figure.savefig(path, dpi=120)

    means = overall[overall.statistic == "mean"].set_index("detector")
    print(f"{'detector':<24}{'IQM [95% CI]':<24}mean [95% CI]")
    for row in rows.iloc[::-1].itertuples():
        print(f"{row.detector:<24}{interval(row):<24}{interval(means.loc[row.detector])}")
    board = oodrl.load_results(SUITE)
    cells = board[(board.tier == args.tier) & (board.metric == args.metric)]
    per_fault = cells.groupby(["detector", "env", "fault"]).value.mean()
    per_env = per_fault.groupby(["detector", "env"]).mean().unstack("env")
    print(f"\nmean over each environment's faults ({len(cells)} cell values):")
    print(per_env.loc[rows.detector.iloc[::-1]].round(3).to_string())
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
