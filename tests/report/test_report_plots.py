"""Figures are non-empty, deterministic PNGs; DVC plot data are small, stable CSV files."""

import csv

import numpy as np
import pytest

from oodrl.report.plots import (
    heatmap_matrix,
    plot_heatmap,
    plot_score_traces,
    plot_severity_curves,
    write_dvc_plot_data,
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def traces():
    rng = np.random.default_rng(0)
    T, onset = 120, 40
    clean = np.abs(rng.normal(1.0, 0.2, size=T))
    jump = clean.copy()
    jump[onset:] *= 1e4  # spans 4 decades: log axis
    drift = np.cumsum(rng.normal(size=T))
    return [
        {"anomaly": "stuck_actuator", "detector": "pedm", "episode": 0, "perturbed": jump,
         "clean": clean, "threshold": 1.5, "onset": onset},
        {"anomaly": "gradual_drift", "detector": "cusum", "episode": 2,
         "perturbed": drift + np.r_[np.zeros(onset), np.linspace(0, 20, T - onset)],
         "clean": drift, "threshold": 5.0, "onset": onset},
    ]  # fmt: skip


@pytest.mark.parametrize(
    "draw",
    [
        lambda results, sweep, path: plot_heatmap(results, path),
        lambda results, sweep, path: plot_severity_curves(sweep, path),
        lambda results, sweep, path: plot_score_traces(traces(), path),
    ],
    ids=["heatmap", "severity_curves", "score_traces"],
)
def test_plots_are_deterministic_pngs(draw, results, sweep, tmp_path):
    first = draw(results, sweep, tmp_path / "a" / "figure.png")
    second = draw(results, sweep, tmp_path / "b.png")
    data = first.read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 10_000
    assert data == second.read_bytes()
    assert b"Software" not in data


def test_heatmap_matrix_orders_detectors_by_mean_auroc(results):
    rows, columns, matrix = heatmap_matrix(results)
    assert matrix.shape == (8, 9)
    means = np.nanmean(matrix, axis=1)
    assert list(means) == sorted(means, reverse=True)
    assert columns[:5] == sorted(columns[:5])  # post-hoc anomalies first, by name


def test_degenerate_inputs_still_draw(tmp_path):
    assert plot_heatmap({"records": []}, tmp_path / "h.png").stat().st_size > 0
    assert plot_severity_curves({"sweep": {}}, tmp_path / "s.png").stat().st_size > 0
    assert plot_score_traces([], tmp_path / "t.png").stat().st_size > 0


def test_dvc_plot_data(results, sweep, tmp_path):
    paths = write_dvc_plot_data(results, sweep, tmp_path / "plots")
    names = sorted(p.name for p in paths)
    assert names[:3] == ["detectors.csv", "heatmap.csv", "sweep.csv"]
    assert len(names) == 3 + 9
    with (tmp_path / "plots" / "sweep_gradual_drift.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [float(r["severity"]) for r in rows] == [0.1, 0.2, 0.4, 0.6, 0.8]
    assert set(rows[0]) == {"severity", "autoencoder", "cusum", "ensemble_disagreement",
                            "kde_density", "lyapunov_divergence", "mahalanobis_distance",
                            "pedm", "time_series_features"}  # fmt: skip
    with (tmp_path / "plots" / "sweep.csv").open() as handle:
        long_rows = list(csv.DictReader(handle))
    assert len(long_rows) == 9 * 8 * 5
    assert set(long_rows[0]) == {
        "injector",
        "detector",
        "severity",
        "matched_auroc",
        "ci_low",
        "ci_high",
    }
    with (tmp_path / "plots" / "heatmap.csv").open() as handle:
        assert len(list(csv.DictReader(handle))) == 8 * 9
    again = write_dvc_plot_data(results, sweep, tmp_path / "again")
    for a, b in zip(paths, again, strict=True):
        assert a.read_bytes() == b.read_bytes()
    assert [p.name for p in write_dvc_plot_data(results, None, tmp_path / "x")] == [
        "detectors.csv",
        "heatmap.csv",
    ]
