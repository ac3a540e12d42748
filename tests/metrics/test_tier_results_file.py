"""The tier results file (protocol 5, `oodrl.metrics.tiers`): canonical JSON, a record a line,
read by one loader that reads a protocol-4 project's YAML to the same dict."""

from __future__ import annotations

import copy
import json
import math

import pytest
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.errors import ContractError, StoreError
from oodrl.io import yamlio
from oodrl.metrics.tier_results import (
    PROTOCOL_4_TIER_RESULTS,
    TIER_RESULTS,
    load_tier_results,
    tier_results_path,
    tier_results_text,
)


def _record(detector: str, tier: str, rate: float, ci: list[float]) -> dict:
    point = {"detection_rate": rate, "clean_false_alarm_ci": ci,
             "detection_curve": {1: 0.0, 2: 0.25, 10: rate}}  # fmt: skip
    return {
        "detector": detector, "injector": "stuck_actuator", "tier": tier, "severity": 0.1 * 3,
        "operating_point": point, "time_aware": {"operating_point": copy.deepcopy(point)},
        "note": "σ drift",
    }  # fmt: skip


def _document() -> dict:
    """A tier results document as `assemble_tier_results` builds it, in small: the audit's
    interval is the same list as a record's (protocol 4's YAML wrote it as an anchor)."""
    ci = [0.01, 0.2]
    records = [_record("cusum", "mild", 0.5, ci), _record("cusum", "severe", 1.0, ci),
               _record("kde_density", "mild", 0.125, [0.0, 0.1])]  # fmt: skip
    return {
        "protocol_version": 5, "params_hash": "sha256:0", "alpha": 0.05, "k": 100,
        "false_alarm_audit": {"kde_density": {"ci": [0.0, 0.1]}, "cusum": {"ci": ci}},
        "records": records,
        "impact": {"stuck_actuator": {"clean_return": 200.0, "tiers": {"mild": {"severity": 0.3}}}},
        "minimum_detectable_impact": {},
    }  # fmt: skip


def test_the_text_is_canonical_with_each_record_on_one_line():
    document = _document()
    text = tier_results_text(document)
    # The same document in another key order: the same bytes.
    shuffled = dict(reversed(list(copy.deepcopy(document).items())))
    shuffled["records"] = [dict(reversed(list(r.items()))) for r in shuffled["records"]]
    assert tier_results_text(shuffled) == text
    assert text.isascii() and text.endswith("}\n") and "\\u03c3" in text
    lines = text.splitlines()
    start = lines.index('"records":[')
    records = lines[start + 1 : start + 1 + len(document["records"])]
    assert [json.loads(line.rstrip(",")) for line in records] == json.loads(
        json.dumps(document["records"])
    )  # each record one line, in order
    assert lines[start + 1 + len(document["records"]) :] == ["]", "}"]  # records: the last key
    assert '"protocol_version":5,' in lines  # the stamp line the leaderboard reads
    assert json.loads(text) == json.loads(json.dumps(document))
    # Pinned bytes: floats by their shortest repr, sorted keys, no spaces.
    assert lines[:6] == [
        "{", '"alpha":0.05,', '"false_alarm_audit":{', '"cusum":{"ci":[0.01,0.2]},',
        '"kde_density":{"ci":[0.0,0.1]}', "},",
    ]  # fmt: skip


def test_a_value_json_cannot_keep_is_refused():
    document = _document()
    document["records"][0]["operating_point"]["detection_rate"] = math.nan
    with pytest.raises(ContractError, match="NaN or infinite"):
        tier_results_text(document)


def test_the_json_and_a_protocol_4_yaml_load_to_the_same_dict(tmp_path):
    document = _document()
    rebuilt, older = tmp_path / "rebuilt", tmp_path / "older"
    (rebuilt / TIER_RESULTS).parent.mkdir(parents=True)
    (rebuilt / TIER_RESULTS).write_text(tier_results_text(document))
    (older / PROTOCOL_4_TIER_RESULTS).parent.mkdir(parents=True)
    (older / PROTOCOL_4_TIER_RESULTS).write_text(yamlio.dump(document))
    assert "*id001" in (older / PROTOCOL_4_TIER_RESULTS).read_text()  # an anchor, as protocol 4

    assert load_tier_results(rebuilt) == load_tier_results(older) == document
    curve = load_tier_results(rebuilt)["records"][0]["time_aware"]["operating_point"]
    assert list(curve["detection_curve"]) == [1, 2, 10]  # int K, as the records hold it
    assert load_tier_results(rebuilt / TIER_RESULTS) == document  # a file, by its suffix
    for project in (rebuilt, older):
        assert load_tier_results(project, keys=["impact", "k"]) == {
            "impact": document["impact"], "k": 100,
        }  # fmt: skip
    # A project holding both (rebuilt, the YAML not yet removed) is read from its JSON.
    (rebuilt / PROTOCOL_4_TIER_RESULTS).write_text(yamlio.dump({"records": []}))
    assert tier_results_path(rebuilt) == rebuilt / TIER_RESULTS
    assert load_tier_results(rebuilt) == document


def test_a_missing_or_broken_file_is_one_line(tmp_path):
    with pytest.raises(StoreError) as missing:
        load_tier_results(tmp_path)
    assert str(missing.value).startswith(f"{tmp_path / TIER_RESULTS}: no tier results file")
    assert "\n" not in str(missing.value)
    (tmp_path / TIER_RESULTS).parent.mkdir()
    (tmp_path / TIER_RESULTS).write_text('{"records": [\n')
    with pytest.raises(StoreError, match="not a tier results file") as broken:
        load_tier_results(tmp_path)
    assert "\n" not in str(broken.value)


def test_the_stage_refuses_a_results_path_that_is_not_json(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(
        app, ["tier-metrics", "--cells", "cells", "--impact", "data/impact",
              "--results", "reports/tier_results.yaml", "--report", "reports/tiers"],
    )  # fmt: skip
    assert result.exit_code == 2
    assert result.output.count("\n") == 1
    assert result.output.startswith("error: --results reports/tier_results.yaml: ")
    assert "reports/tier_results.json" in result.output
    assert not (tmp_path / "reports").exists()
