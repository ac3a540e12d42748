"""The tier machinery of the suite (SPEC §15; the stages themselves: tests/pipeline)."""

from __future__ import annotations

import numpy as np
import pytest

from oodrl.errors import StoreError
from oodrl.io import yamlio
from oodrl.metrics.operating import per_stream_detections
from oodrl.metrics.tiers import detection_metric
from oodrl.protocol.tiers import read_tiers


def _impact_document(tiers: dict) -> dict:
    return {"faults": {"stuck_actuator": {"tiers": tiers, "curve": []}}, "clean_return": 1.0}


def test_read_tiers_keeps_the_reachable_ones_and_names_the_rest(tmp_path):
    path = tmp_path / "stuck_actuator.yaml"
    tiers = {
        "mild": {"level": 0.95, "severity": 0.2},
        "moderate": {"level": 0.9, "severity": 0.35},
        "severe": {"level": 0.75, "severity": "unreachable"},
    }
    path.write_text(yamlio.dump(_impact_document(tiers)))
    assert read_tiers(path, "stuck_actuator") == ({"mild": 0.2, "moderate": 0.35}, ["severe"])


def test_a_tier_a_search_did_not_reach_gets_no_streams(tmp_path):
    """Protocol 4's search names a level its probes ran out before reaching "not reached"
    (not "unreachable": nothing showed the fault cannot reach it); either has no severity, so
    no streams are collected there."""
    from oodrl.protocol.tier_search import NOT_REACHED

    path = tmp_path / "stuck_actuator.yaml"
    tiers = {
        "benign": {"level": 0.99, "severity": 0.05},
        "mild": {"level": 0.95, "severity": 0.2},
        "moderate": {"level": 0.9, "severity": NOT_REACHED},
        "severe": {"level": 0.75, "severity": "unreachable"},
    }
    path.write_text(yamlio.dump(_impact_document(tiers)))
    assert read_tiers(path, "stuck_actuator") == (
        {"benign": 0.05, "mild": 0.2},
        ["moderate", "severe"],
    )
    from oodrl.report.impact import impact_table

    check = {"normalised": 0.95, "ci": [0.94, 0.96], "episodes": 50, "verified": True}
    for name in ("benign", "mild"):
        tiers[name]["verification"] = check
    document = {
        "env_id": "Toy-v0",
        "levels": {name: tier["level"] for name, tier in tiers.items()},
        "faults": {"stuck_actuator": {"tiers": tiers, "curve": [
            {"severity": 1.0, "normalised": 0.8}]}},
    }  # fmt: skip
    row = [cell.strip() for cell in impact_table(document).splitlines()[-1].split("|")]
    assert row[-4:] == ["not reached", "unreachable", "0.800 (σ=1)", ""]


def test_read_tiers_names_the_stage_that_rebuilds_a_missing_or_foreign_document(tmp_path):
    with pytest.raises(StoreError, match=r"missing; .*impact@stuck_actuator"):
        read_tiers(tmp_path / "absent.yaml", "stuck_actuator")
    path = tmp_path / "other.yaml"
    path.write_text(yamlio.dump(_impact_document({})))
    with pytest.raises(StoreError, match="no impact curve of 'gradual_drift'"):
        read_tiers(path, "gradual_drift")


def test_per_stream_detection_counts_only_first_alarms_within_k_of_the_onset():
    # Hand-worked: T = 10, onset 4, K = 3, threshold 1, latency 1 (an alarm at t is raised at
    # t + 1). Stream 0 first alarms at t = 3, raised at 4: detected (delay 0). Stream 1 first
    # alarms at t = 1, raised at 2 < onset: a false alarm, not a detection, whatever follows.
    # Stream 2 first alarms at t = 7, raised at 8 > 4 + 3: too late. Stream 3 never alarms.
    # Stream 4 first alarms at t = 6, raised at 7 = onset + K: detected.
    scores = np.zeros((5, 10))
    scores[0, 3] = scores[1, [1, 5]] = scores[2, 7] = scores[4, 6] = 2.0
    detected = per_stream_detections(scores, threshold=1.0, onset=4, k=3, latency=1)
    assert detected.tolist() == [1.0, 0.0, 0.0, 0.0, 1.0]
    assert detection_metric(3) == "detection_rate@3"


def test_a_tier_table_cell_with_fewer_than_5_detections_prints_no_delay():
    from oodrl.metrics.tiers import tier_tables

    few = {"median": None, "p90": None, "n_detected": 3}
    enough = {"median": 12.0, "p90": 20.0, "n_detected": 40}
    records = [
        {"detector": name, "injector": "stuck_actuator", "tier": "mild", "severity": 0.2,
         "metrics": {"matched_auroc": {"mean": 0.8}},
         "operating_point": {"detection_rate": 0.2, "detection_rate_ci": [0.0, 0.5], "n_faulty": 10,
                             "delay": delay}}
        for name, delay in (("a", few), ("b", enough))
    ]  # fmt: skip
    verification = {
        "severity": 0.2, "normalised": 0.951, "ci": [0.93, 0.97], "episodes": 100, "batches": 2,
        "half_width": 0.02, "ci_target_met": True, "verified": True,
    }  # fmt: skip
    impact = {
        "env_id": "Toy-v0", "n_episodes": 30, "levels": {"mild": 0.95},
        "search": {"verify_batch": 50},
        "faults": {"stuck_actuator": {"curve": [{"normalised": 0.9, "severity": 1.0}],
                                      "tiers": {"mild": {"severity": 0.2,
                                                         "verification": verification}}}},
    }  # fmt: skip
    text = tier_tables({"k": 100, "alpha": 0.05, "records": records}, impact)
    assert "| a | stuck_actuator | 0.2 | 0.20 [0.00, 0.50] (10) | — (n = 3) | 0.800 |" in text
    assert "| b | stuck_actuator | 0.2 | 0.20 [0.00, 0.50] (10) | 12 (n = 40) | 0.800 |" in text
    # The tier, verified where it is read: R̃ there, its CI and its episodes.
    assert "0.2 (R̃ 0.951 [0.930, 0.970], n = 100)" in text
