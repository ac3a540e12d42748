"""oodrl.load_results (SPEC §25): the committed results as tidy DataFrames, checked against the
files read independently; the API's lazy imports; its one-line errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
import yaml

import oodrl
from oodrl.api.results import COLUMNS
from oodrl.errors import ConfigError, StoreError
from oodrl.metrics.tier_results import load_tier_results, tier_results_path

KEYS = ["env", "policy", "fault", "tier", "detector", "metric"]


def _yaml(path):
    return yaml.load(path.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


@pytest.fixture(scope="module")
def board_json(repo_root):
    return json.loads((repo_root / "pipeline/suite/reports/leaderboard.json").read_text())


@pytest.fixture(scope="module")
def board(repo_root):
    return oodrl.load_results(repo_root / "pipeline" / "suite")


def _one(frame, **match):
    rows = frame
    for key, value in match.items():
        rows = rows[rows[key] == value]
    assert len(rows) == 1, match
    return rows.iloc[0]


def test_import_oodrl_stays_light_and_offers_the_api():
    code = (
        "import sys, oodrl, oodrl.api; "
        "heavy = [m for m in ('pandas', 'numpy', 'torch') if m in sys.modules]; "
        "assert not heavy, heavy; "
        "assert set(oodrl.api.__all__) <= set(dir(oodrl)); "
        "print(oodrl.load_results.__module__, oodrl.evaluate.__module__)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["oodrl.api.results", "oodrl.api.evaluation"]


def test_api_names_are_the_plugin_authors_objects():
    from oodrl.core.detector import BaseDetector
    from oodrl.monitor import OodMonitor, run_monitor
    from oodrl.testing import check_detector

    assert oodrl.BaseDetector is BaseDetector
    assert oodrl.check_detector is check_detector
    assert oodrl.OodMonitor is OodMonitor and oodrl.run_monitor is run_monitor
    assert sorted(oodrl.api.__all__) == sorted(
        ["BaseDetector", "OodMonitor", "check_detector", "evaluate", "load_results", "run_monitor"]
    )
    for name in ("evaluate", "load_results"):  # numpy-style docstrings (the API reference)
        doc = getattr(oodrl, name).__doc__
        assert all(part in doc for part in ("Parameters\n", "Returns\n", "Raises\n")), name
    with pytest.raises(AttributeError):
        oodrl.api.no_such_name  # noqa: B018


def test_suite_leaderboard_is_one_row_per_cell_detector_and_metric(board, board_json):
    assert list(board.columns) == list(COLUMNS)
    expected = sum(
        1 + (5 if "operating_point" in evidence else 0)
        for cell in board_json["cells"]
        for evidence in cell["evidence"].values()
    )
    assert len(board) == expected
    assert not board.duplicated(KEYS).any()
    assert board.attrs["protocol_version"] == board_json["protocol_version"]
    cell = next(c for c in board_json["cells"] if c["tier"] == "mild")
    detector = sorted(cell["evidence"])[0]
    evidence = cell["evidence"][detector]
    where = {"env": cell["environment"], "policy": cell["policy"], "fault": cell["fault"],
             "tier": "mild", "detector": detector}  # fmt: skip
    point = evidence["operating_point"]
    row = _one(board, **where, metric=f"detection_rate@{point['k']}")
    assert (row.value, row.ci_low, row.ci_high, row.n_streams) == (
        point["detection_rate"],
        *point["detection_rate_ci"],
        point["n_faulty"],
    )
    assert row.value == cell["scores"][f"detection_rate@{point['k']}"][detector]
    auroc = _one(board, **where, metric="matched_auroc")
    assert (auroc.value, auroc.ci_low, auroc.ci_high) == tuple(
        evidence["matched_auroc"][k] for k in ("mean", "ci_low", "ci_high")
    )
    assert auroc.family == cell["family"] and auroc.severity == evidence["severity"]


def test_suite_ranking_is_the_leaderboards_aggregates_best_first(repo_root, board_json):
    ranking = oodrl.load_results(repo_root / "pipeline/suite", kind="ranking")
    overall = ranking[ranking.env.isna()]
    assert set(overall.statistic) == {"iqm", "mean"}
    for (tier, metric, statistic), rows in overall.groupby(["tier", "metric", "statistic"]):
        stats = board_json[statistic][metric][tier]
        assert sorted(rows.detector) == sorted(stats)
        quietest_first = tier in board_json["lower_is_better"][metric]
        assert list(rows.value) == sorted(rows.value, reverse=not quietest_first)
        assert set(rows.n_cells) == {board_json["n_cells"][metric][tier]}
        for row in rows.itertuples():
            assert (row.value, row.ci_low, row.ci_high) == tuple(
                stats[row.detector][k] for k in ("value", "ci_low", "ci_high")
            )
    scoped = ranking[ranking.env.notna()]
    assert set(scoped.env) == {
        "|".join(g["environments"])
        for tiers in board_json["iqm_where_more_detectors_run"].values()
        for groups in tiers.values()
        for g in groups
    }


def test_a_pipelines_results_are_its_records_metrics(repo_root):
    document = _yaml(repo_root / "reports/results.yaml")
    frame = oodrl.load_results(repo_root)
    assert len(frame) == sum(len(r["metrics"]) for r in document["records"])
    assert set(frame.env) == {"LunarLander-v3"} and set(frame.policy) == {"0"}
    assert set(frame.tier) == {"headline", "null"}
    record = next(r for r in document["records"] if r["kind"] == "anomaly")
    stats = record["metrics"]["matched_auroc"]
    row = _one(frame, fault=record["injector"], tier="headline", detector=record["detector"],
               mode=record["mode"], metric="matched_auroc")  # fmt: skip
    assert (row.value, row.ci_low, row.ci_high, row.n_streams, row.severity) == (
        stats["mean"],
        stats["ci_low"],
        stats["ci_high"],
        stats["n_episodes"],
        record["severity"],
    )
    assert frame.attrs["params_hash"] == document["params_hash"]
    by_file = oodrl.load_results(repo_root / "reports" / "results.yaml")
    assert by_file.equals(frame)


def test_a_pipelines_tiers_hold_the_operating_points(repo_root):
    document = load_tier_results(repo_root)  # protocol 4's YAML until the root is rebuilt
    frame = oodrl.load_results(repo_root, kind="tiers")
    k = document["k"]
    # Five rows a rule's operating point (the time-aware rule's from protocol version 4, where a
    # record has it), then the per-episode metrics.
    expected = sum(
        5 * (1 + bool((r.get("time_aware") or {}).get("operating_point"))) + len(r["metrics"])
        for r in document["records"]
    )
    assert len(frame) == expected and not frame.duplicated(KEYS).any()
    for record in document["records"][:40]:
        where = {"fault": record["injector"], "tier": record["tier"],
                 "detector": record["detector"]}  # fmt: skip
        point = record["operating_point"]
        rate = _one(frame, **where, metric=f"detection_rate@{k}")
        assert (rate.value, [rate.ci_low, rate.ci_high], rate.n_streams) == (
            point["detection_rate"],
            point["detection_rate_ci"],
            point["n_faulty"],
        )
        assert rate.verified == record["verified"] and rate.severity == record["severity"]
        median = _one(frame, **where, metric=f"delay_median@{k}")
        shown = point["delay"]["median"]
        assert math.isnan(median.value) if shown is None else median.value == shown
        assert median.n_streams == point["delay"]["n_detected"]
        alarms = _one(frame, **where, metric="clean_false_alarm_rate")
        assert alarms.value == point["clean_false_alarm_rate"] and alarms.n_streams == 200


def test_a_pipelines_sweep_is_every_severity(repo_root):
    document = _yaml(repo_root / "reports/sweep_results.yaml")
    frame = oodrl.load_results(repo_root, kind="sweep")
    fault = sorted(document["sweep"])[0]
    severity = sorted(document["sweep"][fault])[-1]
    detector, metrics = sorted(document["sweep"][fault][severity].items())[0]
    row = _one(frame, fault=fault, severity=severity, detector=detector, metric="matched_auroc")
    assert row.value == metrics["matched_auroc"]["mean"] and row.tier == "sweep"
    assert row["mode"] == document["modes"][fault]
    assert len(frame) == sum(
        len(m) for s in document["sweep"].values() for d in s.values() for m in d.values()
    )


def test_names_find_the_suites_pipelines(monkeypatch, repo_root, tmp_path):
    monkeypatch.chdir(tmp_path)  # names resolve in the project of the installed checkout
    for where, policy in [("cartpole", "0"), ("CartPole-v1", "0"), ("cartpole_policy1", "1")]:
        frame = oodrl.load_results(where)
        assert set(frame.env) == {"CartPole-v1"} and set(frame.policy) == {policy}, where


@pytest.mark.parametrize(
    ("where", "kind", "error", "message"),
    [
        (".", "headline", ConfigError, "kind 'headline' is not a kind of results. Allowed: "
         "results, tiers, sweep, leaderboard, ranking."),
        ("no/such/dir", None, ConfigError, "where 'no/such/dir': no such file or directory. "
         "Allowed: a pipeline directory"),
        (".", "leaderboard", ConfigError, "kind 'leaderboard' is the suite's"),
        ("reports/results.yaml", "tiers", ConfigError, "kind 'tiers' does not match results.yaml"),
        ("params.yaml", None, ConfigError, "where 'params.yaml': not a results file by its name. "
         "Allowed: "),
        ("src", None, ConfigError, "where 'src': a directory that is neither a pipeline"),
    ],
)  # fmt: skip
def test_unknown_where_or_kind_is_one_line_naming_what_is_allowed(
    monkeypatch, repo_root, where, kind, error, message
):
    monkeypatch.chdir(repo_root)
    with pytest.raises(error) as raised:
        oodrl.load_results(where, kind=kind)
    assert str(raised.value).startswith(message)
    assert "\n" not in str(raised.value)


def test_a_broken_results_file_is_a_store_error(tmp_path):
    (tmp_path / "results.yaml").write_text("records: [1, 2\n")
    with pytest.raises(StoreError, match="not a YAML results file"):
        oodrl.load_results(tmp_path / "results.yaml")
    (tmp_path / "leaderboard.json").write_text('{"cells": 3}')
    with pytest.raises(StoreError, match="not the suite's leaderboard.json"):
        oodrl.load_results(tmp_path / "leaderboard.json")


def test_evaluate_reads_tier_results_impact_section_alone(repo_root):
    """`evaluate` reads only the tier results' `impact` section (of a protocol-4 YAML, parsed
    alone); it equals the whole file's."""
    path = tier_results_path(repo_root)
    whole = load_tier_results(path)
    assert load_tier_results(path, keys=["impact"]) == {"impact": whole["impact"]}
