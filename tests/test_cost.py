"""Cost beside accuracy (SPEC §13): fitted size and streaming latency of real fitted detectors,
and the fit time the fit stage records."""

from __future__ import annotations

import json

import pytest

from oodrl.detectors import DETECTORS
from oodrl.io.store import save_detector
from oodrl.metrics.cost import detector_costs, stream_latencies_ns, timed_streams

NAMES = ["cusum", "mahalanobis_distance", "lyapunov_divergence"]  # lyapunov: latency 5, flushes


@pytest.fixture(scope="module")
def fitted(heuristic_clean, tmp_path_factory):
    """name -> pickle written as the fit stage writes it; fitted on 3, calibrated on 2 streams."""
    streams = heuristic_clean.trajectories()
    models = tmp_path_factory.mktemp("models")
    paths = {}
    for name in NAMES:
        detector = DETECTORS.get(name)().fit(streams[:3])
        detector.calibrate(streams[3:5])
        paths[name] = models / f"{name}.pkl"
        save_detector(paths[name], detector, name, {})
    return paths


def test_every_detector_gets_its_size_and_latency(fitted, heuristic_clean):
    clean = heuristic_clean.trajectories()[5:]
    costs = detector_costs(fitted, clean, {"cusum": 0.25})
    assert list(costs) == NAMES
    for name, cost in costs.items():
        assert set(cost) == {"fit_s", "fitted_bytes", "step_us_median", "step_us_p99"}
        assert cost["fitted_bytes"] == fitted[name].stat().st_size
        assert cost["step_us_p99"] >= cost["step_us_median"] > 0, name
    assert costs["cusum"]["fit_s"] == 0.25
    assert costs["mahalanobis_distance"]["fit_s"] is None  # no fit record: unknown, not 0


def test_latency_is_one_figure_per_streamed_step(fitted, heuristic_clean):
    from oodrl.io.store import load_detector

    clean = heuristic_clean.trajectories()[5:7]
    detector = load_detector(fitted["lyapunov_divergence"], stage="fit")
    latencies = stream_latencies_ns(detector, clean)
    assert latencies.shape == (sum(t.T for t in clean),) and (latencies > 0).all()


def test_timed_streams_are_whole_and_just_enough(heuristic_clean):
    streams = heuristic_clean.trajectories()  # 8 streams of 300 steps
    assert len(timed_streams(streams, min_steps=1000)) == 4
    assert len(timed_streams(streams, min_steps=300)) == 1
    assert timed_streams(streams, min_steps=10_000) == streams


def test_fit_stage_records_its_fit_time_beside_its_wall_time(tmp_path, monkeypatch):
    from oodrl.report.provenance import fit_seconds, timing_records
    from oodrl.stages.common import TIMINGS_DIR, timed_stage

    monkeypatch.chdir(tmp_path)
    with timed_stage("detectors/cusum/dvc.yaml:fit") as record:
        record.update(detector="cusum", fit_s=0.5)
    with timed_stage("metrics"):
        pass
    records = timing_records(TIMINGS_DIR)
    assert {r["stage"] for r in records} == {"detectors/cusum/dvc.yaml:fit", "metrics"}
    assert all(r["wall_s"] >= 0 for r in records)
    assert fit_seconds(records) == {"cusum": 0.5}
    written = json.loads((TIMINGS_DIR / "detectors_cusum_dvc.yaml_fit.json").read_text())
    assert written["fit_s"] == 0.5
