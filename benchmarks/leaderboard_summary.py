"""What the suite's leaderboard says about chosen detectors, read from the committed results.

    python benchmarks/leaderboard_summary.py [--suite pipeline/suite/reports]
        [--pipelines pipeline] [--metric detection_rate@100] [--tiers benign mild moderate]
        [--detectors D ...] [--versus cusum] [--at mild] [--n-boot 2000]

Reads the suite's leaderboard.json (the leaderboard stage's output, git-tracked) and each run's
tier results under --pipelines (reports/tier_results.json, or a protocol-4 run's
reports/tier_results.yaml), computes nothing the pipeline has not measured,
and prints markdown:

1. the top five per tier with the IQM of the metric and its 95% CI, as the leaderboard ranks
   them (`benign` quietest first: an alarm on a harmless shift is a cost);
2. where each detector of --detectors (default: SPEC §20's) lands at each tier: rank among
   all, IQM [95% CI] (a detector that runs on some runs only: among the detectors of its
   cells, marked *);
3. each detector's false-alarm rate achieved on its run's audit set (200 clean streams used for
   nothing else, SPEC §19): over the runs, the median rate, the range, and the runs whose
   Clopper-Pearson interval lies above α;
4. where each detector beats --versus at tier --at, by environment and fault family: the mean
   over the group's cells (each (policy, fault) cell once) of the detector's score minus the
   versus detector's, with a 95% percentile bootstrap over the group's cells (paired: both
   scores of a cell move together); "beats" when the interval lies above 0. A group of fewer
   than 5 cells is counted, not judged;
5. what the time-aware per-stream rule (SPEC §24) changes, per detector and environment: the
   mean over each environment's verified (policy, fault) cells of --tiers of the detection rate
   under the time-aware rule minus under the constant one, from the runs' tier records (the
   rows of `oodrl.load_results(kind="tiers")`); the leaderboard gives each detector's paired CI.

Every number says how many runs or cells stand behind it.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from oodrl.errors import StoreError
from oodrl.metrics.tier_results import load_tier_results, tier_results_path

#: SPEC §20's detectors: the policy view, value-function surprise, a recurrent predictor, an
#: anytime-valid test and the two baselines.
SECTION_20 = (
    "q_margin", "q_entropy", "q_energy", "max_softmax", "fqe_td", "riqn",
    "conformal_martingale", "deedee", "random_scores",
)  # fmt: skip
BENIGN = "benign"
#: A group of fewer cells gives no verdict: a bootstrap over two or three cells is no interval.
MIN_CELLS = 5


def load(path: Path, parse, keys: tuple[str, ...], what: str) -> dict:
    """`parse(path)`; exit 1 with one line when it does not parse or lacks one of `keys`."""
    try:
        document = parse(path)
        missing = [key for key in keys if key not in document]
    except (ValueError, TypeError, StoreError) as error:
        reason = f"{type(error).__name__}: {(str(error).splitlines() or [''])[0]}"
    else:
        if not missing:
            return document
        reason = f"no {', '.join(missing)}"
    raise SystemExit(f"error: {path} is not {what} ({reason}).")


def interval(d: dict) -> str:
    return f"{d['value']:.3f} [{d['ci_low']:.3f}, {d['ci_high']:.3f}]"


def ranked(iqm: dict[str, dict], tier: str) -> list[str]:
    """The leaderboard's order: highest IQM first, `benign` lowest first; ties by name."""
    sign = 1 if tier == BENIGN else -1
    return sorted(iqm, key=lambda d: (sign * iqm[d]["value"], d))


def top_five(board: dict, metric: str, tiers: list[str]) -> list[str]:
    lines = []
    for tier in tiers:
        iqm = board["iqm"][metric].get(tier)
        if not iqm:
            continue
        n_cells = sum(1 for c in board["cells"] if c["tier"] == tier)
        order = "quietest first" if tier == BENIGN else "highest first"
        lines += [f"### Top five at `{tier}` ({order}; IQM over {n_cells} (policy, cell) scores)",
                  "", "| rank | detector | IQM [95% CI] |", "|---:|---|---:|"]  # fmt: skip
        lines += [f"| {i} | {d} | {interval(iqm[d])} |"
                  for i, d in enumerate(ranked(iqm, tier)[:5], 1)]  # fmt: skip
        lines.append("")
    return lines


def landing(board: dict, metric: str, tiers: list[str], detectors: list[str]) -> list[str]:
    present = [t for t in tiers if board["iqm"][metric].get(t)]
    lines = ["### Where each detector lands (rank among all, IQM [95% CI])", "",
             "| detector | " + " | ".join(present) + " |",
             "|---|" + "---:|" * len(present)]  # fmt: skip
    scoped = board.get("iqm_where_more_detectors_run", {}).get(metric, {})
    for d in detectors:
        row = []
        for tier in present:
            iqm, mark = board["iqm"][metric][tier], ""
            if d not in iqm:  # a detector of some runs only: over the most cells it runs on
                mine = [s for s in scoped.get(tier, []) if d in s["iqm"]]
                if not mine:
                    row.append("—")
                    continue
                scope = max(mine, key=lambda s: s["n_cells"])
                iqm, mark = scope["iqm"], f" * ({scope['n_cells']} cells)"
            order = ranked(iqm, tier)
            row.append(f"{order.index(d) + 1}/{len(order)}: {interval(iqm[d])}{mark}")
        lines.append(f"| {d} | " + " | ".join(row) + " |")
    note = "* ranked over the cells where it runs, among the detectors that run there."
    return [*lines, "", *([note, ""] if scoped else [])]


@functools.cache
def tier_documents(pipelines: Path) -> dict[Path, dict]:
    """Each run's parsed tier results (megabytes each: parsed once), by file."""
    paths = [tier_results_path(run) for run in sorted(pipelines.iterdir()) if run.is_dir()]
    return {
        path: load(path, load_tier_results, ("alpha",), "a tier results file")
        for path in paths
        if path.is_file()
    }


def false_alarms(pipelines: Path) -> list[str]:
    rates, above, alarmed, streams, alpha = defaultdict(list), defaultdict(int), {}, {}, set()
    runs = tier_documents(pipelines)
    for document in runs.values():
        alpha.add(document["alpha"])
        for d, audit in (document.get("false_alarm_audit") or {}).items():
            rates[d].append(audit["rate"])
            above[d] += audit["ci"][0] > document["alpha"]
            alarmed[d] = alarmed.get(d, 0) + audit["n_alarmed"]
            streams[d] = streams.get(d, 0) + audit["n_streams"]
    (a,) = alpha or {float("nan")}
    lines = [f"### False-alarm rate achieved on the audit sets (α = {a:g}; {len(runs)} runs)", "",
             "| detector | runs | median | range | pooled (alarmed/streams) | runs above α |",
             "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for d in sorted(rates, key=lambda d: (np.median(rates[d]), d)):
        r = rates[d]
        lines.append(
            f"| {d} | {len(r)} | {np.median(r):.3f} | {min(r):.3f}–{max(r):.3f} | "
            f"{alarmed[d] / streams[d]:.3f} ({alarmed[d]}/{streams[d]}) | {above[d]} |"
        )
    return [*lines, "", "A run is above α when its rate's Clopper-Pearson 95% interval is.", ""]


def versus(board: dict, metric: str, tier: str, rival: str, detectors: list[str], n_boot: int):
    groups = defaultdict(list)
    for cell in board["cells"]:
        scores = cell["scores"].get(metric, {})
        if cell["tier"] == tier and rival in scores:
            groups[(cell["environment"], cell["family"])].append(scores)
    rng = np.random.default_rng(0)
    lines = [f"### Where each detector beats `{rival}` at `{tier}` (mean {metric} difference "
             "over a group's cells [95% bootstrap CI], groups by environment and fault family)",
             ""]  # fmt: skip
    for d in detectors:
        wins, n_groups, small = [], 0, 0
        for (env, family), cells in sorted(groups.items()):
            diffs = np.array([c[d] - c[rival] for c in cells if d in c])
            if diffs.size == 0:
                continue
            n_groups += 1
            if diffs.size < MIN_CELLS:
                small += 1
                continue
            boot = diffs[rng.integers(0, diffs.size, (n_boot, diffs.size))].mean(axis=1)
            low, high = np.quantile(boot, [0.025, 0.975])
            if low > 0:
                wins.append(f"{env}/{family} {diffs.mean():+.3f} [{low:+.3f}, {high:+.3f}] "
                            f"({diffs.size} cells)")  # fmt: skip
        where = "; ".join(wins) if wins else "nowhere"
        unjudged = f", {small} of fewer than {MIN_CELLS} cells not judged" if small else ""
        lines.append(f"- **{d}** (in {n_groups} groups{unjudged}): {where}")
    return [*lines, ""]


def by_rule(pipelines: Path, metric: str, tiers: list[str]) -> list[str]:
    import pandas as pd

    from oodrl.api.project import pipeline_at
    from oodrl.api.results import tier_rows
    from oodrl.metrics.leaderboard import time_aware_metric

    key = ["env", "policy", "fault", "detector"]
    changes: dict[str, dict[tuple[str, str], list[float]]] = defaultdict(lambda: defaultdict(list))
    for path, document in tier_documents(pipelines).items():
        if not document.get("records"):
            continue
        # load_results' rows, from the document false_alarms already parsed
        run = pipeline_at(path.parents[1])
        frame = pd.DataFrame(tier_rows(document["records"], run.env, run.policy))
        frame = frame[frame.verified.astype(bool) & frame.tier.isin(tiers)]
        for tier, rows in frame.groupby("tier"):
            constant = rows[rows.metric == metric].set_index(key)["value"]
            time_aware = rows[rows.metric == time_aware_metric(metric)].set_index(key)["value"]
            for (env, _, _, detector), change in (time_aware - constant).dropna().items():
                changes[tier][(detector, env)].append(change)
    lines = []
    for tier in tiers:
        cells = changes.get(tier, {})
        if not cells:  # results of protocol 3 hold one rule
            lines += [f"### What the time-aware rule changes at `{tier}`: no verified cell holds "
                      "both rules", ""]  # fmt: skip
            continue
        envs = sorted({env for _, env in cells})
        lines += [f"### What the time-aware rule changes at `{tier}` (mean over each "
                  f"environment's verified cells of {metric} under it minus under the constant "
                  "rule)", "", "| detector | " + " | ".join(envs) + " |",
                  "|---|" + "---:|" * len(envs)]  # fmt: skip
        for detector in sorted({d for d, _ in cells}):
            row = [f"{np.mean(cells[(detector, e)]):+.3f} ({len(cells[(detector, e)])})"
                   if (detector, e) in cells else "—" for e in envs]  # fmt: skip
            lines.append(f"| {detector} | " + " | ".join(row) + " |")
        lines += ["", "(n): the environment's cells with both rules.", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", type=Path, default=Path("pipeline/suite/reports"))
    parser.add_argument("--pipelines", type=Path, default=Path("pipeline"))
    parser.add_argument("--metric", default="detection_rate@100")
    parser.add_argument("--tiers", nargs="+", default=[BENIGN, "mild", "moderate"])
    parser.add_argument("--detectors", nargs="+", default=list(SECTION_20))
    parser.add_argument("--versus", default="cusum")
    parser.add_argument("--at", default="mild")
    parser.add_argument("--n-boot", type=int, default=2000)
    args = parser.parse_args(argv)
    path = args.suite / "leaderboard.json"
    if not path.is_file():
        print(f"error: {path} not found; build the suite (oodrl suite run) or pass --suite.",
              file=sys.stderr)  # fmt: skip
        return 1
    board = load(
        path, lambda p: json.loads(p.read_text()), ("iqm", "cells", "runs"),
        "the leaderboard stage's JSON",
    )  # fmt: skip
    if args.metric not in board["iqm"]:
        print(f"error: --metric {args.metric}: the leaderboard has {', '.join(board['iqm'])}.",
              file=sys.stderr)  # fmt: skip
        return 2
    out = [f"# The suite's leaderboard (protocol version {board['protocol_version']}, "
           f"{len(board['runs'])} runs, {args.metric})", ""]  # fmt: skip
    out += top_five(board, args.metric, args.tiers)
    out += landing(board, args.metric, args.tiers, args.detectors)
    out += false_alarms(args.pipelines)
    out += versus(board, args.metric, args.at, args.versus, args.detectors, args.n_boot)
    out += by_rule(args.pipelines, args.metric, [BENIGN, args.at])
    print("\n".join(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
