"""Both per-stream rules in the tier results (SPEC §24, `oodrl.metrics.tiers`): the constant
rule's operating point as before, the time-aware rule's beside it, each rule's α curve and its
per-stream detections; plain values a cells file keeps exactly; the tier tables show both.

Synthetic score stores in the scoring stages' layout. The clean law: T = 60 steps of independent
N(0, σ_t²) scores, σ_t = 1 in the quiet phase (steps 0–29) and 10 in the loud one (30–59); the
faults of the `mild` tier add 3 (three quiet sd) on the quiet steps from the onset (20) on, which
only the time-aware rule can see (the library's own proof: tests/metrics/test_time_aware.py);
those of `moderate` add 60, which both rules see."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from tiny_pipeline import DETECTORS, tiny_params

from oodrl.config import parse_params
from oodrl.core.spec import make_labels
from oodrl.io import yamlio
from oodrl.io.fileio import atomic_write_text
from oodrl.io.layout import CLEAN_GROUP, heldout_score_store, id_score_store, tier_score_store
from oodrl.io.store import severity_key, write_scores
from oodrl.metrics.cells import DetectorCells, cells_text, parse_cells
from oodrl.metrics.tiers import (
    CURVE_KEYS,
    _false_alarm_audit,
    detector_records,
    tier_tables,
    time_aware_detection_metric,
)
from oodrl.metrics.time_aware import ALPHAS
from oodrl.protocol.impact import LEVELS, UNREACHABLE
from oodrl.protocol.tiers import impact_path

T, QUIET = 60, 30
SD = np.r_[np.ones(QUIET), np.full(T - QUIET, 10.0)]
#: The first detector's ID scores: 100 streams (6,000 values, windows of 3 steps); the second's:
#: 4 streams (240 values, fewer than the 300 the time-aware rule needs).
ID_STREAMS = {DETECTORS[0]: 100, DETECTORS[1]: 4}
TIERS = {"mild": 0.5, "moderate": 1.0}
N_STREAMS = 100


def _clean(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.standard_normal((n, T)) * SD


@pytest.fixture(scope="module")
def params(_default_params):
    data = tiny_params(_default_params)
    data["env"]["T"] = T
    data["tiers"].pop("search", None)  # the tier search's knobs: not read here
    data["tiers"].update(
        n_calibration=200, n_audit=200, n_streams=N_STREAMS,
        threshold_rule="episode_max_conditional", delta=0.1,
    )  # fmt: skip
    return parse_params(data, components=False)


@pytest.fixture(scope="module")
def stores(params, tmp_path_factory) -> tuple[Path, Path]:
    """(scores_dir, impact_dir) as the scoring and impact stages lay them out."""
    rng = np.random.default_rng(11)
    root = tmp_path_factory.mktemp("tier-rules")
    scores_dir, impact_dir = root / "scores", root / "impact"
    onset, offset = params.env.resolved_onset, params.anomaly.offset
    labels = np.tile(make_labels(T, onset, offset), (N_STREAMS, 1))
    tiers = params.tiers
    for detector in params.benchmark.detectors:
        clean = {"calibration": tiers.n_calibration, "audit": tiers.n_audit, "twins": N_STREAMS}
        for which, count in clean.items():
            groups = {CLEAN_GROUP: {"scores": _clean(rng, count)}}
            write_scores(heldout_score_store(scores_dir, detector, which), groups, {})
        groups = {CLEAN_GROUP: {"scores": _clean(rng, ID_STREAMS[detector])}}
        write_scores(id_score_store(scores_dir, detector), groups, {})
        for injector in params.benchmark.injectors:
            sets = {}
            for tier, severity in TIERS.items():
                faulty = _clean(rng, N_STREAMS)
                faulty[:, onset:QUIET] += 3.0 if tier == "mild" else 60.0
                sets[severity_key(severity)] = {"scores": faulty, "labels": labels}
            spec = {"onset": onset, "offset": offset}
            attrs = {"spec": spec, "tiers": TIERS, "mode": "online", "unreachable": []}
            write_scores(tier_score_store(scores_dir, detector, injector), sets, attrs)
    for injector in params.benchmark.injectors:
        check = {"ci": [0.9, 0.97], "normalised": 0.94, "verified": True}
        fault = {
            "tiers": {
                "benign": {"severity": UNREACHABLE},
                "mild": {"severity": 0.5, "verification": check},
                "moderate": {"severity": 1.0, "verification": check},
                "severe": {"severity": UNREACHABLE},
            },
            "curve": [{"severity": 0.5, "monotone": 0.95, "normalised": 0.95, "ci": [0.9, 0.99]}],
        }
        document = {"env_id": params.env.id, "clean_return": 200.0, "random_return": -150.0,
                    "levels": LEVELS, "faults": {injector: fault}}  # fmt: skip
        atomic_write_text(impact_path(impact_dir, injector), yamlio.dump(document))
    return scores_dir, impact_dir


@pytest.fixture(scope="module")
def records(params, stores) -> dict[str, list[dict]]:
    return {d: detector_records(params, *stores, d) for d in params.benchmark.detectors}


def _plain(value, where: str = "record") -> None:
    """Only what a cells file and YAML keep exactly: no tuple, no numpy scalar."""
    if isinstance(value, dict):
        for key, item in value.items():
            assert type(key) in (str, int, float), f"{where}: key {key!r}"
            _plain(item, f"{where}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _plain(item, f"{where}[{i}]")
    else:
        assert value is None or type(value) in (str, int, float, bool), f"{where}: {value!r}"


def test_a_record_holds_both_rules_and_the_time_aware_one_sees_a_quiet_phase_fault(params, records):
    detector = DETECTORS[0]
    k = params.tiers.k
    by_tier = {r["tier"]: r for r in records[detector] if r["injector"] == "stuck_actuator"}
    mild = by_tier["mild"]
    for record in (r for part in records.values() for r in part):
        _plain(record)
    constant, aware = mild["operating_point"], mild["time_aware"]["operating_point"]
    assert mild["time_aware"] == {
        "operating_point": aware, "fit_streams": 100, "fit_values": 6000, "reason": None,
    }  # fmt: skip
    # The same keys under either rule; the delay's mean beside its median and p90.
    assert set(constant) == set(aware)
    assert set(constant["delay"]) == {"median", "p90", "mean", "n_detected"}
    # The constant threshold (set by the loud phase's maxima, ~30) is out of the quiet's reach;
    # standardised, a faulty step exceeds the threshold (~3.4) with probability ~1/3, and the
    # quiet steps 20–27 (28 and 29 take the loud phase's scale from their windows) make nearly
    # every faulty stream alarm.
    assert constant["detection_rate"] <= 0.1 and aware["detection_rate"] >= 0.85
    # Delays: shown from 5 detected streams on, hidden below (and their count always).
    assert aware["delay"]["median"] <= aware["delay"]["p90"] and aware["delay"]["mean"] >= 0
    assert constant["delay"]["n_detected"] < 5
    assert constant["delay"]["median"] is constant["delay"]["mean"] is None
    # The per-stream detections of both rules, paired stream by stream.
    episodes = mild["episodes"]
    assert sum(episodes[f"detection_rate@{k}"]) == round(constant["detection_rate"] * N_STREAMS)
    aware_hits = episodes[time_aware_detection_metric(k)]
    assert (
        len(aware_hits) == N_STREAMS
        and sum(aware_hits) == aware["n_faulty"] * aware["detection_rate"]
    )
    # Both audited on the same 200 clean streams, within a loose bound of α (exact promises:
    # test_time_aware.py).
    for point in (constant, aware):
        assert point["n_clean"] == 200 and point["clean_false_alarm_rate"] <= 0.15
        low, high = point["clean_false_alarm_ci"]
        assert low <= point["clean_false_alarm_rate"] <= high
    # A loud fault: both rules see it.
    moderate = by_tier["moderate"]
    assert moderate["operating_point"]["detection_rate"] >= 0.9
    assert moderate["time_aware"]["operating_point"]["detection_rate"] >= 0.9


def test_each_rule_has_an_alpha_curve(params, records):
    mild = next(r for r in records[DETECTORS[0]] if r["tier"] == "mild")
    curves = mild["alpha_curve"]
    assert set(curves) == {"constant", "time_aware"}
    for rule, curve in curves.items():
        assert [entry["alpha"] for entry in curve] == list(ALPHAS)
        assert all(set(entry) <= set(CURVE_KEYS) for entry in curve)
        # 200 calibration streams at δ = 0.1 support α ≥ 0.0114: not 0.01.
        assert not curve[0]["supported"] and "needs at least 230" in curve[0]["reason"]
        supported = [e for e in curve if e["supported"]]
        assert len(supported) == 4
        thresholds = [e["threshold"] for e in supported]
        assert thresholds == sorted(thresholds, reverse=True)
        # The curve at the tier's α is the record's operating point.
        point = mild["operating_point"] if rule == "constant" else mild[rule]["operating_point"]
        at = next(e for e in curve if e["alpha"] == params.tiers.alpha)
        assert {key: point[key] for key in at if key not in ("alpha", "supported")} == {
            key: value for key, value in at.items() if key not in ("alpha", "supported")
        }
        # A larger α, a lower threshold: never fewer alarms, before the onset or on clean streams
        # (detections may fall: an earlier first alarm before the onset is no detection).
        for key in ("early_false_alarm_rate", "clean_false_alarm_rate"):
            values = [e[key] for e in supported]
            assert values == sorted(values)


def test_fewer_than_300_fit_values_leave_the_time_aware_rule_null_with_its_reason(
    params, records, stores, tmp_path
):
    k = params.tiers.k
    for record in records[DETECTORS[1]]:
        assert record["time_aware"] == {
            "operating_point": None, "fit_streams": 4, "fit_values": 240,
            "reason": "240 ID scores (4 streams of 60 steps); the time-aware rule needs at "
                      "least 300",
        }  # fmt: skip
        assert record["alpha_curve"]["time_aware"] is None
        assert len(record["alpha_curve"]["constant"]) == len(ALPHAS)
        assert time_aware_detection_metric(k) not in record["episodes"]
        assert record["operating_point"]["detection_rate"] is not None  # the rest as before
    # No ID scores at all (a caller that scored none): null too, naming no host path.
    scores_dir, impact_dir = stores
    alone = tmp_path / "scores"
    for path in (scores_dir / DETECTORS[0]).rglob("*.zarr"):
        if path.name != "id.zarr":
            target = alone / path.relative_to(scores_dir)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(path.read_bytes())
    without = detector_records(params, alone, impact_dir, DETECTORS[0])
    aware = without[0]["time_aware"]
    assert aware["operating_point"] is None and aware["fit_values"] is None
    assert aware["reason"].startswith(f"no scores of the ID set ({DETECTORS[0]}/id.zarr")
    assert str(tmp_path) not in aware["reason"]
    # ... and every constant-rule number is the one computed with them.
    assert [r["operating_point"] for r in without] == [
        r["operating_point"] for r in records[DETECTORS[0]]
    ]


def test_the_records_survive_a_cells_file_and_yaml_exactly(params, records):
    for detector, part in records.items():
        cells = DetectorCells(detector, [], {}, {}, part)
        text = cells_text(cells)
        back = parse_cells(text)
        assert back.tier_records == part and cells_text(back) == text
    everything = [r for part in records.values() for r in part]
    audit = _false_alarm_audit(everything)
    document = {"false_alarm_audit": audit, "records": everything}
    dumped = yamlio.dump(document)
    assert yamlio.load(dumped) == document
    # The one shared object stays the constant rule's audit interval (one anchor a detector).
    assert dumped.count("clean_false_alarm_ci: *id") == len(DETECTORS)
    aware = audit[DETECTORS[0]]["time_aware"]
    point = records[DETECTORS[0]][-1]["time_aware"]["operating_point"]
    assert aware == {
        "threshold": point["threshold"], "rate": point["clean_false_alarm_rate"],
        "ci": point["clean_false_alarm_ci"], "n_streams": 200,
        "n_alarmed": round(point["clean_false_alarm_rate"] * 200),
    }  # fmt: skip
    assert audit[DETECTORS[1]]["time_aware"] == {
        "reason": records[DETECTORS[1]][0]["time_aware"]["reason"]
    }


def test_the_tier_tables_show_both_rules(params, records):
    everything = [r for part in records.values() for r in part]
    document = {
        "k": params.tiers.k, "alpha": params.tiers.alpha, "records": everything,
        "false_alarm_audit": _false_alarm_audit(everything),
    }  # fmt: skip
    impact = {"env_id": "Toy-v0", "levels": {"mild": 0.95, "moderate": 0.9}, "faults": {},
              "search": {"verify_episodes": 2}}  # fmt: skip
    text = tier_tables(document, impact)
    assert (
        "| detector | constant: false-alarm rate [95% CI] | streams alarmed "
        "| time-aware: false-alarm rate [95% CI] | streams alarmed |" in text
    )
    assert f"| {DETECTORS[1]} | " in text and " | — | — |" in text
    assert (
        f"No time-aware rule (—): {DETECTORS[1]}: 240 ID scores (4 streams of 60 steps); the "
        "time-aware rule needs at least 300." in text
    )
    assert "## mild: detection_rate@100 at α = 0.05 [95% CI] and median delay under the " in text
    mild = next(
        r for r in records[DETECTORS[0]] if (r["tier"], r["injector"]) == ("mild", "stuck_actuator")
    )
    point, aware = mild["operating_point"], mild["time_aware"]["operating_point"]
    row = next(
        line for line in text.splitlines() if line.startswith(f"| {DETECTORS[0]} | stuck_actuator")
    )
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3].startswith(f"{point['detection_rate']:.2f} [")
    assert cells[5].startswith(f"{aware['detection_rate']:.2f} [")
    assert cells[6].endswith(f"(n = {aware['delay']['n_detected']})")
    assert math.isclose(float(cells[-1]), mild["metrics"]["matched_auroc"]["mean"], abs_tol=5e-4)


def test_load_results_has_a_row_a_metric_of_each_rule_and_the_alpha_curves_when_asked(
    params, records, tmp_path
):
    import oodrl
    from oodrl.errors import ConfigError

    everything = [r for part in records.values() for r in part]
    path = tmp_path / "tier_results.yaml"
    path.write_text(yamlio.dump({"protocol_version": 4, "records": everything}))
    k, alpha, prefix = params.tiers.k, params.tiers.alpha, "time_aware_"
    keys = ["fault", "tier", "detector", "metric", "alpha"]

    frame = oodrl.load_results(path)
    aware = [r for r in everything if r["time_aware"]["operating_point"] is not None]
    assert 0 < len(aware) < len(everything)  # DETECTORS[1] has too few ID scores for the rule
    assert len(frame) == sum(5 + len(r["metrics"]) for r in everything) + 5 * len(aware)
    assert not frame.duplicated(keys).any()
    assert set(frame.alpha.dropna()) == {alpha}  # the operating points only, by default
    for record in everything:
        where = (
            (frame.fault == record["injector"]) & (frame.tier == record["tier"])
            & (frame.detector == record["detector"])
        )  # fmt: skip
        for name, point in (("", record["operating_point"]),
                            (prefix, record["time_aware"]["operating_point"])):  # fmt: skip
            rows = frame[where & (frame.metric == f"{name}detection_rate@{k}")]
            if point is None:
                assert rows.empty
                continue
            [row] = rows.itertuples()
            assert [row.value, row.ci_low, row.ci_high, row.n_streams, row.alpha] == [
                point["detection_rate"], *point["detection_rate_ci"], point["n_faulty"], alpha,
            ]  # fmt: skip
            [alarms] = frame[where & (frame.metric == f"{name}clean_false_alarm_rate")].itertuples()
            assert (alarms.value, alarms.n_streams) == (point["clean_false_alarm_rate"], 200)

    curves = oodrl.load_results(path, kind="tiers", alpha_curves=True)
    assert curves.equals(oodrl.load_results(path, alpha_curves=True))  # the file's name says tiers
    assert not curves.duplicated(keys).any()
    # The curve at the tier's α is the operating point: the default frame, row for row.
    at_alpha = curves[curves.alpha.isna() | (curves.alpha == alpha)].reset_index(drop=True)
    assert at_alpha.equals(frame)
    # Each rule's other supported α (200 calibration streams at δ = 0.1 support all but 0.01).
    others = [a for a in ALPHAS if a not in (alpha, 0.01)]
    assert len(curves) == len(frame) + 5 * len(others) * (len(everything) + len(aware))
    mild = next(r for r in aware if r["tier"] == "mild")
    entry = next(e for e in mild["alpha_curve"]["time_aware"] if e["alpha"] == 0.1)
    [row] = curves[
        (curves.fault == mild["injector"]) & (curves.tier == "mild")
        & (curves.detector == mild["detector"]) & (curves.alpha == 0.1)
        & (curves.metric == f"{prefix}detection_rate@{k}")
    ].itertuples()  # fmt: skip
    assert [row.value, row.ci_low, row.ci_high, row.n_streams] == [
        entry["detection_rate"], *entry["detection_rate_ci"], N_STREAMS,
    ]  # fmt: skip

    with pytest.raises(ConfigError, match="alpha_curves=True asks for the tier results' α curv"):
        results = tmp_path / "results.yaml"  # its name says kind "results"
        results.write_text(yamlio.dump({"protocol_version": 4, "records": []}))
        oodrl.load_results(results, alpha_curves=True)
