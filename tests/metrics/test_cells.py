"""Per-detector cells and their merge (`oodrl.metrics.cells`): the metrics and tier_metrics
stages, merging every detector's cells, write byte for byte what one pass over every detector's
scores computes; a detector's cells read only its own scores; and adding a detector's cells
changes nothing of the others'.

On synthetic score stores (written here with the stores' own writer, in the layout the scoring
stages write) and, marked slow, on the tests' tiny pipeline (`built_repo`)."""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import numpy as np
import pytest
from tiny_pipeline import DETECTORS, INJECTORS, file_stamps, tiny_params

from oodrl.config import load_params, parse_params, read_params_data
from oodrl.core.spec import make_labels
from oodrl.errors import ContractError, StoreError
from oodrl.io import yamlio
from oodrl.io.fileio import atomic_write_text
from oodrl.io.layout import (
    CLEAN_GROUP,
    HEADLINE_GROUP,
    heldout_score_store,
    score_store,
    sweep_score_store,
    tier_score_store,
)
from oodrl.io.store import severity_key, write_scores
from oodrl.metrics.cells import (
    cells_path,
    cells_text,
    ordered_cells,
    parse_cells,
    read_cells,
    write_cells,
)
from oodrl.metrics.results import assemble_results, compute_results
from oodrl.metrics.tiers import assemble_tier_results, compute_tier_results
from oodrl.protocol.impact import LEVELS, UNREACHABLE
from oodrl.protocol.tiers import impact_path
from oodrl.stages.cells import detector_cells
from oodrl.stages.metrics import run_metrics, write_results
from oodrl.stages.tier_metrics import run_tier_metrics, write_tier_results

#: The files the two stages write, relative to the folder `_stage_outputs` gives them.
OUTPUTS = (
    "results.yaml", "sweep_results.yaml", "metrics.json", "tables.md", "tier_results.json",
    "tiers/tables.md", "tiers/impact_curves.png",
)  # fmt: skip
MODES = {"observation_delay": "online", "stuck_actuator": "posthoc"}
TIERS = {"mild": 0.5, "moderate": 1.0}


# -- synthetic score stores ----------------------------------------------------------------
def _scores(rng, n: int, T: int, onset: int | None = None, shift: float = 0.0) -> np.ndarray:  # noqa: N803
    scores = rng.normal(size=(n, T))
    if onset is not None:
        scores[:, onset:] += shift
    return scores


def _labelled(rng, params, n: int, shift: float) -> dict[str, np.ndarray]:
    T, onset, offset = params.env.T, params.env.resolved_onset, params.anomaly.offset  # noqa: N806
    labels = np.tile(make_labels(T, onset, offset), (n, 1))
    return {"scores": _scores(rng, n, T, onset, shift), "labels": labels}


def _write_synthetic(params, root: Path, seed: int = 7) -> tuple[Path, Path]:
    """Score stores of every benchmark detector and impact documents, as the pipeline's scoring
    and impact stages lay them out: (scores_dir, impact_dir)."""
    rng = np.random.default_rng(seed)
    scores_dir, impact_dir = root / "scores", root / "impact"
    T, onset, offset = params.env.T, params.env.resolved_onset, params.anomaly.offset  # noqa: N806
    n, tiers = params.data.n_ood, params.tiers
    spec = {"onset": onset, "offset": offset}
    for d_index, detector in enumerate(params.benchmark.detectors):
        clean = {CLEAN_GROUP: {"scores": _scores(rng, n, T)}}
        write_scores(score_store(scores_dir, detector), clean, {"threshold": 1.5 + d_index})
        heldout = {"calibration": tiers.n_calibration, "audit": tiers.n_audit,
                   "twins": tiers.n_streams}  # fmt: skip
        for which, count in heldout.items():
            groups = {CLEAN_GROUP: {"scores": _scores(rng, count, T)}}
            write_scores(heldout_score_store(scores_dir, detector, which), groups, {})
        for i_index, injector in enumerate(params.benchmark.injectors):
            shift = 0.5 + d_index + i_index
            write_scores(
                score_store(scores_dir, detector, injector),
                {HEADLINE_GROUP: _labelled(rng, params, n, shift)},
                {"spec": {**spec, "severity": 0.4}, "mode": MODES[injector]},
            )
            sweep = [float(s) for s in params.anomaly.sweep]
            write_scores(
                sweep_score_store(scores_dir, detector, injector),
                {severity_key(s): _labelled(rng, params, n, shift * s) for s in sweep},
                {"spec": spec, "severities": sweep, "mode": MODES[injector]},
            )
            write_scores(
                tier_score_store(scores_dir, detector, injector),
                {severity_key(s): _labelled(rng, params, tiers.n_streams, shift * s)
                 for s in TIERS.values()},
                {"spec": spec, "tiers": TIERS, "mode": "online", "unreachable": []},
            )  # fmt: skip
    for injector in params.benchmark.injectors:
        check = {"ci": [0.9, 0.97], "normalised": 0.94, "episodes": 2}
        fault = {
            "tiers": {
                "benign": {"severity": UNREACHABLE},
                "mild": {"severity": 0.5, "verification": {**check, "verified": True}},
                "moderate": {"severity": 1.0, "verification": {**check, "verified": False}},
                "severe": {"severity": UNREACHABLE},
            },
            "curve": [
                {"severity": 0.5, "monotone": 0.95, "normalised": 0.95, "ci": [0.9, 0.99]},
                {"severity": 1.0, "monotone": 0.85, "normalised": 0.86, "ci": [0.8, 0.9]},
            ],
        }
        document = {"env_id": params.env.id, "clean_return": 200.0, "random_return": -150.0,
                    "levels": LEVELS, "search": {"verify_episodes": 2},
                    "faults": {injector: fault}}  # fmt: skip
        atomic_write_text(impact_path(impact_dir, injector), yamlio.dump(document))
    return scores_dir, impact_dir


@pytest.fixture(scope="module")
def tiny_data(_default_params) -> dict:
    return tiny_params(_default_params)


@pytest.fixture(scope="module")
def params(tiny_data):
    return parse_params(tiny_data, components=False)


@pytest.fixture(scope="module")
def synthetic(params, tmp_path_factory) -> tuple[Path, Path]:
    return _write_synthetic(params, tmp_path_factory.mktemp("synthetic"))


# -- helpers ---------------------------------------------------------------------------------
def _stage_outputs(params, scores_dir: Path, impact_dir: Path, out: Path) -> dict[str, bytes]:
    """The files of both stages computed in one pass over every detector's scores."""
    write_results(params, compute_results(params, scores_dir), *(out / n for n in OUTPUTS[:4]))
    document = compute_tier_results(params, scores_dir, impact_dir)
    write_tier_results(params, document, impact_dir, out / OUTPUTS[4], out / "tiers")
    return {name: (out / name).read_bytes() for name in OUTPUTS}


def _merged_outputs(params, scores_dir: Path, impact_dir: Path, out: Path) -> dict[str, bytes]:
    """The same files as the pipeline writes them: every detector's cells written to and read
    back from its own file (the cells stage), then merged by the metrics and tier_metrics
    stages."""
    for detector in params.benchmark.detectors:
        cells = detector_cells(params, scores_dir, impact_dir, detector)
        write_cells(cells, cells_path(out / "cells", detector))
    run_metrics(params, out / "cells", *(out / name for name in OUTPUTS[:4]))
    run_tier_metrics(params, out / "cells", impact_dir, out / OUTPUTS[4], out / "tiers")
    return {name: (out / name).read_bytes() for name in OUTPUTS}


def merge_cells(params, cells_by_detector: dict, impact_dir: Path) -> tuple[object, dict]:
    """Both stages' merge of every detector's cells: (results, the tier results document)."""
    cells = ordered_cells(params, cells_by_detector)
    results = assemble_results(params, [(c.detector, (c.records, c.sweep, c.modes)) for c in cells])
    records = [r for c in cells for r in c.tier_records]
    return results, assemble_tier_results(params, records, impact_dir)


def _read_and_merge(params, cells_dir: Path, impact_dir: Path):
    cells = {d: read_cells(cells_path(cells_dir, d)) for d in params.benchmark.detectors}
    return merge_cells(params, cells, impact_dir)


def _assert_same_bytes(today: dict[str, bytes], merged: dict[str, bytes]) -> None:
    differ = [name for name in OUTPUTS if today[name] != merged[name]]
    assert not differ, f"the merge differs from one pass in {differ}"


def _one_detector(data: dict, detector: str):
    data = copy.deepcopy(data)
    data["benchmark"]["detectors"] = [detector]
    return parse_params(data, components=False)


def _records_of(merged, detector: str) -> dict:
    """Everything of one detector in a merge's outputs."""
    results, tiers = merged
    return {
        "records": [r.as_dict() for r in results.records if r.detector == detector],
        "sweep": {(i, s): by_detector[detector] for i, per_severity in results.sweep.items()
                  for s, by_detector in per_severity.items() if detector in by_detector},
        "modes": results.modes,
        "thresholds": results.thresholds[detector],
        "tier_records": [r for r in tiers["records"] if r["detector"] == detector],
        "audit": tiers["false_alarm_audit"][detector],
        "mdi": tiers["minimum_detectable_impact"][detector],
        "impact": tiers["impact"],
    }  # fmt: skip


# -- on synthetic scores ---------------------------------------------------------------------
def test_the_merge_writes_todays_files_byte_for_byte(params, synthetic, tmp_path):
    scores_dir, impact_dir = synthetic
    today = _stage_outputs(params, scores_dir, impact_dir, tmp_path / "today")
    merged = _merged_outputs(params, scores_dir, impact_dir, tmp_path / "merged")
    _assert_same_bytes(today, merged)
    # The shared object that YAML writes as an anchor is there, and kept: the null summary of
    # a detector's two modes.
    assert today["results.yaml"].count(b"  metrics: *id") == len(DETECTORS)


def test_a_cells_file_is_deterministic_and_exact(params, synthetic, tmp_path):
    scores_dir, impact_dir = synthetic
    cells = detector_cells(params, scores_dir, impact_dir, DETECTORS[0])
    again = detector_cells(params, scores_dir, impact_dir, DETECTORS[0])
    write_cells(cells, tmp_path / "a.json")
    write_cells(again, tmp_path / "b.json")
    text = (tmp_path / "a.json").read_text()
    assert text == (tmp_path / "b.json").read_text() == cells_text(cells)
    assert str(tmp_path) not in text and str(scores_dir) not in text  # no host paths
    read = read_cells(tmp_path / "a.json")
    assert read == cells
    assert cells_text(read) == text
    nulls = [r for r in read.records if r.kind == "null"]
    assert len(nulls) == 2 and nulls[0].metrics is nulls[1].metrics
    # A detection curve's int K and a sweep's float severity come back with their types.
    curve = read.tier_records[0]["operating_point"]["detection_curve"]
    assert curve and all(type(k) is int for k in curve)
    assert all(type(s) is float for _, s in read.sweep)


def test_a_detectors_cells_read_no_other_detectors_scores(params, synthetic, tmp_path):
    scores_dir, impact_dir = synthetic
    alone = tmp_path / "scores"
    shutil.copytree(scores_dir / DETECTORS[0], alone / DETECTORS[0])
    assert sorted(p.name for p in alone.iterdir()) == [DETECTORS[0]]
    expected = detector_cells(params, scores_dir, impact_dir, DETECTORS[0])
    assert cells_text(detector_cells(params, alone, impact_dir, DETECTORS[0])) == cells_text(
        expected
    )
    with pytest.raises(StoreError):
        detector_cells(params, alone, impact_dir, DETECTORS[1])


def test_adding_a_detectors_cells_changes_nothing_of_the_others(
    params, tiny_data, synthetic, tmp_path
):
    scores_dir, impact_dir = synthetic
    cells = {d: detector_cells(params, scores_dir, impact_dir, d) for d in DETECTORS}
    both = merge_cells(params, cells, impact_dir)
    first = DETECTORS[0]
    alone = merge_cells(_one_detector(tiny_data, first), {first: cells[first]}, impact_dir)
    assert _records_of(alone, first) == _records_of(both, first)
    assert [r.detector for r in alone[0].records] == [first] * 4
    # The cells themselves are not changed by a merge.
    assert cells_text(cells[first]) == cells_text(
        detector_cells(params, scores_dir, impact_dir, first)
    )


def test_the_merge_needs_exactly_the_benchmarks_detectors(params, synthetic):
    scores_dir, impact_dir = synthetic
    cells = {d: detector_cells(params, scores_dir, impact_dir, d) for d in DETECTORS}
    with pytest.raises(ContractError, match=f"missing: {DETECTORS[1]}"):
        merge_cells(params, {DETECTORS[0]: cells[DETECTORS[0]]}, impact_dir)
    with pytest.raises(ContractError, match="not in benchmark.detectors: other"):
        merge_cells(params, {**cells, "other": cells[DETECTORS[0]]}, impact_dir)
    with pytest.raises(ContractError, match="are .*'s"):
        merge_cells(params, {DETECTORS[0]: cells[DETECTORS[1]], DETECTORS[1]: cells[DETECTORS[1]]},
                    impact_dir)  # fmt: skip
    with pytest.raises(ContractError, match="not in benchmark.detectors"):
        detector_cells(params, scores_dir, impact_dir, "other")


def test_a_cells_file_refuses_what_json_would_change(params, synthetic):
    import dataclasses

    cells = detector_cells(params, *synthetic, DETECTORS[0])
    record = dict(cells.tier_records[0])
    for value in ((1, 2), np.float64(0.5), {True: 1}, {"__items__": 1}):
        odd = dataclasses.replace(cells, tier_records=[{**record, "extra": value}])
        with pytest.raises(ContractError, match="cells file"):
            cells_text(odd)
    # An object met twice would lose its YAML anchor: refused, but for the null summary.
    first, second = cells.tier_records[:2]
    shared = [1.0]
    odd = dataclasses.replace(
        cells, tier_records=[{**first, "extra": shared}, {**second, "extra": shared}]
    )
    with pytest.raises(ContractError, match="shared between cells"):
        cells_text(odd)
    records = [
        dataclasses.replace(r, metrics=dict(r.metrics)) if r.kind == "null" else r
        for r in cells.records
    ]
    with pytest.raises(ContractError, match="do not share one summary"):
        cells_text(dataclasses.replace(cells, records=records))
    # Non-finite floats and mixed key types still round-trip exactly.
    odd = dataclasses.replace(
        cells, tier_records=[{**record, "extra": {1: float("inf"), 0.5: -0.0, 2: [None, True]}}]
    )
    back = parse_cells(cells_text(odd)).tier_records[0]["extra"]
    assert list(back) == [1, 0.5, 2] and back[1] == float("inf")
    assert [type(k) for k in back] == [int, float, int] and str(back[0.5]) == "-0.0"


def test_a_foreign_or_missing_cells_file_is_refused(tmp_path):
    with pytest.raises(StoreError, match="missing"):
        read_cells(tmp_path / "absent.json")
    refused = {
        "{": "not a cells file",
        "[]": "not an oodrl-cells file",
        '{"format": "oodrl-cells", "version": 99}': "cells version 99",
    }
    for text, message in refused.items():
        with pytest.raises(StoreError, match=message):
            parse_cells(text)


# -- on the tiny pipeline's scores -------------------------------------------------------------
@pytest.mark.slow
def test_the_merge_writes_todays_files_on_the_tiny_pipeline(built_repo, tmp_path):
    before = file_stamps(built_repo)
    params = load_params(built_repo / "params.yaml", components=False)
    assert list(params.benchmark.detectors) == DETECTORS
    assert list(params.benchmark.injectors) == INJECTORS
    scores_dir, impact_dir = built_repo / "scores", built_repo / "data" / "impact"
    today = _stage_outputs(params, scores_dir, impact_dir, tmp_path / "today")
    merged = _merged_outputs(params, scores_dir, impact_dir, tmp_path / "merged")
    _assert_same_bytes(today, merged)
    # ... which are the files the pipeline's own stages wrote.
    reports = built_repo / "reports"
    for name in OUTPUTS:
        assert merged[name] == (reports / name).read_bytes(), name

    # A detector's cells in a copy without the other detector's scores are unchanged.
    alone = tmp_path / "alone"
    shutil.copytree(scores_dir / DETECTORS[0], alone / DETECTORS[0])
    cells = read_cells(cells_path(tmp_path / "merged" / "cells", DETECTORS[0]))
    assert cells_text(detector_cells(params, alone, impact_dir, DETECTORS[0])) == cells_text(cells)
    # Adding the other detector's cells changes nothing of the first's.
    data = read_params_data(built_repo / "params.yaml")
    both = _read_and_merge(params, tmp_path / "merged" / "cells", impact_dir)
    first = merge_cells(_one_detector(data, DETECTORS[0]), {DETECTORS[0]: cells}, impact_dir)
    assert _records_of(first, DETECTORS[0]) == _records_of(both, DETECTORS[0])
    assert file_stamps(built_repo) == before  # the shared build is only read
