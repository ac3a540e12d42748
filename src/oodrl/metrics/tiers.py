"""Detection at impact tiers and a per-stream false-alarm budget (SPEC §15): the tier_metrics
stage's results, `reports/tier_results.yaml` (the stages that feed it: `oodrl.protocol.tiers`).

Per (detector, fault, tier) a record holds every metric of SPEC §6 against the matched clean
twins of its `tiers.n_streams` faulty streams (per-episode matched AUROC kept for the
leaderboard), whether the tier's verification held (SPEC §19: an unverified cell is left out of
tier aggregates), and the operating point of the per-stream conformal rule
(`oodrl.metrics.operating`): its threshold is computed from the detector's scores on the
calibration streams at `tiers.alpha` by `tiers.threshold_rule` (training-conditional
`episode_max_conditional` at `tiers.delta`, or marginal `episode_max`); `detection_rate@K` per
stream (kept per episode too), the delays of the streams detected within K (shown from 5 on),
the detection-rate curve, and the clean false-alarm rate the threshold achieves on the audit
streams (used for nothing else), also kept once per detector. Per detector × fault, the
minimum detectable impact:
the smallest return loss at which matched AUROC, and `detection_rate@K`, reach 0.9 on the tiers
(the metric linear between the tiers' severities, the loss read on the monotone impact curve).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from oodrl.config import Params
from oodrl.io.layout import CLEAN_GROUP, detector_stage, heldout_score_store, tier_score_store
from oodrl.io.store import read_scores, severity_key
from oodrl.protocol.tiers import impact_path, read_impact

#: The level matched AUROC and detection_rate@K must reach for the minimum detectable impact.
MDI_TARGET = 0.9


def detection_metric(k: int) -> str:
    """The per-stream detection metric's name: `detection_rate@100`."""
    return f"detection_rate@{k}"


def _per_stream_detections(faulty: np.ndarray, threshold: float, onset: int, k: int, latency: int):
    """1.0 per faulty stream whose first alarm is raised in [t*, t* + K] within the stream."""
    from oodrl.metrics.operating import first_raise

    raised = first_raise(faulty >= threshold, latency)
    detected = (raised >= onset) & (raised <= onset + k) & (raised < faulty.shape[1])
    return detected.astype(np.float64)


def _rounded(values) -> list[float]:
    return [round(float(v), 6) + 0.0 for v in values]


def _detector_records(params: Params, scores_dir: Path, impact_dir: Path, detector: str):
    """One detector's records at every fault's reachable tiers."""
    from oodrl.metrics.aggregate import episode_metrics, summarise
    from oodrl.metrics.operating import operating_point as operating
    from oodrl.metrics.operating import per_stream_threshold

    tiers = params.tiers
    latency = params.detector(detector).latency

    def heldout(which: str) -> np.ndarray:
        groups, _ = read_scores(
            heldout_score_store(scores_dir, detector, which),
            stage=detector_stage(detector, "score_clean"),
        )
        return groups[CLEAN_GROUP]["scores"]

    # The tier streams' clean twins (same seeds) for the matched metrics; the audit streams,
    # used for nothing else, for the false-alarm rate the threshold achieves (SPEC §19).
    twins, audit = heldout("twins"), heldout("audit")
    # The per-stream rule (`tiers.threshold_rule`): an order statistic of the calibration
    # streams' maxima, training-conditional or marginal.
    maxima = heldout("calibration").max(axis=1)
    threshold = per_stream_threshold(maxima, tiers.alpha, tiers.threshold_rule, tiers.delta)
    records = []
    for fault in params.benchmark.injectors:
        groups, attrs = read_scores(
            tier_score_store(scores_dir, detector, fault),
            stage=detector_stage(detector, "score", fault),
        )
        verification = {
            name: tier.get("verification", {}).get("verified", False)
            for name, tier in read_impact(impact_path(impact_dir, fault), fault)["fault"][
                "tiers"
            ].items()
        }
        for tier, severity in attrs["tiers"].items():
            group = groups[severity_key(severity)]
            onset, offset = attrs["spec"]["onset"], attrs["spec"]["offset"]
            per_episode = episode_metrics(
                group["scores"], twins, group["labels"], threshold, onset, offset,
                params.metrics, detector, latency,
            )  # fmt: skip
            detected = _per_stream_detections(group["scores"], threshold, onset, tiers.k, latency)
            point = operating(
                group["scores"], audit, threshold, onset,
                alpha=tiers.alpha, k=tiers.k, latency=latency, confidence=params.metrics.ci,
            )  # fmt: skip
            records.append({
                "kind": "anomaly",
                "detector": detector,
                "injector": fault,
                "tier": tier,
                "severity": float(severity),
                "verified": bool(verification.get(tier, False)),
                "mode": "online",
                "latency": latency,
                "metrics": summarise(per_episode, params.metrics, seed=params.seed),
                "episodes": {
                    "matched_auroc": _rounded(per_episode["matched_auroc"]),
                    detection_metric(tiers.k): _rounded(detected),
                },
                "operating_point": point.as_dict(),
            })  # fmt: skip
    return records


def _minimum_detectable_impact(
    records: list[dict], impacts: Mapping[str, dict], k: int
) -> dict[str, dict[str, dict[str, float | str | dict[str, float]]]]:
    """detector -> fault -> {criterion: the return loss 1 − R̃ at which it reaches 0.9}."""
    from oodrl.protocol.impact import BEYOND_RANGE, impact_curve_points, minimum_detectable_impact

    by_cell: dict[tuple[str, str], list[dict]] = {}
    for record in records:
        by_cell.setdefault((record["detector"], record["injector"]), []).append(record)
    table: dict[str, dict[str, dict[str, float | str | dict[str, float]]]] = {}
    for (detector, fault), cell in sorted(by_cell.items()):
        xs, ys = impact_curve_points(impacts[fault]["fault"])
        steps = impacts[fault]["fault"].get("severity_steps")
        cell = sorted(cell, key=lambda r: r["severity"])
        severities = [r["severity"] for r in cell]
        criteria = {
            "matched_auroc": [r["metrics"]["matched_auroc"]["mean"] for r in cell],
            detection_metric(k): [r["operating_point"]["detection_rate"] for r in cell],
        }
        table.setdefault(detector, {})[fault] = {
            name: minimum_detectable_impact(xs, ys, severities, values, MDI_TARGET, steps)
            if severities
            else BEYOND_RANGE
            for name, values in criteria.items()
        }
    return table


def _impact_summary(document: Mapping[str, Any]) -> dict[str, Any]:
    """A fault's impact record as tier results carry it: the returns, the tiers and the curve
    (the leaderboard page draws it with each tier's severity, SPEC §21)."""
    fault = document["fault"]
    steps = {"severity_steps": fault["severity_steps"]} if fault.get("severity_steps") else {}
    return {
        "clean_return": document["clean_return"],
        "random_return": document["random_return"],
        "tiers": fault["tiers"],
        "curve": fault["curve"],
        **steps,
    }


def _false_alarm_audit(records: list[dict]) -> dict[str, dict[str, Any]]:
    """Per detector, the false-alarm rate its per-stream threshold achieves on the audit
    streams (every record of a detector holds the same, from one threshold)."""
    audit = {}
    for r in records:
        point = r["operating_point"]
        audit[r["detector"]] = {
            "threshold": point["threshold"],
            "rate": point["clean_false_alarm_rate"],
            "ci": point["clean_false_alarm_ci"],
            "n_alarmed": round(point["clean_false_alarm_rate"] * point["n_clean"]),
            "n_streams": point["n_clean"],
        }
    return audit


def compute_tier_results(params: Params, scores_dir: Path, impact_dir: Path) -> dict[str, Any]:
    """tier_results.yaml's content (sorted records, the impact tiers, the stamp)."""
    from oodrl.metrics.stamp import protocol_stamp
    from oodrl.parallel import ordered_map

    impacts = {f: read_impact(impact_path(impact_dir, f), f) for f in params.benchmark.injectors}
    detectors = params.benchmark.detectors
    jobs = [(params, scores_dir, impact_dir, d) for d in detectors]
    parts = ordered_map(_detector_records, jobs, params.executor.resolved_workers)
    records = sorted(
        (r for part in parts for r in part),
        key=lambda r: (r["detector"], r["injector"], r["severity"]),
    )
    return {
        **protocol_stamp(params),
        "alpha": params.tiers.alpha,
        "k": params.tiers.k,
        "false_alarm_audit": _false_alarm_audit(records),
        "records": records,
        "impact": {fault: _impact_summary(doc) for fault, doc in impacts.items()},
        "minimum_detectable_impact": _minimum_detectable_impact(records, impacts, params.tiers.k),
    }


def impact_document(params: Params, impact_dir: Path) -> dict[str, Any]:
    """Every fault's impact record in one document, as `oodrl.report.impact.impact_table` and
    `plot_impact_curves` take it."""
    docs = {f: read_impact(impact_path(impact_dir, f), f) for f in params.benchmark.injectors}
    first = next(iter(docs.values()))
    shared = {k: v for k, v in first.items() if k not in ("faults", "fault")}
    return {**shared, "faults": {f: doc["fault"] for f, doc in docs.items()}}


def tier_tables(document: Mapping[str, Any], impact: Mapping[str, Any]) -> str:
    """Markdown: the tiers' severities per fault, then per tier the detection rate at α
    (with its CI), the median delay of the streams detected within K with their count ("—"
    below 5) and the matched AUROC of every (detector, fault)."""
    from oodrl.metrics.operating import delay_text
    from oodrl.protocol.impact import LEVELS
    from oodrl.report.impact import impact_table

    k, alpha = document["k"], document["alpha"]
    levels = " / ".join(f"{level:g}" for level in LEVELS.values())
    lines = ["# Impact tiers and detection at a false-alarm budget", "",
             f"## Tier severities (normalised return R̃ falls to {levels})", "",
             impact_table(impact).rstrip("\n"), ""]  # fmt: skip
    audit = document.get("false_alarm_audit") or {}
    if audit:
        n = next(iter(audit.values()))["n_streams"]
        lines += [
            f"## Achieved false-alarm rate on {n} audit streams (α = {alpha:g})",
            "",
            "Clean streams used for nothing else (SPEC §19): the share that raises any alarm at "
            "the per-stream threshold, with its Clopper-Pearson 95% CI.",
            "",
            "| detector | false-alarm rate [95% CI] | streams alarmed |",
            "|---|---:|---:|",
            *(
                f"| {d} | {a['rate']:.3f} [{a['ci'][0]:.3f}, {a['ci'][1]:.3f}] | "
                f"{a['n_alarmed']} of {a['n_streams']} |"
                for d, a in sorted(audit.items())
            ),
            "",
        ]
    by_tier: dict[str, list[dict]] = {}
    for record in document["records"]:
        by_tier.setdefault(record["tier"], []).append(record)
    for tier in LEVELS:
        rows = by_tier.get(tier, [])
        if not rows:
            continue
        cost = " (harmless shifts: a detection here is a false alarm)" if tier == "benign" else ""
        lines += [
            f"## {tier}: detection_rate@{k} at α = {alpha:g} [95% CI], median delay, matched "
            f"AUROC{cost}",
            "",
            "| detector | fault | σ | detection rate (n streams) | median delay (n detected) "
            "| matched AUROC |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for r in rows:
            point = r["operating_point"]
            low, high = point["detection_rate_ci"]
            mark = "" if r.get("verified", True) else " ✗"
            lines.append(
                f"| {r['detector']} | {r['injector']}{mark} | {r['severity']:.4g} | "
                f"{point['detection_rate']:.2f} [{low:.2f}, {high:.2f}] ({point['n_faulty']}) | "
                f"{delay_text(point['delay'])} | "
                f"{r['metrics']['matched_auroc']['mean']:.3f} |"
            )
        lines.append("")
    if any(not r.get("verified", True) for r in document["records"]):
        lines += ["✗: the tier's verification missed its level; left out of tier aggregates.", ""]
    return "\n".join(lines)
