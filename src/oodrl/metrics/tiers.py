"""Detection at impact tiers and a per-stream false-alarm budget (SPEC §15): the tier_metrics
stage's results, `reports/tier_results.json` (the file, and the loader that reads it or a
protocol-4 project's `reports/tier_results.yaml`: `oodrl.metrics.tier_results`; the stages that
feed it: `oodrl.protocol.tiers`).

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

Both per-stream rules (SPEC §24, `oodrl.metrics.time_aware`): `operating_point` is the constant
rule's (a stream's maximum score against the order statistic); `time_aware.operating_point` the
time-aware rule's, its standardiser fitted on the detector's scores of every stream of the ID set
(`scores/<detector>/id.zarr`, never the calibration or audit streams), its threshold the same
order statistic of the calibration streams' maxima of z, its false-alarm rate audited on the same
audit streams. Where the ID scores hold fewer than `time_aware.MIN_WINDOW_VALUES` (300) values,
or there are none, `time_aware.operating_point` is None and `time_aware.reason` says why (the
rest of the record is unchanged); `time_aware` also names the ID streams and values fitted on.
Each operating point's `delay` holds the median, 90th percentile and mean of the delays of the
streams detected within K, each None below 5 such streams (SPEC §19), and their count.
`alpha_curve` holds per rule (`constant`, `time_aware`; None where the rule has no operating
point) an entry per α of `time_aware.ALPHAS`: its own threshold, `detection_rate@K` with its CI,
the delays and the audited false-alarm rate with its CI, or `supported: False` with the reason
where the calibration streams cannot support that α under `tiers.threshold_rule`. `episodes`
keeps both rules' 0/1 detections per faulty stream (`detection_rate@K`,
`time_aware_detection_rate@K`), which the suite's leaderboard pairs stream by stream
(`oodrl.metrics.rule_change`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from oodrl.config import Params
from oodrl.io.layout import (
    CLEAN_GROUP,
    detector_stage,
    heldout_score_store,
    id_score_store,
    tier_score_store,
)
from oodrl.io.store import read_scores, severity_key
from oodrl.metrics.operating import per_stream_detections
from oodrl.protocol.tiers import impact_path, read_impact

#: The level matched AUROC and detection_rate@K must reach for the minimum detectable impact.
MDI_TARGET = 0.9


def detection_metric(k: int) -> str:
    """The per-stream detection metric's name: `detection_rate@100`."""
    return f"detection_rate@{k}"


def _rounded(values) -> list[float]:
    return [round(float(v), 6) + 0.0 for v in values]


def time_aware_detection_metric(k: int) -> str:
    """The time-aware rule's per-stream detections in a record's `episodes`:
    `time_aware_detection_rate@100` (beside the constant rule's `detection_rate@100`)."""
    from oodrl.metrics.leaderboard import time_aware_metric

    return time_aware_metric(detection_metric(k))


#: What an entry of a record's α curves keeps of `time_aware.alpha_curve`'s: the rule is the
#: curve's key, and K, the stream counts and the CI level are the record's operating point's.
CURVE_KEYS = (
    "alpha", "supported", "reason", "threshold", "detection_rate", "detection_rate_ci",
    "early_false_alarm_rate", "delay", "clean_false_alarm_rate", "clean_false_alarm_ci",
)  # fmt: skip


def _curve(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: r[k] for k in CURVE_KEYS if k in r} for r in records]


def _time_aware_fit(scores_dir: Path, detector: str):
    """The time-aware rule's standardiser from the detector's scores of the ID set (every
    stream of `scores/<detector>/id.zarr`), and what a record says of it: the streams and
    values it was fitted on, or why there is none (SPEC §24: fewer than `MIN_WINDOW_VALUES`
    values, or no such store). The reason names no host path (cells files hold none)."""
    from oodrl.metrics.time_aware import MIN_WINDOW_VALUES, fit_step_standardiser

    path = id_score_store(scores_dir, detector)
    if not path.is_file():
        reason = (
            f"no scores of the ID set ({detector}/id.zarr in the scores directory; the "
            f"score_clean stage writes them from --id)"
        )
        return None, {"fit_streams": None, "fit_values": None, "reason": reason}
    groups, _ = read_scores(path, stage=detector_stage(detector, "score_clean"))
    scores = groups[CLEAN_GROUP]["scores"]
    fit = {"fit_streams": int(scores.shape[0]), "fit_values": int(scores.size)}
    if scores.size < MIN_WINDOW_VALUES:
        reason = (
            f"{scores.size} ID scores ({scores.shape[0]} streams of {scores.shape[1]} steps); the "
            f"time-aware rule needs at least {MIN_WINDOW_VALUES}"
        )
        return None, {**fit, "reason": reason}
    return fit_step_standardiser(list(scores)), {**fit, "reason": None}


def detector_records(
    params: Params, scores_dir: Path, impact_dir: Path, detector: str
) -> list[dict[str, Any]]:
    """One detector's tier records, the `records` of tier results that are its own: one per
    fault (in `benchmark.injectors` order) and tier its tier scores hold, under both per-stream
    rules (SPEC §24): the constant rule's `operating_point` and the time-aware rule's
    (`time_aware.operating_point`, None with `time_aware.reason` where the ID scores cannot
    fit its standardiser), each rule's α curve, and both rules' per-stream detections. The
    cells stage stores them (`oodrl.metrics.cells`); `assemble_tier_results` merges every
    detector's."""
    from oodrl.metrics.aggregate import episode_metrics, summarise
    from oodrl.metrics.operating import per_stream_threshold
    from oodrl.metrics.time_aware import (
        alpha_curve,
        point_record,
        rule_operating_point,
        stream_detections,
        time_aware_threshold,
    )

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
    # streams' maxima, training-conditional or marginal; the time-aware rule takes the same
    # order statistic of the maxima of the calibration scores standardised per step by the ID
    # set's (SPEC §24).
    calibration = heldout("calibration")
    rule = {"delta": tiers.delta, "threshold_rule": tiers.threshold_rule}
    threshold = per_stream_threshold(
        calibration.max(axis=1), tiers.alpha, tiers.threshold_rule, tiers.delta
    )
    standardiser, fit = _time_aware_fit(scores_dir, detector)
    aware = None
    if standardiser is not None:
        aware = time_aware_threshold(standardiser, calibration, tiers.alpha, **rule)
    options = {"k": tiers.k, "latency": latency, "confidence": params.metrics.ci}
    records = []
    for fault in params.benchmark.injectors:
        groups, attrs = read_scores(
            tier_score_store(scores_dir, detector, fault),
            stage=detector_stage(detector, "score_variants"),
        )
        verification = {
            name: tier.get("verification", {}).get("verified", False)
            for name, tier in read_impact(impact_path(impact_dir, fault), fault)["fault"][
                "tiers"
            ].items()
        }
        for tier, severity in attrs["tiers"].items():
            group = groups[severity_key(severity)]
            faulty = group["scores"]
            onset, offset = attrs["spec"]["onset"], attrs["spec"]["offset"]
            per_episode = episode_metrics(
                faulty, twins, group["labels"], threshold, onset, offset,
                params.metrics, detector, latency,
            )  # fmt: skip
            detected = per_stream_detections(faulty, threshold, onset, tiers.k, latency)
            point = rule_operating_point(faulty, audit, threshold, onset, alpha=tiers.alpha,
                                         **options)  # fmt: skip
            episodes = {
                "matched_auroc": _rounded(per_episode["matched_auroc"]),
                detection_metric(tiers.k): _rounded(detected),
            }
            curves = {"constant": _curve(alpha_curve(calibration, faulty, audit, onset,
                                                     **rule, **options))}  # fmt: skip
            aware_point = None
            if standardiser is not None:
                episodes[time_aware_detection_metric(tiers.k)] = _rounded(
                    stream_detections(faulty, aware, onset, tiers.k, latency, standardiser)
                )
                aware_point = point_record(rule_operating_point(
                    faulty, audit, aware, onset, standardiser, alpha=tiers.alpha, **options
                ))  # fmt: skip
                curves["time_aware"] = _curve(alpha_curve(
                    calibration, faulty, audit, onset, standardiser=standardiser, **rule,
                    **options,
                ))  # fmt: skip
            else:
                curves["time_aware"] = None
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
                "episodes": episodes,
                "operating_point": point_record(point),
                "time_aware": {"operating_point": aware_point, **fit},
                "alpha_curve": curves,
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
    streams (every record of a detector holds the same, from one threshold); with records that
    hold the time-aware rule, its threshold's too under `time_aware` (or why it has none)."""
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
        if "time_aware" in r:
            aware = r["time_aware"]["operating_point"]
            audit[r["detector"]]["time_aware"] = (
                {"reason": r["time_aware"]["reason"]}
                if aware is None
                else {
                    "threshold": aware["threshold"],
                    "rate": aware["clean_false_alarm_rate"],
                    "ci": list(aware["clean_false_alarm_ci"]),  # a copy: no YAML anchor
                    "n_alarmed": round(aware["clean_false_alarm_rate"] * aware["n_clean"]),
                    "n_streams": aware["n_clean"],
                }
            )
    return audit


def compute_tier_results(params: Params, scores_dir: Path, impact_dir: Path) -> dict[str, Any]:
    """The tier results document from every benchmark detector's scores in `scores_dir` (the
    pipeline computes each detector's records in a stage of its own, `oodrl.metrics.cells`, and
    merges them with `assemble_tier_results`)."""
    from oodrl.parallel import ordered_map

    jobs = [(params, scores_dir, impact_dir, d) for d in params.benchmark.detectors]
    parts = ordered_map(detector_records, jobs, params.executor.resolved_workers)
    return assemble_tier_results(params, [r for part in parts for r in part], impact_dir)


def assemble_tier_results(params: Params, records: list[dict], impact_dir: Path) -> dict[str, Any]:
    """The tier results document from every detector's records: sorted, with the false-alarm
    audit, the faults' impact tiers, the minimum detectable impacts and the protocol stamp."""
    from oodrl.metrics.stamp import protocol_stamp

    impacts = {f: read_impact(impact_path(impact_dir, f), f) for f in params.benchmark.injectors}
    records = sorted(records, key=lambda r: (r["detector"], r["injector"], r["severity"]))
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


def _rate_text(point: Mapping[str, Any]) -> str:
    low, high = point["detection_rate_ci"]
    return f"{point['detection_rate']:.2f} [{low:.2f}, {high:.2f}]"


def _audit_text(entry: Mapping[str, Any]) -> tuple[str, str]:
    low, high = entry["ci"]
    return (
        f"{entry['rate']:.3f} [{low:.3f}, {high:.3f}]",
        f"{entry['n_alarmed']} of {entry['n_streams']}",
    )


def tier_tables(document: Mapping[str, Any], impact: Mapping[str, Any]) -> str:
    """Markdown: the tiers' severities per fault, then per tier the detection rate at α
    (with its CI), the median delay of the streams detected within K with their count ("—"
    below 5) and the matched AUROC of every (detector, fault). Where the records hold the
    time-aware rule (SPEC §24), the false-alarm audit and each tier's rows show both rules
    ("—" where a detector has no time-aware rule, its reason below the audit)."""
    from oodrl.metrics.operating import delay_text
    from oodrl.protocol.impact import LEVELS
    from oodrl.report.impact import impact_table

    k, alpha = document["k"], document["alpha"]
    both = any("time_aware" in r for r in document["records"])
    levels = " / ".join(f"{level:g}" for level in LEVELS.values())
    lines = ["# Impact tiers and detection at a false-alarm budget", "",
             f"## Tier severities (normalised return R̃ falls to {levels})", "",
             impact_table(impact).rstrip("\n"), ""]  # fmt: skip
    audit = document.get("false_alarm_audit") or {}
    if audit and not both:
        n = next(iter(audit.values()))["n_streams"]
        lines += [
            f"## Achieved false-alarm rate on {n} audit streams (α = {alpha:g})",
            "",
            "Clean streams used for nothing else (SPEC §19): the share that raises any alarm at "
            "the per-stream threshold, with its Clopper-Pearson 95% CI.",
            "",
            "| detector | false-alarm rate [95% CI] | streams alarmed |",
            "|---|---:|---:|",
            *(f"| {d} | {' | '.join(_audit_text(a))} |" for d, a in sorted(audit.items())),
            "",
        ]
    elif audit:
        n = next(iter(audit.values()))["n_streams"]
        rows, reasons = [], []
        for d, a in sorted(audit.items()):
            aware = a.get("time_aware") or {"reason": "no time-aware rule in its records"}
            if "reason" in aware:
                reasons.append(f"{d}: {aware['reason']}")
                aware_text = ("—", "—")
            else:
                aware_text = _audit_text(aware)
            rows.append(f"| {d} | {' | '.join((*_audit_text(a), *aware_text))} |")
        lines += [
            f"## Achieved false-alarm rate on {n} audit streams (α = {alpha:g})",
            "",
            "Clean streams used for nothing else (SPEC §19): the share that raises any alarm at "
            "the per-stream threshold, with its Clopper-Pearson 95% CI, under the constant rule "
            "(a stream's maximum score) and the time-aware rule (its maximum score standardised "
            "per step by the clean law of the detector's scores on the ID streams, SPEC §24).",
            "",
            "| detector | constant: false-alarm rate [95% CI] | streams alarmed "
            "| time-aware: false-alarm rate [95% CI] | streams alarmed |",
            "|---|---:|---:|---:|---:|",
            *rows,
            "",
            *([f"No time-aware rule (—): {'; '.join(reasons)}.", ""] if reasons else []),
        ]
    by_tier: dict[str, list[dict]] = {}
    for record in document["records"]:
        by_tier.setdefault(record["tier"], []).append(record)
    for tier in LEVELS:
        rows = by_tier.get(tier, [])
        if not rows:
            continue
        cost = " (harmless shifts: a detection here is a false alarm)" if tier == "benign" else ""
        if both:
            lines += [
                f"## {tier}: detection_rate@{k} at α = {alpha:g} [95% CI] and median delay under "
                f"the constant and the time-aware rule, matched AUROC{cost}",
                "",
                "| detector | fault | σ | constant: detection rate (n streams) | constant: "
                "median delay (n detected) | time-aware: detection rate | time-aware: median "
                "delay (n detected) | matched AUROC |",
                "|---|---|---:|---:|---:|---:|---:|---:|",
            ]
        else:
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
            mark = "" if r.get("verified", True) else " ✗"
            cells = [
                f"{r['detector']}", f"{r['injector']}{mark}", f"{r['severity']:.4g}",
                f"{_rate_text(point)} ({point['n_faulty']})", delay_text(point["delay"]),
            ]  # fmt: skip
            if both:
                aware = (r.get("time_aware") or {}).get("operating_point")
                cells += [_rate_text(aware), delay_text(aware["delay"])] if aware else ["—", "—"]
            cells.append(f"{r['metrics']['matched_auroc']['mean']:.3f}")
            lines.append(f"| {' | '.join(cells)} |")
        lines.append("")
    if any(not r.get("verified", True) for r in document["records"]):
        lines += ["✗: the tier's verification missed its level; left out of tier aggregates.", ""]
    return "\n".join(lines)
