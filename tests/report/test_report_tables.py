"""Markdown tables and metrics.json from a small hand-made results dict."""

import json

from oodrl.report.tables import (
    false_alarm_table,
    headline_table,
    markdown_table,
    metrics_json,
    render_tables,
    sweep_tables,
)


def stats(mean):
    return {
        "mean": mean,
        "std": 0.1,
        "ci_low": mean - 0.05,
        "ci_high": mean + 0.05,
        "n_episodes": 20,
    }


LATENCY = {"a": 0, "b": 5}


def record(detector, anomaly, mode="posthoc", severity=0.5, kind="anomaly", **metrics):
    return {
        "kind": kind,
        "detector": detector,
        "injector": anomaly,
        "mode": mode,
        "severity": severity,
        "latency": LATENCY[detector],
        "metrics": {name: stats(value) for name, value in metrics.items()},
    }


# a: best on noise, fast on stuck; b: best on stuck, fastest on noise, better mean AUROC.
SMALL = {
    "records": [
        record("a", "noise", matched_auroc=0.9, matched_auprc=0.8, detection_delay=30.0,
               matched_fpr95=0.2, clean_alarm_rate=0.01),
        record("a", "stuck", "online", matched_auroc=0.6, matched_auprc=0.6,
               detection_delay=5.0, matched_fpr95=0.3, clean_alarm_rate=0.03),
        record("b", "noise", matched_auroc=0.7, matched_auprc=0.7, detection_delay=2.0,
               matched_fpr95=0.1, clean_alarm_rate=0.02),
        record("b", "stuck", "online", matched_auroc=0.85, matched_auprc=0.9,
               detection_delay=50.0, matched_fpr95=0.5, clean_alarm_rate=0.02),
        record("a", "null", "posthoc", None, "null", null_auroc=0.52, clean_alarm_rate=0.011),
        record("b", "null", "online", None, "null", null_auroc=0.48, clean_alarm_rate=0.021),
    ]
}  # fmt: skip

SWEEP = {
    "modes": {"noise": "posthoc"},
    "sweep": {
        "noise": {
            0.2: {"a": {"matched_auroc": stats(0.6)}, "b": {"matched_auroc": stats(0.55)}},
            0.1: {"a": {"matched_auroc": stats(0.5)}},
        }
    },
}


def table_after(text, heading):
    """The rows (as lists of cells) of the first table after a line starting with `heading`."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    rows = []
    for line in lines[start + 1 :]:
        if line.startswith("|"):
            rows.append([c.strip() for c in line.strip("|").split("|")])
        elif rows:
            break
    return rows[0], rows[2:]


def table_with(text, header_start):
    """(header, rows) of the first table whose header row starts with `header_start`."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    return table_after("\n".join(lines[start - 1 :]), lines[start - 1])


def test_headline_table_ranks_detectors_by_mean_matched_auroc():
    header, rows = table_after("x\n" + headline_table(SMALL), "x")
    assert header == ["detector", "matched AUROC", "matched AUPRC (AP)", "anomalies"]
    assert rows == [["b", "0.775", "0.800", "2"], ["a", "0.750", "0.700", "2"]]


def test_best_detector_per_anomaly():
    _, rows = table_after(render_tables(SMALL), "## Best detector")
    assert rows[0][:4] == ["noise", "posthoc", "0.50", "a"]
    assert rows[0][4] == "0.900 [0.850, 0.950]"
    assert rows[0][6] == "b (0.700)"
    assert rows[1][:4] == ["stuck", "online", "0.50", "b"]


def test_every_auprc_label_says_average_precision():
    text = render_tables(SMALL, SWEEP)
    assert text.count("AUPRC") == text.count("AUPRC (AP)") + text.count("AUPRC is average")
    assert "AUPRC (AP)" in headline_table(SMALL)


def test_delay_tables_compare_best_auroc_with_fastest_and_state_the_latency():
    text = render_tables(SMALL)
    assert "counts at t + latency" in text
    header, per_detector = table_with(text, "| detector | latency")
    assert header == ["detector", "latency (steps)", "mean delay"]
    assert per_detector == [["a", "0", "17.5"], ["b", "5", "26.0"]]  # lower is better
    per_anomaly = [r for r in text.split("\n\n") if "best-AUROC detector" in r and "delay" in r][0]
    _, rows = table_after("x\n" + per_anomaly, "x")
    assert rows == [["noise", "a", "30.0", "b", "2.0"], ["stuck", "b", "50.0", "a", "5.0"]]


def test_fpr95_tables_prefer_lower_values():
    text = render_tables(SMALL)
    _, per_detector = table_after(text, "## Matched FPR")
    assert per_detector == [["a", "0.250"], ["b", "0.300"]]
    per_anomaly = [r for r in text.split("\n\n") if "best by FPR95" in r][0]
    _, rows = table_after("x\n" + per_anomaly, "x")
    assert rows == [["noise", "a", "0.200", "b", "0.100"], ["stuck", "b", "0.500", "a", "0.300"]]


def test_null_baseline_per_detector_and_mode():
    header, rows = table_after(render_tables(SMALL), "## Null baseline")
    assert header == [
        "detector",
        "null AUROC (posthoc)",
        "clean alarm rate (posthoc)",
        "null AUROC (online)",
        "clean alarm rate (online)",
    ]
    assert rows[0] == ["a", "0.520 [0.470, 0.570]", "0.0110", "—", "—"]
    assert rows[1] == ["b", "—", "—", "0.480 [0.430, 0.530]", "0.0210"]


def test_sweep_tables():
    text = sweep_tables(SWEEP)
    assert "### noise (posthoc)" in text
    header, rows = table_after(text, "### noise")
    assert header == ["detector", "σ=0.1", "σ=0.2"]
    assert rows == [["a", "0.500", "0.600"], ["b", "—", "0.550"]]
    assert render_tables(SMALL, SWEEP).endswith(text)
    assert "Severity sweeps" not in render_tables(SMALL)


def test_duplicate_anomaly_names_get_mode_and_severity():
    results = {
        "records": [
            record("a", "noise", severity=0.2, matched_auroc=0.6),
            record("a", "noise", severity=0.8, matched_auroc=0.9),
        ]
    }
    _, rows = table_after(render_tables(results), "## Best detector")
    assert [r[0] for r in rows] == ["noise (posthoc, σ=0.2)", "noise (posthoc, σ=0.8)"]


def test_missing_metrics_render_as_dashes():
    results = {"records": [record("a", "noise", matched_auroc=0.6)]}
    text = render_tables(results)
    _, rows = table_after(text, "## Detectors")
    assert rows == [["a", "0.600", "—", "1"]]
    assert "## Detection delay" in text
    # A results file from before latencies were recorded shows a dash.
    del results["records"][0]["latency"]
    _, rows = table_with(render_tables(results), "| detector | latency")
    assert rows == [["a", "—", "—"]]


def test_markdown_table_alignment():
    table = markdown_table(["name", "value"], [["x", "1.0"], ["long name", "10.25"]])
    assert table.splitlines() == [
        "| name      | value |",
        "| --------- | ----: |",
        "| x         |   1.0 |",
        "| long name | 10.25 |",
    ]


def test_metrics_json_holds_only_the_headline_figures():
    data = metrics_json(SMALL)
    assert data == {"matched_auroc": {"a": 0.75, "b": 0.775}}
    assert json.dumps(data) == json.dumps(data, sort_keys=True)


def test_tables_render_the_realistic_fixture(results, sweep):
    text = render_tables(results, sweep)
    assert text.count("### ") == 9  # one sweep table per injector
    assert text == render_tables(results, sweep)
    headline = metrics_json(results)["matched_auroc"]
    assert len(headline) == 8
    assert all(v == round(v, 6) for v in headline.values())


def test_false_alarm_table_sets_nominal_beside_achieved():
    results = {
        "records": [
            record("a", None, "posthoc", None, "null", clean_alarm_rate=0.034,
                   clean_episode_alarm=0.45),
            record("b", None, "posthoc", None, "null", clean_alarm_rate=0.002,
                   clean_episode_alarm=0.1),
        ],
        "thresholds": {
            "a": {"rule": "percentile", "nominal_rate": 0.01, "per": "step"},
            "b": {"rule": "max", "nominal_rate": 1 / 7, "per": "episode"},
        },
    }  # fmt: skip
    rows = {line.split("|")[1].strip(): line for line in false_alarm_table(results).splitlines()}
    assert [c.strip() for c in rows["a"].split("|")[2:6]] == [
        "percentile", "1.0% of steps", "3.40%", "45%"
    ]  # fmt: skip
    assert [c.strip() for c in rows["b"].split("|")[2:6]] == [
        "max", "14.3% of episodes", "0.20%", "10%"
    ]  # fmt: skip


def test_results_written_before_the_injector_rename_render_alike():
    old = json.loads(json.dumps(SMALL))
    for entry in old["records"]:
        entry["anomaly"] = entry.pop("injector") or "null"
    assert render_tables(old, SWEEP) == render_tables(SMALL, SWEEP)
