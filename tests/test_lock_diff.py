"""benchmarks/lock_diff.py judges a build's changed outputs: a change under a detector that is
not certified machine-independent is allowed (SPEC §14), any other is a reproduction failure.
Its judgement of results files, on hand-made documents."""

from __future__ import annotations

import json

import pytest
import yaml
from benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def lock_diff():
    return load_benchmark("lock_diff")


RESULTS = {
    "protocol_version": 3,
    "records": [
        {"detector": "cusum", "injector": "stuck_actuator", "auroc": {"mean": 0.91}},
        {"detector": "pyod_iforest", "injector": "stuck_actuator", "auroc": {"mean": 0.71}},
    ],
    "sweep": {"stuck_actuator": {"0.5": {"pyod_iforest": {"mean": 0.6}, "cusum": {"mean": 0.8}}}},
}


def _changed(**edits) -> dict:
    document = json.loads(json.dumps(RESULTS))
    if "record" in edits:
        document["records"][edits["record"]]["auroc"]["mean"] += 1e-6
    if "sweep" in edits:
        document["sweep"]["stuck_actuator"]["0.5"][edits["sweep"]]["mean"] += 1e-6
    return document


@pytest.mark.parametrize(
    ("edits", "found", "unexplained"),
    [
        ({}, set(), 0),
        ({"record": 1}, {"pyod_iforest"}, 0),  # a record names its detector in a field
        ({"sweep": "pyod_iforest"}, {"pyod_iforest"}, 0),  # a key names it
        ({"record": 0}, set(), 1),  # a certified detector's number moved
        ({"record": 1, "sweep": "cusum"}, {"pyod_iforest"}, 1),
    ],
)
def test_a_yaml_change_is_explained_only_under_an_uncertified_detector(
    lock_diff, tmp_path, edits, found, unexplained
):
    path = tmp_path / "results.yaml"
    old, new = yaml.safe_dump(RESULTS), yaml.safe_dump(_changed(**edits))
    assert lock_diff.changed_detectors(path, old, new, {"pyod_iforest"}) == (found, unexplained)


def test_a_json_key_joining_a_name_with_other_words_names_it(lock_diff, tmp_path):
    old = json.dumps({"iqm.pyod_iforest": 0.5, "iqm.cusum": 0.9})
    new = json.dumps({"iqm.pyod_iforest": 0.51, "iqm.cusum": 0.9})
    path = tmp_path / "metrics.json"
    assert lock_diff.changed_detectors(path, old, new, {"pyod_iforest"}) == ({"pyod_iforest"}, 0)
    moved = json.dumps({"iqm.pyod_iforest": 0.5, "iqm.cusum": 0.91})
    assert lock_diff.changed_detectors(path, old, moved, {"pyod_iforest"}) == (set(), 1)


def test_a_table_row_is_explained_by_the_detector_it_names(lock_diff, tmp_path):
    old = "| detector | AUROC |\n| cusum | 0.91 |\n| pyod_iforest † | 0.71 |\n"
    path = tmp_path / "tables.md"
    new = old.replace("0.71", "0.72")
    assert lock_diff.changed_detectors(path, old, new, {"pyod_iforest"}) == ({"pyod_iforest"}, 0)
    new = old.replace("0.91", "0.92")
    assert lock_diff.changed_detectors(path, old, new, {"pyod_iforest"}) == (set(), 2)


def test_the_code_stamps_are_reported_and_any_other_protocol_data_is_a_failure(lock_diff):
    """A change of code moves the code stamps by design; a moved store of the certified protocol
    (here an ID set) is a reproduction failure, a library detector's scores are not."""
    project = lock_diff.ROOT
    stamps = lock_diff.judged(project, lock_diff.CODE_STAMPS, None, set(), "HEAD")
    assert stamps["unexplained"] == 0 and "code stamps" in stamps["note"]
    data = lock_diff.judged(project, ("collect_id", "data/id.zarr"), None, set(), "HEAD")
    assert data["unexplained"] == 1
    scores = lock_diff.judged(project, ("score@x", "scores/k"), "pyod_knn", {"pyod_knn"}, "HEAD")
    assert (scores["detectors"], scores["unexplained"]) == (["pyod_knn"], 0)


def test_the_suite_judges_by_every_environments_detectors_and_reports_its_page(lock_diff):
    """The suite's project has no params of its own: its leaderboard gathers every environment's
    detectors, so their uncertified ones explain its changes; its HTML page renders the JSON
    beside it and is reported, not judged."""
    projects = lock_diff.project_dirs(lock_diff.ROOT)
    uncertified = lock_diff.uncertified_by_project(projects)
    suite = lock_diff.ROOT / "pipeline" / "suite"
    environments = [uncertified[p] for p in projects if p != suite]
    assert uncertified[suite] == set().union(*environments)
    assert "pyod_iforest" in uncertified[suite]
    assert not uncertified[lock_diff.ROOT]  # the root's detectors are all certified
    page = lock_diff.judged(suite, ("leaderboard", "reports/leaderboard.html"), None, set(), "HEAD")
    assert page["unexplained"] == 0 and "page" in page["note"]
