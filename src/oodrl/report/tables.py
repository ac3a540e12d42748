"""Markdown tables of SPEC §7 from results.yaml and sweep_results.yaml contents.

`results` is the mapping of results.yaml: `{"records": [{kind, detector, anomaly, mode,
severity, latency, metrics: {name: {mean, std, ci_low, ci_high, n_episodes}}}, ...]}` with
`kind` "anomaly" or "null" (`latency`, the detector's look-ahead in steps, may be missing in
files written before it existed). `sweep` is the mapping of sweep_results.yaml:
`{"sweep": {injector: {severity: {detector: {name: stats}}}}, "modes": {injector: mode}}`.
`cost` is the `cost:` mapping of run_meta.yaml: `{detector: {fit_s, fitted_bytes,
step_us_median, step_us_p99}}`. A metric missing from a record is shown as "—". Which
detector is "best" follows the metric's `higher_is_better`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from oodrl.metrics import higher_is_better

MISSING = "—"

#: The headline figure metrics.json holds per detector (its mean over anomalies), so that
#: `dvc exp show` and `dvc metrics diff` compare runs in a few columns; results.yaml keeps the rest.
HEADLINE_METRIC = "matched_auroc"
#: results.yaml's list of the detectors not certified machine-independent (SPEC §14, §17: they
#: run a library's own kernels, or are plugins); absent when every detector is certified.
UNCERTIFIED = "uncertified_detectors"
#: Marks an uncertified detector's name in the tables.
UNCERTIFIED_MARK = " †"

#: Human names of metrics. AUPRC is average precision (the step-wise area), and says so.
LABELS = {
    "matched_auroc": "matched AUROC",
    "matched_auprc": "matched AUPRC (AP)",
    "matched_fpr95": "matched FPR95",
    "detection_delay": "detection delay",
}

AnomalyKey = tuple[str, str, Any]  # (injector, mode, severity): one anomaly condition


# ---------------------------------------------------------------------------------- record access


def anomaly_records(results: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [r for r in results.get("records", []) if r.get("kind", "anomaly") == "anomaly"]


def null_records(results: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [r for r in results.get("records", []) if r.get("kind") == "null"]


def stat(record: Mapping[str, Any], metric: str, field: str = "mean") -> float | None:
    """One number of one metric of a record; None when the record lacks it."""
    value = record.get("metrics", {}).get(metric, {}).get(field)
    return None if value is None else float(value)


def record_injector(record: Mapping[str, Any]) -> str | None:
    """The injector of a results record; files written before `injector` call it `anomaly`."""
    return record["injector"] if "injector" in record else record.get("anomaly")


def anomaly_key(record: Mapping[str, Any]) -> AnomalyKey:
    return (record_injector(record), record["mode"], record["severity"])


def anomaly_keys(records: Iterable[Mapping[str, Any]]) -> list[AnomalyKey]:
    """Distinct anomalies, post-hoc ones first, then by name and severity."""
    keys = {anomaly_key(r) for r in records}
    return sorted(keys, key=lambda k: (k[1] != "posthoc", k[1], k[0], k[2] or 0.0))


def anomaly_labels(keys: Sequence[AnomalyKey]) -> dict[AnomalyKey, str]:
    """The anomaly name, with mode and σ only where one name occurs more than once."""
    names = [k[0] for k in keys]
    return {k: k[0] if names.count(k[0]) == 1 else f"{k[0]} ({k[1]}, σ={k[2]})" for k in keys}


def detectors(records: Iterable[Mapping[str, Any]]) -> list[str]:
    return sorted({r["detector"] for r in records})


def mean_over_anomalies(
    records: Sequence[Mapping[str, Any]], detector: str, metric: str
) -> float | None:
    """Mean over anomalies of a detector's per-anomaly means; None if no record has the metric."""
    values = [stat(r, metric) for r in records if r["detector"] == detector]
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def ranked(
    records: Iterable[Mapping[str, Any]], metric: str
) -> list[tuple[float, Mapping[str, Any]]]:
    """(value, record) best first by the metric's direction; ties broken by detector name."""
    sign = -1.0 if higher_is_better(metric) else 1.0
    scored = [(stat(r, metric), r) for r in records]
    scored = [(v, r) for v, r in scored if v is not None]
    return sorted(scored, key=lambda vr: (sign * vr[0], vr[1]["detector"]))


def best_first(values: Mapping[str, float | None], metric: str) -> list[str]:
    """Keys of `values` best first by the metric's direction; missing values last."""
    sign = -1.0 if higher_is_better(metric) else 1.0
    return sorted(values, key=lambda k: (values[k] is None, sign * (values[k] or 0.0), k))


def detector_means(records: Sequence[Mapping[str, Any]], metric: str) -> dict[str, float | None]:
    return {d: mean_over_anomalies(records, d, metric) for d in detectors(records)}


def detector_latencies(records: Iterable[Mapping[str, Any]]) -> dict[str, int | None]:
    """Each detector's latency (steps of look-ahead) as its records state it; None if unstated."""
    latencies: dict[str, int | None] = {}
    for r in records:
        latencies.setdefault(r["detector"], r.get("latency"))
    return latencies


SweepSeries = tuple[list[float], list[float], list[float], list[float]]


def sweep_curves(
    sweep: Mapping[str, Any], metric: str = "matched_auroc"
) -> dict[str, dict[str, SweepSeries]]:
    """injector -> detector -> (severities, means, ci_lows, ci_highs), severities ascending;
    a missing CI bound falls back to the mean."""
    curves: dict[str, dict[str, SweepSeries]] = {}
    for injector, grid in sorted(sweep.get("sweep", {}).items()):
        per_detector: dict[str, SweepSeries] = {}
        for severity in sorted(grid, key=float):
            for detector, metrics in sorted(grid[severity].items()):
                record = {"metrics": metrics}
                mean = stat(record, metric)
                if mean is None:
                    continue
                low, high = stat(record, metric, "ci_low"), stat(record, metric, "ci_high")
                series = per_detector.setdefault(detector, ([], [], [], []))
                for values, value in zip(series, (float(severity), mean, low, high), strict=True):
                    values.append(mean if value is None else value)
        curves[injector] = per_detector
    return curves


def sweep_grid(
    per_detector: Mapping[str, SweepSeries],
) -> tuple[list[float], list[str], dict[tuple[str, float], float]]:
    """Severities, detectors and (detector, severity) -> mean of one injector's curves."""
    severities = sorted({x for xs, *_ in per_detector.values() for x in xs})
    lookup = {
        (d, x): mean
        for d, (xs, means, *_) in per_detector.items()
        for x, mean in zip(xs, means, strict=True)
    }
    return severities, sorted(per_detector), lookup


# ------------------------------------------------------------------------------------ formatting


def fmt(value: float | None, digits: int = 3) -> str:
    return MISSING if value is None else f"{value:.{digits}f}"


def fmt_ci(record: Mapping[str, Any], metric: str, digits: int = 3) -> str:
    mean, low, high = (stat(record, metric, f) for f in ("mean", "ci_low", "ci_high"))
    if mean is None:
        return MISSING
    if low is None or high is None:
        return fmt(mean, digits)
    return f"{mean:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def markdown_table(
    header: Sequence[str], rows: Sequence[Sequence[str]], align: str | None = None
) -> str:
    """A pipe table padded to column width (readable as plain text). `align` has one letter per
    column, "l" or "r"; the default is the first column left, the others right."""
    align = align or "l" + "r" * (len(header) - 1)
    widths = [max(len(str(c)) for c in column) for column in zip(header, *rows, strict=True)]
    widths = [max(w, 3) for w in widths]

    def line(cells: Sequence[str]) -> str:
        padded = [
            str(c).rjust(w) if a == "r" else str(c).ljust(w)
            for c, w, a in zip(cells, widths, align, strict=True)
        ]
        return "| " + " | ".join(padded) + " |"

    rule = [
        "-" * (w - 1) + ":" if a == "r" else "-" * w for w, a in zip(widths, align, strict=True)
    ]
    return "\n".join(
        [line(header), "|" + "|".join(f" {r} " for r in rule) + "|"] + [line(r) for r in rows]
    )


# ---------------------------------------------------------------------------------------- tables


def marked(detector: str, uncertified: Iterable[str]) -> str:
    """The detector's name, marked when it is not certified machine-independent."""
    return detector + UNCERTIFIED_MARK if detector in uncertified else detector


def certification_note(uncertified: Sequence[str]) -> str:
    return (
        f"{UNCERTIFIED_MARK.strip()} not certified machine-independent (docs/SPEC.md §14, §17): "
        f"{', '.join(uncertified)} run a library's own kernels or are plugins, so their scores "
        "may differ on another CPU. Every other detector is certified."
    )


def headline_table(results: Mapping[str, Any]) -> str:
    """Per-detector mean matched AUROC / AUPRC (AP) over anomalies, best first (for the README)."""
    records = anomaly_records(results)
    aurocs = detector_means(records, "matched_auroc")
    auprcs = detector_means(records, "matched_auprc")
    uncertified = results.get(UNCERTIFIED) or []
    counts = {d: str(sum(r["detector"] == d for r in records)) for d in aurocs}
    rows = [
        [marked(d, uncertified), fmt(aurocs[d]), fmt(auprcs[d]), counts[d]]
        for d in best_first(aurocs, "matched_auroc")
    ]
    header = ["detector", LABELS["matched_auroc"], LABELS["matched_auprc"], "anomalies"]
    return markdown_table(header, rows)


def best_per_anomaly_table(results: Mapping[str, Any]) -> str:
    """Per anomaly: the best detector by matched AUROC (with its CI) and the runner-up."""
    records = anomaly_records(results)
    keys = anomaly_keys(records)
    labels = anomaly_labels(keys)
    rows = []
    for key in keys:
        ranking = ranked([r for r in records if anomaly_key(r) == key], "matched_auroc")
        if not ranking:
            continue
        best = ranking[0][1]
        runner_up = MISSING
        if len(ranking) > 1:
            runner_up = f"{ranking[1][1]['detector']} ({ranking[1][0]:.3f})"
        rows.append(
            [
                labels[key],
                key[1],
                fmt(key[2], 2),
                best["detector"],
                fmt_ci(best, "matched_auroc"),
                fmt(stat(best, "matched_auprc")),
                runner_up,
            ]
        )
    header = ["anomaly", "mode", "σ", "best detector", "matched AUROC [95% CI]"]
    return markdown_table([*header, LABELS["matched_auprc"], "runner-up"], rows, align="llrlrrl")


def per_detector_table(results: Mapping[str, Any], metric: str, title: str, digits: int) -> str:
    """A detector's mean of `metric` over anomalies, best first."""
    means = detector_means(anomaly_records(results), metric)
    rows = [[d, fmt(means[d], digits)] for d in best_first(means, metric)]
    return markdown_table(["detector", title], rows)


def delay_table(results: Mapping[str, Any]) -> str:
    """A detector's mean detection delay over anomalies, best first, beside its latency."""
    records = anomaly_records(results)
    means = detector_means(records, "detection_delay")
    latencies = detector_latencies(records)
    rows = [
        [d, MISSING if latencies[d] is None else str(latencies[d]), fmt(means[d], 1)]
        for d in best_first(means, "detection_delay")
    ]
    return markdown_table(["detector", "latency (steps)", "mean delay"], rows)


def best_auroc_versus_best_table(
    results: Mapping[str, Any], metric: str, title: str, digits: int
) -> str:
    """Per anomaly: the best-AUROC detector's value of `metric` against the best value of it."""
    records = anomaly_records(results)
    keys = anomaly_keys(records)
    labels = anomaly_labels(keys)
    rows = []
    for key in keys:
        group = [r for r in records if anomaly_key(r) == key]
        by_auroc, by_metric = ranked(group, "matched_auroc"), ranked(group, metric)
        if not by_auroc or not by_metric:
            continue
        top = by_auroc[0][1]
        rows.append(
            [
                labels[key],
                top["detector"],
                fmt(stat(top, metric), digits),
                by_metric[0][1]["detector"],
                fmt(by_metric[0][0], digits),
            ]
        )
    header = ["anomaly", "best-AUROC detector", title, f"best by {title}", title]
    return markdown_table(header, rows, align="llrlr")


def null_baseline_table(results: Mapping[str, Any]) -> str:
    """Null AUROC and clean alarm rate per detector and execution mode."""
    records = null_records(results)
    modes = sorted({r["mode"] for r in records}, key=lambda m: (m != "posthoc", m))
    header = ["detector"]
    for mode in modes:
        header += [f"null AUROC ({mode})", f"clean alarm rate ({mode})"]
    rows = []
    for d in detectors(records):
        row = [d]
        for mode in modes:
            record = next((r for r in records if r["detector"] == d and r["mode"] == mode), {})
            row += [fmt_ci(record, "null_auroc"), fmt(stat(record, "clean_alarm_rate"), 4)]
        rows.append(row)
    return markdown_table(header, rows)


def false_alarm_table(results: Mapping[str, Any]) -> str:
    """Per detector: its threshold rule's nominal clean false-alarm rate and the rates achieved
    on the clean evaluation episodes (share of steps; share of episodes with any alarm)."""
    thresholds = results.get("thresholds") or {}
    records = null_records(results)
    rows = []
    for d in detectors(records):
        record = next(r for r in records if r["detector"] == d)  # every mode: the same scores
        rule = thresholds.get(d, {})
        nominal = "—"
        if "nominal_rate" in rule:
            nominal = f"{100 * rule['nominal_rate']:.1f}% of {rule['per']}s"
        step, episode = stat(record, "clean_alarm_rate"), stat(record, "clean_episode_alarm")
        rows.append([
            d, rule.get("rule", "—"), nominal,
            "—" if step is None else f"{100 * step:.2f}%",
            "—" if episode is None else f"{100 * episode:.0f}%",
        ])  # fmt: skip
    header = ["detector", "threshold rule", "nominal", "achieved: steps", "achieved: episodes"]
    return markdown_table(header, rows)


def sweep_tables(sweep: Mapping[str, Any], metric: str = "matched_auroc") -> str:
    """One table per injector: `metric` per detector × severity."""
    modes = sweep.get("modes", {})
    parts = [f"## Severity sweeps ({LABELS.get(metric, metric)})"]
    for injector, per_detector in sweep_curves(sweep, metric).items():
        severities, names, lookup = sweep_grid(per_detector)
        rows = [[d] + [fmt(lookup.get((d, x))) for x in severities] for d in names]
        header = ["detector"] + [f"σ={x:g}" for x in severities]
        mode = f" ({modes[injector]})" if injector in modes else ""
        parts += [f"### {injector}{mode}", markdown_table(header, rows)]
    return "\n\n".join(parts) + "\n"


def cost_table(
    cost: Mapping[str, Mapping[str, Any]],
    results: Mapping[str, Any] | None = None,
    max_us_per_step: float | None = None,
) -> str:
    """Each detector's cost (run_meta.yaml `cost:`) beside its mean matched AUROC (from
    `results`, if given), most accurate first (SPEC §13). With `max_us_per_step`, only the
    detectors whose median µs/step is at most that, and a line naming the most accurate one."""
    aurocs = detector_means(anomaly_records(results or {}), HEADLINE_METRIC)
    kept = {
        d: c
        for d, c in cost.items()
        if max_us_per_step is None or c["step_us_median"] <= max_us_per_step
    }
    order = best_first({d: aurocs.get(d) for d in kept}, HEADLINE_METRIC)
    header = [
        "detector", LABELS[HEADLINE_METRIC], "fit s", "size KiB", "µs/step median", "µs/step p99"
    ]  # fmt: skip
    rows = [
        [
            d,
            fmt(aurocs.get(d)),
            fmt(kept[d].get("fit_s"), 2),
            fmt(kept[d]["fitted_bytes"] / 1024, 1),
            fmt(kept[d]["step_us_median"], 1),
            fmt(kept[d]["step_us_p99"], 1),
        ]
        for d in order
    ]
    table = markdown_table(header, rows) + "\n"
    if max_us_per_step is None:
        return table
    budget = f"≤ {max_us_per_step:g} µs/step (median)"
    if not order:
        return f"No detector streams at {budget}.\n"
    best = order[0]
    if aurocs.get(best) is None:
        return f"{table}\nNo results.yaml beside it: the detectors at {budget} are not ranked.\n"
    return (
        f"{table}\nMost accurate at {budget}: {best} ({LABELS[HEADLINE_METRIC]} "
        f"{aurocs[best]:.3f}).\n"
    )


def render_tables(results: Mapping[str, Any], sweep: Mapping[str, Any] | None = None) -> str:
    """All tables of SPEC §7 as one markdown document (tables.md, `oodrl show`)."""
    sections = [
        "# oodrl results",
        "## Detectors: mean matched AUROC / AUPRC (AP) over anomalies",
        "AUPRC is average precision (AP): the step-wise area under the precision-recall curve.",
        headline_table(results),
        "## Best detector per anomaly (by matched AUROC)",
        best_per_anomaly_table(results),
        "## Detection delay",
        "Steps from the onset t* to the first alarm the detector could have raised: an alarm on "
        "the score of step t counts at t + latency, the steps of the future that score uses "
        "(1 for a score of s_{t+1}, H for lyapunov_divergence's horizon). T − t* when there is "
        "no alarm.",
        delay_table(results),
        best_auroc_versus_best_table(results, "detection_delay", "delay", 1),
        "## Matched FPR at 95% TPR",
        "On the interpolated ROC curve: a score tied with the threshold counts as a fraction "
        "(docs/SPEC.md §6).",
        per_detector_table(results, "matched_fpr95", "matched FPR95", 3),
        best_auroc_versus_best_table(results, "matched_fpr95", "FPR95", 3),
        "## Null baseline (clean evaluation trajectories, counterfactual labels)",
        null_baseline_table(results),
        "## False alarms on the clean evaluation set",
        "What each detector's threshold rule promises on clean data (calibrated on the "
        "held-out ID episodes) against what it does: the share of clean steps that alarm and "
        "the share of clean episodes with any alarm (docs/SPEC.md §13).",
        false_alarm_table(results),
    ]
    if results.get(UNCERTIFIED):
        sections += ["## Machine independence", certification_note(results[UNCERTIFIED])]
    text = "\n\n".join(sections) + "\n"
    return text + "\n" + sweep_tables(sweep) if sweep else text


# ------------------------------------------------------------------------------------ metrics.json


def _round(value: float) -> float:
    return round(float(value), 6) + 0.0


def metrics_json(results: Mapping[str, Any]) -> dict[str, Any]:
    """The headline figures for `dvc exp show` / `dvc metrics diff`, rounded to 6 decimals.

    `{HEADLINE_METRIC: {detector: mean over anomalies}}`: one column per detector, so that a
    comparison of runs fits a terminal. Every other number stays in results.yaml and
    sweep_results.yaml (`oodrl show` renders them).
    """
    means = detector_means(anomaly_records(results), HEADLINE_METRIC)
    return {HEADLINE_METRIC: {d: _round(v) for d, v in sorted(means.items()) if v is not None}}
