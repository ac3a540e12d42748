"""The leaderboard page (SPEC §21, §25): one self-contained HTML file that opens on the ranking.

`page_data` gathers what the leaderboard read (`oodrl.report.leaderboard.read_inputs`) and
ranked into one document, leaderboard.json: per (metric, tier) each detector's IQM and mean
with their CIs and the number of cells (and the same where more detectors run); where a lower
score is the better one (`lower_is_better`: alarms on harmless shifts), each metric's colour
scale, and the detection rate whose `benign` and `mild` IQMs give the alarm rate on harmless
shifts and the gap; every (environment, policy, fault, tier) cell with each detector's score per
metric (the mean of its per-episode values, the (run, task) score the leaderboard aggregates)
and its evidence (the record's severity, matched AUROC with its CI and, at the impact tiers, its
operating point: detection rate against K, delays, the clean false-alarm rate achieved beside
α); each (environment, policy, fault)'s impact curve and tiers, with a tier's verification where
the tier results carry one; the protocol version and a params hash. `page_html` embeds that
document, as a `<script type="application/json">` block, in the template leaderboard_page.html,
whose inline CSS and JavaScript draw, first, the chosen tier and metric's ranking (IQM [95% CI]
drawn as intervals, mean, benign alarm rate, mild − benign gap), then, where the results hold the
time-aware per-stream rule (SPEC §24), what it changes of the tier's detection rate per detector
(`rule_change`: time-aware − constant [95% CI], Kendall τ), and then that tier's cells, each
opening its evidence (SVG); the view (tier, metric, sorts, filters) is kept in the URL's
fragment. The page needs no network and no fetch. Same inputs, same bytes: keys sorted, no
time, no host path (SPEC §14).
"""

from __future__ import annotations

import hashlib
import html
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from oodrl.metrics.leaderboard import (
    BENIGN_TIER,
    FAULT_FAMILIES,
    FLOOR_DETECTOR,
    OTHER_FAMILY,
    TRIVIAL_DETECTORS,
    Board,
    Cell,
    fault_family,
    policy_key,
)
from oodrl.metrics.stamp import UNSTAMPED_VERSION
from oodrl.report.leaderboard import (
    ARCHIVE,
    HARMFUL_TIER,
    MATCHED_AUROC,
    OPERATING_POINT,
    Inputs,
    Versions,
    harm_metric,
    lower_is_better,
    metric_label,
    rule_change_mapping,
)

#: The suite's directory, where the page's reports/ and the archive are.
SUITE_FOLDER = "pipeline/suite"
#: The page's HTML, CSS and JavaScript; the suite's leaderboard stage depends on it.
PAGE_TEMPLATE = Path(__file__).with_name("leaderboard_page.html")
#: What the template holds in place of the page's data and stamp.
MARKS = ("@@PROTOCOL_VERSION@@", "@@PARAMS_HASH@@", "@@DATA@@", "@@PROTOCOL_RUNS@@")


def _rounded(value: float) -> float:
    return round(float(value), 6) + 0.0


def curve_steps(curve: Mapping[int, float]) -> list[list[float]]:
    """A detection-rate curve {K: rate} as its steps: each K where the rate changes, and the
    last K. Lossless on the curve's grid: the rate holds from one step to the next."""
    points = sorted((int(k), float(rate)) for k, rate in curve.items())
    steps = [[k, r] for i, (k, r) in enumerate(points) if i == 0 or r != points[i - 1][1]]
    if points and steps[-1][0] != points[-1][0]:
        steps.append(list(points[-1]))
    return steps


def record_evidence(record: Mapping[str, Any]) -> dict[str, Any]:
    """What a cell's panel shows of a results record."""
    evidence: dict[str, Any] = {"severity": record.get("severity")}
    auroc = (record.get("metrics") or {}).get(MATCHED_AUROC)
    if auroc:
        evidence[MATCHED_AUROC] = {k: auroc[k] for k in ("mean", "ci_low", "ci_high") if k in auroc}
    point = record.get(OPERATING_POINT)
    if point:
        steps = curve_steps(point.get("detection_curve") or {})
        kept = {k: v for k, v in point.items() if k != "detection_curve"}
        evidence[OPERATING_POINT] = kept | {"detection_curve_steps": steps}
    return evidence


def suite_params_hash(
    params_hashes: Mapping[tuple[str, str], tuple[str | None, ...]], settings: Mapping[str, Any]
) -> str:
    """sha256 of every run's params hashes and the leaderboard's own params, as canonical JSON:
    it changes whenever the params behind a number on the page do."""
    runs = {f"{e}/{p}": list(hashes) for (e, p), hashes in sorted(params_hashes.items())}
    text = _compact({"leaderboard": dict(settings), "runs": runs})
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def _cells(inputs: Inputs, board: Board) -> list[dict[str, Any]]:
    scores: dict[Cell, dict[str, dict[str, float]]] = {}
    for metric, cells in inputs.cells.items():
        if metric not in board.metrics:  # the time-aware rule's detections: `rule_change`
            continue
        for cell, values in cells.items():
            scores.setdefault(Cell(*cell), {})[metric] = {
                d: _rounded(np.mean(v)) for d, v in values.items()
            }
    evidence: dict[Cell, dict[str, Any]] = {}
    for (cell, detector), record in inputs.records.items():
        evidence.setdefault(Cell(*cell), {})[detector] = record_evidence(record)
    order = sorted(
        scores,
        key=lambda c: (c.environment, policy_key(c.policy), c.fault, board.tiers.index(c.tier)),
    )
    return [
        {
            **cell._asdict(),
            "family": fault_family(cell.fault),
            "scores": scores[cell],
            "evidence": evidence.get(cell, {}),
            "trivially_detected": (cell.environment, cell.fault, cell.tier) in board.flagged,
        }
        for cell in order
    ]


def colour_scale(metric: str) -> list[float]:
    """The scores a metric's colours run between, worst to best when higher is better: an AUROC
    at chance (½) is as bad as it gets, a rate runs from 0 to 1."""
    return [0.5, 1.0] if metric.endswith("auroc") else [0.0, 1.0]


def page_data(
    inputs: Inputs,
    board: Board,
    *,
    n_boot: int,
    ci: float,
    seed: int,
    us_per_step: Mapping[str, float] | None = None,
    versions: Versions | None = None,
) -> dict:
    """leaderboard.json's content (see the module doc). `us_per_step`: each detector's median µs
    per streamed step, when the caller measured it; a pipeline's timings are the machine's, never
    a pipeline output (SPEC §13, §14), so the suite's page carries none."""
    settings = {"ci": ci, "n_boot": n_boot, "seed": seed}
    cells = _cells(inputs, board)
    lead = board.overall[board.lead].ranked()
    detectors = lead + sorted(
        {d for c in cells for m in c["scores"].values() for d in m} - set(lead)
    )
    families = {c["family"] for c in cells}
    harm = harm_metric(board)
    by_metric = {m: {t: a for (n, t), a in board.overall.items() if n == m} for m in board.metrics}
    data = (versions.mapping() if versions is not None else {}) | {
        "protocol_version": inputs.protocol_version,
        "params_hash": suite_params_hash(inputs.params_hashes, settings),
        "leaderboard_params": settings,
        "runs": [
            {"environment": e, "policy": p, "params_hashes": list(hashes)}
            for (e, p), hashes in sorted(
                inputs.params_hashes.items(), key=lambda r: (r[0][0], policy_key(r[0][1]))
            )
        ],
        "alpha": inputs.alpha,
        "metrics": list(board.metrics),
        "metric_labels": {m: metric_label(m, inputs.alpha) for m in board.metrics},
        "tiers": list(board.tiers),
        "families": [f for f in (*FAULT_FAMILIES, OTHER_FAMILY) if f in families],
        "environments": sorted({c["environment"] for c in cells}),
        "policies": sorted({c["policy"] for c in cells}, key=policy_key),
        "detectors": detectors,
        "lead": {"metric": board.lead[0], "tier": board.lead[1]},
        "iqm": {
            metric: {tier: {d: a.iqm[d].as_dict() for d in a.detectors} for tier, a in ts.items()}
            for metric, ts in by_metric.items()
        },
        "mean": {
            metric: {tier: {d: a.mean[d].as_dict() for d in a.detectors} for tier, a in ts.items()}
            for metric, ts in by_metric.items()
        },
        "n_cells": {
            metric: {tier: a.n_cells for tier, a in ts.items()} for metric, ts in by_metric.items()
        },
        # Where a lower score is the better one (alarms on harmless shifts), and the range each
        # metric's colours run over: the page colours and sorts by them.
        "lower_is_better": {
            metric: [tier for tier in ts if lower_is_better(metric, tier)]
            for metric, ts in by_metric.items()
        },
        "colour_scale": {metric: colour_scale(metric) for metric in board.metrics},
        # The detection rate whose IQM on harmless shifts is an alarm rate, beside the same at
        # the mildest harmful tier: the ranking's "detects what hurts" columns (SPEC §19).
        "harm": harm and {"metric": harm, "harmful": HARMFUL_TIER, "harmless": BENIGN_TIER},
        # Detectors that run on some cells only, ranked there (`detector_scopes`).
        "iqm_where_more_detectors_run": {
            metric: {
                tier: [
                    {
                        "environments": list(scope.environments),
                        "n_cells": scope.n_cells,
                        "iqm": {d: scope.iqm[d].as_dict() for d in scope.detectors},
                        "mean": {d: scope.mean[d].as_dict() for d in scope.detectors},
                    }
                    for scope in scopes
                ]
                for (m, tier), scopes in board.scoped.items()
                if m == metric
            }
            for metric in board.metrics
        },
        "trivial_detectors": [d for d in TRIVIAL_DETECTORS if d in detectors],
        "floor_detector": FLOOR_DETECTOR if FLOOR_DETECTOR in detectors else None,
        "uncertified_detectors": list(inputs.uncertified),
        "cells": cells,
        "impact": [
            {"environment": e, "policy": p, "fault": f, **impact}
            for (e, p, f), impact in sorted(
                inputs.impact.items(), key=lambda r: (r[0][0], policy_key(r[0][1]), r[0][2])
            )
        ],
    }
    if board.rule_change:  # what the time-aware rule changes (SPEC §24), where results hold it
        data["rule_change"] = rule_change_mapping(board)
    if us_per_step is not None:
        data["us_per_step"] = {d: _rounded(v) for d, v in us_per_step.items()}
    return data


def _compact(value: Any) -> str:
    return json.dumps(
        value, sort_keys=True, ensure_ascii=False, allow_nan=False, separators=(",", ":")
    )


def page_json(data: Mapping[str, Any]) -> str:
    """leaderboard.json: keys sorted, compact, each cell (and each run, each impact curve) on a
    line of its own, so a changed number is a one-line diff of a file that stays small."""
    lines = []
    for key, value in sorted(data.items()):
        if isinstance(value, list) and value and isinstance(value[0], dict):
            value_text = "[\n" + ",\n".join(_compact(item) for item in value) + "\n]"
        else:
            value_text = _compact(value)
        lines.append(f"{_compact(key)}:{value_text}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def page_html(data: Mapping[str, Any]) -> str:
    """leaderboard.html: the template with the stamp and leaderboard.json embedded."""
    version = data["protocol_version"]
    stamp = f"{version} (unstamped results)" if version == UNSTAMPED_VERSION else str(version)
    # "<" escaped inside JSON strings, so no "</script>" in the data can end its block.
    embedded = page_json(data).replace("<", "\\u003c")
    page = PAGE_TEMPLATE.read_text(encoding="utf-8")
    texts = (html.escape(stamp), html.escape(data["params_hash"]), embedded, _runs_line(data))
    for mark, text in zip(MARKS, texts, strict=True):
        page = page.replace(mark, text)
    return page


def _runs_line(data: Mapping[str, Any]) -> str:
    """The runs the page ranks and those pending at an older protocol (SPEC §26), escaped."""
    if "runs_at_version" not in data:
        return ""
    pending = {(r["environment"], r["policy"]): r["protocol_version"] for r in data["pending"]}
    line = html.escape(Versions(data["protocol_version"], data["runs_at_version"], pending).line())
    for version in sorted(set(pending.values())):  # the page is pipeline/suite/reports/'s
        folder = f"{ARCHIVE}/protocol-{version}/"
        link = f"../{folder.removeprefix(f'{SUITE_FOLDER}/')}leaderboard.html"
        line = line.replace(folder, f'<a href="{link}">{folder}</a>')
    return line
