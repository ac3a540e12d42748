"""The suite's leaderboard v2 (SPEC §12, §15, §16): tables, a metrics file and one figure.

Reads each (environment, policy)'s ``results.yaml``: anomaly records keep per-episode values
of their metrics under ``episodes`` (matched AUROC always; ``detection_rate@K`` as 0/1 per
faulty stream where the metrics stage computes operating points), and name their ``tier``
(records without one are scored at the headline severity: tier ``headline``). A record's
``operating_point.alpha`` is the false-alarm budget of its detection rate; a document's
``minimum_detectable_impact`` maps detector → fault → criterion → the smallest return loss
1 − R̃ at which the criterion is met, `{at_most: loss}` when already met at the first measured
severity (a bound, shown "≤ loss"), or "beyond range". Every file carries a protocol version
(`oodrl.metrics.stamp.protocol_stamp`; unstamped files are version 1) and files of two
versions are refused. Aggregation: `oodrl.metrics.leaderboard.build_board`; the page of
every cell and its evidence: `oodrl.report.leaderboard_page`.

Tier records of protocol 4 also keep the time-aware rule's 0/1 detections per faulty stream
(``time_aware_detection_rate@K``, SPEC §24) where the detector has that rule. They are read into
the same cells under that name, are no metric of their own (no record needs them; a record
without them is simply not compared) and are not ranked: `build_board` compares them with
``detection_rate@K`` on the same streams (`Board.rule_change`), which leaderboard.md ("What the
time-aware rule changes"), leaderboard.yaml and leaderboard.json carry (`rule_change_mapping`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from oodrl.io import yamlio
from oodrl.metrics.leaderboard import (
    BENIGN_TIER,
    FIRST_POLICY,
    FLOOR_DETECTOR,
    HEADLINE_TIER,
    MATCHED_AUROC,
    TRIVIAL_DETECTORS,
    TRIVIAL_THRESHOLD,
    Aggregate,
    Board,
    Cell,
    Interval,
    above_floor,
    constant_metric,
    policy_key,
    tier_order,
)
from oodrl.metrics.stamp import UNSTAMPED_VERSION, one_protocol_version
from oodrl.report.tables import UNCERTIFIED, certification_note, marked, record_injector

#: Where a record keeps the false-alarm budget α of its operating point.
OPERATING_POINT = "operating_point"
#: A results document's minimum-detectable-impact section.
MINIMUM_DETECTABLE_IMPACT = "minimum_detectable_impact"
#: The level a criterion of the minimum detectable impact must reach (SPEC §15).
MDI_LEVEL = 0.9
#: Human names of the leaderboard's metrics (others print as named).
METRIC_LABELS = {MATCHED_AUROC: "matched AUROC"}
#: The performance-profile thresholds the tables quote (the figure draws every τ).
QUOTED_TAUS = (0.9, 1.0)
#: The tier whose detection rate the harm table sets beside the alarm rate on `benign` shifts.
HARMFUL_TIER = "mild"
#: Where the log axis of the optimality-gap figure draws a gap of exactly 0.
GAP_FLOOR = 1e-4

#: Results files (one or several) by (environment, policy), or by environment for policy "0".
ResultsPaths = Mapping[tuple[str, str] | str, Path | Sequence[Path]]
#: criterion → (environment, policy, fault) → detector → return loss, a bound
#: `{at_most: loss}`, or "beyond range" (`oodrl.protocol.impact.minimum_detectable_impact`).
MinimumDetectableImpact = dict[
    str, dict[tuple[str, str, str], dict[str, float | str | dict[str, float]]]
]


@dataclass(frozen=True)
class Inputs:
    """What the leaderboard reads from the results files."""

    #: metric → cell → detector → per-episode values.
    cells: dict[str, dict[Cell, dict[str, list[float]]]]
    protocol_version: int
    #: The false-alarm budget of `detection_rate@K`, when the records name one α.
    alpha: float | None = None
    minimum_detectable_impact: MinimumDetectableImpact = field(default_factory=dict)
    #: Detectors some results file lists as not certified machine-independent (SPEC §14, §17).
    uncertified: tuple[str, ...] = ()
    #: (cell, detector) → its results record: the evidence the leaderboard page shows.
    records: dict[tuple[Cell, str], dict[str, Any]] = field(default_factory=dict)
    #: (environment, policy, fault) → its impact curve and tiers, where tier results hold one.
    impact: dict[tuple[str, str, str], dict[str, Any]] = field(default_factory=dict)
    #: (environment, policy) → the params hashes of its results files (None: unstamped).
    params_hashes: dict[tuple[str, str], tuple[str | None, ...]] = field(default_factory=dict)
    #: Cells whose tier's verification missed its level (SPEC §19): left out of every aggregate.
    unverified: tuple[Cell, ...] = ()


@dataclass(frozen=True)
class Versions:
    """Which runs a leaderboard ranks during a change of protocol (SPEC §26): those at
    `version`, `ranked` of them; `pending` runs (run -> version) hold an older protocol's
    results, left out of every aggregate until their pipeline is rebuilt."""

    version: int
    ranked: int
    pending: dict[tuple[str, str], int] = field(default_factory=dict)

    def line(self) -> str:
        """ "Protocol 4: 7 of 21 runs ranked; pending: …" (and where the previous one is)."""
        total = self.ranked + len(self.pending)
        if not self.pending:
            return f"Protocol {self.version}: all {_count(total, 'run')} ranked; none pending."
        runs = ", ".join(f"{e}/{p} (protocol {v})" for (e, p), v in sorted(self.pending.items()))
        older = sorted(set(self.pending.values()))
        archives = ", ".join(f"{ARCHIVE}/protocol-{v}/" for v in older)
        return (
            f"Protocol {self.version}: {self.ranked} of {_count(total, 'run')} ranked; pending "
            f"(results of an older protocol, ranked by none of this page's numbers): {runs}. "
            f"The previous version's complete leaderboard: {archives}."
        )

    def mapping(self) -> dict[str, Any]:
        """The keys leaderboard.yaml and leaderboard.json carry."""
        return {
            "runs_at_version": self.ranked,
            "pending": [
                {"environment": e, "policy": p, "protocol_version": v}
                for (e, p), v in sorted(self.pending.items())
            ],
        }


#: Where a maintainer keeps the previous protocol's complete leaderboard while a change of
#: protocol is rebuilt (docs/how-to/change-protocol.md): ARCHIVE/protocol-<version>/.
ARCHIVE = "pipeline/suite/archive"
#: A results file's stamp line (top-level; `oodrl.metrics.stamp.protocol_stamp`):
#: `protocol_version: 4` in YAML, `"protocol_version":5,` in the tier results' JSON, which
#: writes a line per top-level key (`oodrl.metrics.tier_results.tier_results_text`).
_STAMP_LINE = re.compile(r'^"?protocol_version"?:[ \t]*(\d+)[ \t]*,?$', re.MULTILINE)


def _file_version(path: Path) -> int:
    """A results file's protocol version from its stamp line (a YAML's whole is seconds)."""
    found = _STAMP_LINE.search(path.read_text()) if path.is_file() else None
    return int(found.group(1)) if found else UNSTAMPED_VERSION


def newest_runs(
    results: Mapping[tuple[str, str] | str, Path | Sequence[Path]],
) -> tuple[dict[tuple[str, str] | str, Path | Sequence[Path]], dict[tuple[str, str], int]]:
    """The runs whose results are at the newest protocol version among them, and the others
    (run -> its oldest file's version): what the suite ranks while a change of protocol is
    being rebuilt a project at a time (SPEC §26)."""
    versions = {key: min(_file_version(p) for p in _paths(paths)) for key, paths in results.items()}
    newest = max(versions.values(), default=UNSTAMPED_VERSION)
    ranked = {key: paths for key, paths in results.items() if versions[key] == newest}
    pending = {_run_key(key): v for key, v in versions.items() if v != newest}
    return ranked, pending


def _run_key(key: tuple[str, str] | str) -> tuple[str, str]:
    return (key, FIRST_POLICY) if isinstance(key, str) else (str(key[0]), str(key[1]))


def _paths(paths: Path | Sequence[Path]) -> list[Path]:
    return [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]


def read_inputs(results: ResultsPaths) -> Inputs:
    """Every results file's per-episode values by metric and cell, its version, α and MDI.

    Within a tier every record must hold the same per-episode metrics (headline records hold
    matched AUROC alone, tier records also `detection_rate@K`); one (cell, detector) comes
    from one record.
    """
    from oodrl.errors import StoreError
    from oodrl.metrics.tier_results import load_tier_results

    documents: dict[str, Any] = {}
    cells: dict[str, dict[Cell, dict[str, list[float]]]] = {}
    metrics_of: dict[tuple[Cell, str], tuple[Path, set[str]]] = {}
    records: dict[tuple[Cell, str], dict[str, Any]] = {}
    impact: dict[tuple[str, str, str], dict[str, Any]] = {}
    hashes: dict[tuple[str, str], set[str | None]] = {}
    alphas: set[float] = set()
    mdi: MinimumDetectableImpact = {}
    uncertified: set[str] = set()
    unverified: set[Cell] = set()
    for key, paths in results.items():
        env_id, policy = _run_key(key)
        for path in _paths(paths):
            if not path.is_file():
                raise StoreError(
                    f"{path}: results of {env_id} are missing; build its pipeline first."
                )
            # Tier results are JSON from protocol 5 (either form: `load_tier_results`).
            document = (
                load_tier_results(path) if path.suffix == ".json" else yamlio.load(path.read_text())
            )
            documents[str(path)] = document
            uncertified.update(document.get(UNCERTIFIED) or ())
            hashes.setdefault((env_id, policy), set()).add(document.get("params_hash"))
            for fault, curve in (document.get("impact") or {}).items():
                impact[(env_id, policy, fault)] = curve
            for record in document["records"]:
                if record["kind"] != "anomaly":
                    continue
                episodes = record.get("episodes") or {}
                if MATCHED_AUROC not in episodes:
                    raise StoreError(
                        f"{path}: records lack per-episode {MATCHED_AUROC}; re-run {env_id}'s "
                        f"metrics stage."
                    )
                tier = record.get("tier", HEADLINE_TIER)
                cell = Cell(env_id, policy, record_injector(record), tier)
                if record.get("verified") is False:  # results before SPEC §19 have no flag
                    unverified.add(cell)
                    continue
                detector = record["detector"]
                if (cell, detector) in metrics_of:
                    raise StoreError(
                        f"{path}: a second record of {detector} on {tuple(cell)} (the first in "
                        f"{metrics_of[(cell, detector)][0]})."
                    )
                # The time-aware rule's detections are optional (`rule_change`): not a metric
                # every record of the tier must hold.
                held = {m for m in episodes if constant_metric(m) is None}
                metrics_of[(cell, detector)] = (path, held)
                records[(cell, detector)] = record
                for metric, values in episodes.items():
                    cells.setdefault(metric, {}).setdefault(cell, {})[detector] = values
                alpha = (record.get(OPERATING_POINT) or {}).get("alpha")
                if alpha is not None:
                    alphas.add(float(alpha))
            for detector, faults in (document.get(MINIMUM_DETECTABLE_IMPACT) or {}).items():
                for fault, criteria in faults.items():
                    for criterion, value in criteria.items():
                        row = mdi.setdefault(criterion, {}).setdefault((env_id, policy, fault), {})
                        row[detector] = value
    in_tier: dict[str, set[str]] = {}
    # A run's detectors are its params' (benchmark.detectors), the same in every cell of a
    # tier; runs may differ (a continuous-action run has no policy-view detectors, SPEC §20:
    # the board ranks them where they run, `oodrl.metrics.leaderboard.detector_scopes`).
    detectors_in_tier: dict[tuple[str, str, str], set[str]] = {}
    detectors_of: dict[Cell, tuple[Path, set[str]]] = {}
    for (cell, detector), (path, found) in metrics_of.items():
        in_tier.setdefault(cell.tier, set()).update(found)
        run_tier = (cell.environment, cell.policy, cell.tier)
        detectors_in_tier.setdefault(run_tier, set()).add(detector)
        detectors_of.setdefault(cell, (path, set()))[1].add(detector)
    for (cell, detector), (path, found) in metrics_of.items():
        if found != in_tier[cell.tier]:
            raise StoreError(
                f"{path}: {detector} on {tuple(cell)} lacks per-episode "
                f"{', '.join(sorted(in_tier[cell.tier] - found))}, which other records of tier "
                f"{cell.tier} have; re-run its metrics stage."
            )
    for cell, (path, found) in detectors_of.items():
        expected = detectors_in_tier[(cell.environment, cell.policy, cell.tier)]
        if found != expected:
            raise StoreError(
                f"{path}: no records of {', '.join(sorted(expected - found))} on {tuple(cell)}, "
                f"which other cells of its run and tier {cell.tier} have; every cell of a run's "
                f"tier needs the same detectors (benchmark.detectors)."
            )
    version = one_protocol_version(documents)
    alpha = next(iter(alphas)) if len(alphas) == 1 else None
    params_hashes = {
        run: tuple(sorted(found, key=lambda h: h or "")) for run, found in sorted(hashes.items())
    }
    return Inputs(
        cells, version, alpha, mdi, tuple(sorted(uncertified)), records, impact, params_hashes,
        tuple(sorted(unverified)),
    )  # fmt: skip


def metric_label(metric: str, alpha: float | None = None) -> str:
    label = METRIC_LABELS.get(metric, metric)
    if metric.startswith("detection_rate") and alpha is not None:
        label += f" at α = {alpha:g}"
    return label


def _count(n: int, noun: str, plural: str | None = None) -> str:
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def _interval(value: Interval) -> str:
    return f"{value.value:.3f} [{value.ci_low:.3f}, {value.ci_high:.3f}]"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """A Markdown table, first column left, the rest right."""
    lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def _bootstrap_note(board: Aggregate) -> str:
    if board.bootstrap == "episodes":
        return "episodes resampled within each cell (one run per cell)"
    if board.bootstrap == "runs":
        return "policies (runs) resampled within each cell"
    return f"policies (runs) resampled within each cell; {board.bootstrap.split('; ', 1)[1]}"


def _runs_note(board: Aggregate) -> str:
    low, high = min(board.runs), max(board.runs)
    if high == 1:
        return "one policy per cell"
    return f"{low} policies per cell" if low == high else f"{low}–{high} policies per cell"


def _floor_lines(overall: Aggregate, label: str) -> list[str]:
    """Which detectors beat the floor (`FLOOR_DETECTOR`) on this tier's cells, and which do not."""
    beats = above_floor(overall)
    if beats is None:
        return []
    below = [d for d in overall.ranked() if d in beats and not beats[d]]
    return [
        f"Floor: `{FLOOR_DETECTOR}` (scores that ignore the data). A detector beats it when "
        f"P(it > {FLOOR_DETECTOR} on a random cell) has its 95% CI above ½ ({label}); "
        f"{len(beats) - len(below)} of {len(beats)} do. "
        + (f"Not above the floor: {', '.join(below)}." if below else "All are above it."),
        "",
    ]


def lower_is_better(metric: str, tier: str) -> bool:
    """Whether a lower score is the better one: a detection on a harmless (`benign`) shift is a
    false alarm; every other (metric, tier) counts the higher score the better."""
    return tier == BENIGN_TIER and metric.startswith("detection_rate")


def _order(board: Aggregate, harmless: bool) -> list[str]:
    """Best first; on harmless shifts, where a detection is a false alarm, the quietest first."""
    if harmless:
        return sorted(board.detectors, key=lambda d: (board.iqm[d].value, d))
    return board.ranked()


def _score_row(board: Aggregate, detector: str, uncertified: Sequence[str]) -> list[str]:
    """A detector's name (marked), its mean per environment, its IQM and mean with CIs."""
    name = marked(detector, uncertified)
    name += " (trivial signal)" if detector in TRIVIAL_DETECTORS else ""
    name += " (floor)" if detector == FLOOR_DETECTOR else ""
    table = board.table[detector]
    return [
        name,
        *(f"{table[e]:.3f}" for e in board.environments),
        _interval(board.iqm[detector]),
        _interval(board.mean[detector]),
    ]


def _section(
    board: Board, metric: str, tier: str, alpha: float | None, uncertified: Sequence[str] = ()
) -> list[str]:
    overall = board.overall[(metric, tier)]
    unflagged = board.unflagged.get((metric, tier))
    label = metric_label(metric, alpha)
    harmless = lower_is_better(metric, tier)
    order = _order(overall, harmless)
    envs = list(overall.environments)
    header = ["detector", *envs, "IQM [95% CI]", "mean [95% CI]"]
    if unflagged is not None:
        header.append(f"IQM without flagged cells ({unflagged.n_cells}) [95% CI]")
    rows = []
    for d in order:
        row = _score_row(overall, d, uncertified)
        if unflagged is not None:
            row.append(_interval(unflagged.iqm[d]))
        rows.append(row)
    flagged = sum(1 for task in overall.tasks if task in board.flagged)
    lines = [
        f"## Tier `{tier}`: mean {label} per detector and environment "
        f"({_count(overall.n_cells, 'cell')})",
        "",
        *(
            ["Harmless shifts (R̃ = 0.99): an alarm here is a cost, so lower is better and the "
             "quietest detector comes first.", ""]
            if harmless else []
        ),
        *_table(header, rows),
        "",
        f"IQM: mean of the middle 50% of (policy, cell) scores ({_runs_note(overall)}); "
        f"CIs: stratified bootstrap, {_bootstrap_note(overall)}. "
        f"Cells a trivial signal detects: {flagged} of {overall.n_cells}.",
        "",
    ]  # fmt: skip
    for scope in board.scoped.get((metric, tier), ()):
        only = [d for d in scope.detectors if d not in overall.detectors]
        lines += [
            f"### Where more detectors run: {', '.join(scope.environments)} "
            f"({_count(scope.n_cells, 'cell')})",
            "",
            f"{', '.join(only)} run only on these cells (a detector that cannot run on a run's "
            f"policy is left out of its params, SPEC §20), so they are ranked here, over these "
            f"cells, beside every detector that runs on them.",
            "",
            *_table(
                ["detector", *scope.environments, "IQM [95% CI]", "mean [95% CI]"],
                [_score_row(scope, d, uncertified) for d in _order(scope, harmless)],
            ),
            "",
        ]
    if harmless:
        return lines
    lines += _floor_lines(overall, label)
    families = board.families[(metric, tier)]
    names = list(families)
    lines += [f"### By fault family (IQM of {label} [95% CI])", ""]
    fam_header = ["detector", *(f"{f} ({_count(families[f].n_cells, 'cell')})" for f in names)]
    fam_rows = [[d, *(_interval(families[f].iqm[d]) for f in names)] for d in order]
    lines += [*_table(fam_header, fam_rows), ""]
    quoted = [t for t in QUOTED_TAUS if t in overall.taus]
    lines += [
        "### Optimality gap and performance profile",
        "",
        *_table(
            [
                "detector",
                f"optimality gap 1 − {label} [95% CI]",
                *(f"share of scores ≥ {t:g} [95% CI]" for t in quoted),
            ],
            [
                [
                    d,
                    _interval(overall.optimality_gap[d]),
                    *(_interval(overall.profile[d][overall.taus.index(t)]) for t in quoted),
                ]
                for d in order
            ],
        ),
        "",
        "### Probability that the row detector beats the column detector on a random cell",
        "",
        *_table(
            ["", *order],
            [
                [a, *("—" if a == b else f"{overall.improvement[(a, b)].value:.2f}" for b in order)]
                for a in order
            ],
        ),
        "",
        "P(row > column): per cell the Mann-Whitney statistic of the row's policies against the "
        "column's (ties ½), averaged over cells.",
        "",
        *_stability_lines(board, metric, tier),
    ]
    return lines


def harm_metric(board: Board) -> str | None:
    """The detection rate ranked at both `mild` and `benign`: what tells a harmful shift from a
    harmless one (SPEC §19), or None when the board has no such metric."""
    return next(
        (m for m in board.metrics if m.startswith("detection_rate")
         and (m, HARMFUL_TIER) in board.overall and (m, BENIGN_TIER) in board.overall),
        None,
    )  # fmt: skip


def _harm_lines(board: Board, alpha: float | None) -> list[str]:
    """Detects what hurts, stays quiet on what does not (SPEC §19): per detector, its
    detection rate at `mild` beside its alarm rate on `benign` shifts, and the difference."""
    metric = harm_metric(board)
    if metric is None:
        return []
    harmful, harmless = board.overall[(metric, HARMFUL_TIER)], board.overall[(metric, BENIGN_TIER)]
    detectors = sorted(
        set(harmful.detectors) & set(harmless.detectors),
        key=lambda d: (-(harmful.iqm[d].value - harmless.iqm[d].value), d),
    )
    rows = [
        [d, _interval(harmful.iqm[d]), _interval(harmless.iqm[d]),
         f"{harmful.iqm[d].value - harmless.iqm[d].value:+.3f}"]
        for d in detectors
    ]  # fmt: skip
    label = metric_label(metric, alpha)
    return [
        "## Detects what hurts, stays quiet on what does not",
        "",
        *_table(["detector", "mild: IQM [95% CI]", "benign: IQM [95% CI]", "mild − benign"], rows),
        "",
        f"{label}: at `mild` (5% of the return lost) a detection; at `benign` (1% lost) a "
        "false alarm. Ordered by the difference of the two IQMs.",
        "",
    ]


def _signed_interval(value: Interval) -> str:
    return f"{value.value:+.3f} [{value.ci_low:+.3f}, {value.ci_high:+.3f}]"


def _tau_text(tau: float | None) -> str:
    return "—" if tau is None else f"{tau:.2f}"


def _finite(value: float) -> float | None:
    return round(value, 6) + 0.0 if math.isfinite(value) else None


def rule_change_mapping(board: Board) -> dict[str, Any]:
    """What the time-aware rule changes (`Board.rule_change`) as plain data: per metric and tier,
    the cells compared, and per detector the difference time-aware − constant (mean over cells
    [CI]), whether its CI excludes 0, each rule's IQM of cell rates and its cells (the
    environments they are in where it runs on some only); Kendall's τ between the rules' IQM
    rankings per scope of detectors (None where τ is undefined: fewer than two detectors, or
    all tied under a rule). Empty where no record holds the time-aware rule."""
    mapping: dict[str, Any] = {}
    for (metric, tier), changes in board.rule_change.items():
        detectors = {}
        for d in changes.detectors:
            environments, change = changes.of(d)
            diff = change.differences[d]
            detectors[d] = {
                "difference": Interval(diff.mean, diff.ci_low, diff.ci_high).as_dict(),
                "changed": diff.excludes_zero,
                "n_cells": diff.n_cells,
                "iqm": {rule: round(v[d], 6) + 0.0 for rule, v in change.iqm.items()},
                "environments": list(environments),
            }
        mapping.setdefault(metric, {})[tier] = {
            "n_cells": changes.n_cells,
            "n_tier_cells": changes.n_tier_cells,
            "detectors": detectors,
            "kendall_tau": [
                {
                    "environments": list(e),
                    "detectors": list(c.detectors),
                    "tau": _finite(c.kendall_tau),
                }
                for e, c in changes.scopes
            ],  # fmt: skip
        }
    return mapping


def _rule_change_lines(board: Board, alpha: float | None) -> list[str]:
    """What the time-aware rule changes (SPEC §24): per detection metric a table of each
    detector's difference time-aware − constant per tier, and Kendall's τ per tier."""
    lines: list[str] = []
    metrics = sorted({m for m, _ in board.rule_change})
    for metric in metrics:
        tiers = tier_order(t for m, t in board.rule_change if m == metric)
        changes = {t: board.rule_change[(metric, t)] for t in tiers}
        lead = board.overall.get((metric, tiers[0]))
        seen = {d for c in changes.values() for d in c.detectors}
        ranked = [d for d in (lead.ranked() if lead else []) if d in seen]
        order = ranked + sorted(seen - set(ranked))
        scoped = False
        rows = []
        for d in order:
            row = [d]
            for t in tiers:
                if d not in changes[t].detectors:
                    row.append("—")
                    continue
                environments, change = changes[t].of(d)
                diff = change.differences[d]
                mark = " *" if diff.excludes_zero else ""
                some = environments != changes[t].scopes[0][0]
                scoped |= some
                row.append(
                    _signed_interval(Interval(diff.mean, diff.ci_low, diff.ci_high))
                    + mark
                    + (" †" if some else "")
                )
            rows.append(row)
        rows.append(
            ["Kendall τ of the two rules' IQM rankings"]
            + [_tau_text(_finite(changes[t].scopes[0][1].kendall_tau)) for t in tiers]
        )
        rows.append(
            ["cells with both rules"]
            + [f"{changes[t].n_cells} of {changes[t].n_tier_cells}" for t in tiers]
        )
        lines += [
            f"## What the time-aware rule changes: {metric_label(metric, alpha)}",
            "",
            "Per detector, its detection rate under the time-aware per-stream rule (each step's "
            "score standardised by the clean law of its scores at that step on the ID streams, "
            "SPEC §24) minus under the constant rule: the mean over cells [95% CI: paired "
            "bootstrap of each cell's streams, the same draws for both rules]; * where the CI "
            "excludes 0. Only cells whose results hold both rules are compared (results of "
            "protocol 3 hold one).",
            "",
            *_table(["detector", *(f"{t}: time-aware − constant [95% CI]" for t in tiers)], rows),
            "",
            *(
                ["† over the cells where the detector runs (it runs on some environments only)."]
                + [""]
                if scoped
                else []
            ),
        ]
    return lines


def _stability_lines(board: Board, metric: str, tier: str) -> list[str]:
    stability = board.stability[(metric, tier)]
    lines = ["### Ranking stability across policies", ""]
    if len(stability.policies) == 1:
        return [*lines, f"One policy (policy {stability.policies[0]}): nothing to compare.", ""]
    environments = sorted({environment for environment, _, _ in stability.tasks})
    if not environments:
        return [*lines, "No (environment, fault, tier) has a cell of every policy.", ""]
    lines += [
        f"Over the {len(stability.tasks)} (environment, fault, tier) tasks every policy has a "
        f"cell of ({', '.join(environments)}): each policy ranked on the same tasks.",
        "",
    ]
    rows = [
        [f"policy {p}", stability.winners[p], f"{stability.iqm[p][stability.winners[p]]:.3f}"]
        for p in stability.policies
    ]
    taus = ", ".join(f"{p}–{q}: {t:.2f}" for (p, q), t in stability.kendall_tau.items())
    mean = stability.mean_tau
    return [
        *lines,
        *_table(["policy", "winner", "its IQM"], rows),
        "",
        f"Kendall τ between per-policy rankings (by IQM): {taus}"
        + (f"; mean {mean:.2f}." if mean is not None else "."),
        "",
    ]


def _flag_lines(board: Board, detectors: Sequence[str]) -> list[str]:
    present = [d for d in TRIVIAL_DETECTORS if d in detectors]
    lines = ["## Cells a trivial signal already detects", ""]
    rule = (
        f"Rule: a cell is flagged when a trivial-signal detector ({', '.join(TRIVIAL_DETECTORS)}) "
        f"reaches matched AUROC ≥ {TRIVIAL_THRESHOLD} there (mean over its policies)."
    )
    if not present:
        return [*lines, rule + " None of them is in the results: no cell is flagged.", ""]
    if not board.flagged:
        return [*lines, rule + " No cell is flagged.", ""]
    rows = [
        [f"{env} / {fault} / {tier}", ", ".join(f"{d} {v:.3f}" for d, v in signals.items())]
        for (env, fault, tier), signals in board.flagged.items()
    ]
    return [*lines, rule, "", *_table(["cell", "trivial signal (matched AUROC)"], rows), ""]


def _mdi_lines(mdi: MinimumDetectableImpact, alpha: float | None) -> list[str]:
    from oodrl.protocol.impact import impact_text

    lines = []
    for criterion, rows in sorted(mdi.items()):
        detectors = sorted({d for row in rows.values() for d in row})
        several = len({p for _, p, _ in rows}) > 1
        table_rows = []
        for (env, policy, fault), values in sorted(rows.items()):
            name = f"{env} / policy {policy} / {fault}" if several else f"{env} / {fault}"
            cells = ["—" if values.get(d) is None else impact_text(values[d]) for d in detectors]
            table_rows.append([name, *cells])
        lines += [
            f"## Minimum detectable impact: the smallest return loss 1 − R̃ at which "
            f"{metric_label(criterion, alpha)} reaches {MDI_LEVEL:g}",
            "",
            *_table(["environment / fault", *detectors], table_rows),
            "",
        ]
    return lines


def markdown(
    board: Board,
    *,
    protocol_version: int,
    alpha: float | None = None,
    minimum_detectable_impact: MinimumDetectableImpact | None = None,
    uncertified: Sequence[str] = (),
    unverified: Sequence[Cell] = (),
    versions: Versions | None = None,
) -> str:
    """leaderboard.md: the lead (metric, tier) first, then every other, the harmless-shift
    view, then flags and MDI; uncertified detectors marked, with a note, when there are some;
    the cells left out for a missed tier verification listed."""
    lead = board.overall[board.lead]
    policies = sorted({p for s in board.stability.values() for p in s.policies}, key=policy_key)
    stamp = (
        f"{protocol_version} (unstamped results)"
        if protocol_version == UNSTAMPED_VERSION
        else str(protocol_version)
    )
    lines = [
        "# Suite leaderboard",
        "",
        f"Protocol version {stamp}; {_count(len(lead.environments), 'environment')}; "
        f"{_count(len(policies), 'policy', 'policies')} "
        f"({', '.join(policies)}); tiers {', '.join(board.tiers)}; metrics "
        f"{', '.join(metric_label(m, alpha) for m in board.metrics)}.",
        "",
        *([versions.line(), ""] if versions is not None else []),
    ]
    for metric, tier in board.order():
        lines += _section(board, metric, tier, alpha, uncertified)
    lines += _harm_lines(board, alpha)
    lines += _rule_change_lines(board, alpha)
    if unverified:
        cells = ", ".join("/".join(cell) for cell in unverified)
        lines += [
            "## Tiers left out",
            "",
            f"{_count(len(unverified), 'cell')} whose tier's verification missed its level "
            f"(SPEC §19), in no aggregate: {cells}.",
            "",
        ]
    if uncertified:
        lines += ["## Machine independence", "", certification_note(uncertified), ""]
    lines += _flag_lines(board, lead.detectors)
    lines += _mdi_lines(minimum_detectable_impact or {}, alpha)
    return "\n".join(lines).rstrip("\n") + "\n"


def _aggregate_mapping(board: Aggregate) -> dict[str, Any]:
    order = board.ranked()
    return {
        "bootstrap": board.bootstrap,
        "n_cells": board.n_cells,
        "runs_per_cell": {"min": min(board.runs), "max": max(board.runs)},
        "environments": list(board.environments),
        "ranking": order,
        "table": {d: {e: round(v, 6) for e, v in row.items()} for d, row in board.table.items()},
        "mean": {d: board.mean[d].as_dict() for d in board.detectors},
        "iqm": {d: board.iqm[d].as_dict() for d in board.detectors},
        "optimality_gap": {d: board.optimality_gap[d].as_dict() for d in board.detectors},
        "probability_of_improvement": {
            a: {b: board.improvement[(a, b)].as_dict() for b in board.detectors if b != a}
            for a in board.detectors
        },
        "performance_profile": {
            "taus": list(board.taus),
            **{
                d: {
                    k: [p.as_dict()[k] for p in board.profile[d]]
                    for k in ("value", "ci_low", "ci_high")
                }
                for d in board.detectors
            },
        },
    }


def board_mapping(
    board: Board,
    *,
    protocol_version: int,
    alpha: float | None = None,
    minimum_detectable_impact: MinimumDetectableImpact | None = None,
    uncertified: Sequence[str] = (),
    versions: Versions | None = None,
) -> dict[str, Any]:
    """Everything the leaderboard computed, as plain data (sorted keys when dumped); the
    uncertified detectors only when there are some; the runs ranked and pending, given
    `versions`."""
    boards: dict[str, dict[str, Any]] = {}
    for (metric, tier), overall in board.overall.items():
        stability = board.stability[(metric, tier)]
        entry = _aggregate_mapping(overall)
        entry["families"] = {
            f: {"n_cells": a.n_cells, "bootstrap": a.bootstrap, "ranking": a.ranked(),
                "mean": {d: a.mean[d].as_dict() for d in a.detectors},
                "iqm": {d: a.iqm[d].as_dict() for d in a.detectors}}
            for f, a in board.families[(metric, tier)].items()
        }  # fmt: skip
        entry["stability"] = {
            "policies": list(stability.policies),
            "shared_tasks": len(stability.tasks),
            "winners": stability.winners,
            "iqm": {p: {d: round(v, 6) for d, v in r.items()} for p, r in stability.iqm.items()},
            "kendall_tau": {f"{p}-{q}": round(t, 6) for (p, q), t in stability.kendall_tau.items()},
        }
        if (metric, tier) in board.unflagged:
            entry["without_flagged_cells"] = _aggregate_mapping(board.unflagged[(metric, tier)])
        if (metric, tier) in board.scoped:
            entry["where_more_detectors_run"] = [
                _aggregate_mapping(scope) for scope in board.scoped[(metric, tier)]
            ]
        boards.setdefault(metric, {})[tier] = entry
    mdi = {
        criterion: [
            {"environment": e, "policy": p, "fault": f, "values": values}
            for (e, p, f), values in sorted(rows.items())
        ]
        for criterion, rows in (minimum_detectable_impact or {}).items()
    }
    mapping = {
        "protocol_version": protocol_version,
        "alpha": alpha,
        "lead": {"metric": board.lead[0], "tier": board.lead[1]},
        "boards": boards,
        "flagged_cells": [
            {
                "environment": e,
                "fault": f,
                "tier": t,
                "signals": {d: round(v, 6) for d, v in s.items()},
            }
            for (e, f, t), s in board.flagged.items()
        ],
        "trivial_rule": {
            "detectors": list(TRIVIAL_DETECTORS),
            "matched_auroc_at_least": TRIVIAL_THRESHOLD,
        },
        "minimum_detectable_impact": mdi,
    }
    mapping |= versions.mapping() if versions is not None else {}
    if board.rule_change:  # results of protocol 3 have none: their files keep their keys
        mapping["rule_change"] = rule_change_mapping(board)
    return mapping | ({UNCERTIFIED: list(uncertified)} if uncertified else {})


def metrics_json(board: Board) -> dict[str, float]:
    """Figures for `dvc metrics diff`: each detector's IQM and mean, keyed
    `<metric>.<tier>.<aggregate>.<detector>`, so that a diff names what each number is (the lead
    (metric, tier) too; SPEC §21); over the cells where more detectors run,
    `<metric>.<tier>.<environment>+<environment>….<aggregate>.<detector>`."""
    flat: dict[str, float] = {}
    for key, overall in board.overall.items():
        scopes = [("", overall)] + [
            ("+".join(scope.environments) + ".", scope) for scope in board.scoped.get(key, ())
        ]  # a detector ranked only where it runs: its key names those environments
        for where, aggregate in scopes:
            prefix = f"{key[0]}.{key[1]}.{where}"
            for d in aggregate.detectors:
                flat[f"{prefix}iqm.{d}"] = round(aggregate.iqm[d].value, 6)
                flat[f"{prefix}mean.{d}"] = round(aggregate.mean[d].value, 6)
    return flat


def plot(board: Board, path: Path, alpha: float | None = None) -> Path:
    """The lead (metric, tier): IQM and mean with CIs; P(row beats column); performance
    profiles with their bootstrap bands; the optimality gap on a log axis."""
    import numpy as np

    from oodrl.report.plots import _colours, _figure, _save

    metric, tier = board.lead
    lead = board.overall[board.lead]
    label = metric_label(metric, alpha)
    order = lead.ranked()
    colours = _colours(order)
    figure = _figure(13, 2 * (0.45 * len(order) + 2.2))
    (scores, matrix_axis), (profiles, gaps) = figure.subplots(2, 2, width_ratios=(1, 1.1))
    for offset, (name, values) in enumerate((("IQM", lead.iqm), ("mean", lead.mean))):
        y = [i + 0.18 * (offset * 2 - 1) for i in range(len(order))]
        x = [values[d].value for d in order]
        error = [
            [values[d].value - values[d].ci_low for d in order],
            [values[d].ci_high - values[d].value for d in order],
        ]
        scores.errorbar(x, y, xerr=error, fmt="o", capsize=3, label=f"{name} [95% CI]")
    scores.set_yticks(range(len(order)), order)
    scores.invert_yaxis()
    scores.set_xlabel(f"{label} over (policy, cell) scores")
    scores.legend(loc="lower right", fontsize="small")
    scores.set_title(f"Tier {tier}: {lead.n_cells} cells, {_runs_note(lead)}")
    matrix = [[lead.improvement[(a, b)].value if a != b else 0.5 for b in order] for a in order]
    image = matrix_axis.imshow(matrix, vmin=0, vmax=1, cmap="RdBu")
    matrix_axis.set_xticks(range(len(order)), order, rotation=45, ha="right")
    matrix_axis.set_yticks(range(len(order)), order)
    for i, row in enumerate(matrix):
        for j, value in enumerate(row):
            if i != j:
                colour = "white" if abs(value - 0.5) > 0.3 else "black"  # readable on dark cells
                matrix_axis.text(j, i, f"{value:.2f}", ha="center", va="center", color=colour)
    matrix_axis.set_title("P(row beats column) on a random cell")
    figure.colorbar(image, ax=matrix_axis, shrink=0.8)
    taus = np.asarray(lead.taus)
    for d in order:
        profile = lead.profile[d]
        # share ≥ τ is a step function of τ, constant up to the next grid point
        profiles.plot(
            taus, [p.value for p in profile], color=colours[d], label=d, drawstyle="steps-post"
        )
        profiles.fill_between(
            taus, [p.ci_low for p in profile], [p.ci_high for p in profile],
            color=colours[d], alpha=0.2, linewidth=0, step="post",
        )  # fmt: skip
    profiles.set_xlabel(f"τ ({label})")
    profiles.set_ylabel("share of (policy, cell) scores ≥ τ")
    profiles.set_ylim(0, 1.02)
    profiles.set_title("Performance profiles [95% CI]")
    profiles.legend(fontsize="x-small", loc="lower left")
    value = [max(lead.optimality_gap[d].value, GAP_FLOOR) for d in order]
    low = [max(lead.optimality_gap[d].ci_low, GAP_FLOOR) for d in order]
    high = [max(lead.optimality_gap[d].ci_high, GAP_FLOOR) for d in order]
    error = [[v - lo for v, lo in zip(value, low, strict=True)],
             [hi - v for v, hi in zip(value, high, strict=True)]]  # fmt: skip
    gaps.errorbar(value, range(len(order)), xerr=error, fmt="o", capsize=3)
    gaps.set_xscale("log")
    gaps.set_yticks(range(len(order)), order)
    gaps.invert_yaxis()
    gaps.set_xlabel(f"optimality gap 1 − {label} (log; 0 drawn at {GAP_FLOOR:g})")
    gaps.set_title("Optimality gap [95% CI] (lower is better)")
    return _save(figure, path)
