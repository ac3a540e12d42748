"""Figures are non-empty, deterministic PNGs; DVC plot data are small, stable CSV files."""

import csv

import numpy as np
import pytest

from oodrl.report.plots import (
    ScoreTraces,
    headline_severities,
    heatmap_matrix,
    linear_range,
    plot_heatmap,
    plot_score_traces,
    plot_severity_curves,
    write_dvc_plot_data,
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def traces():
    rng = np.random.default_rng(0)
    N, T, onset = 6, 120, 40
    clean = np.abs(rng.normal(1.0, 0.2, size=(N, T)))
    jump = clean.copy()
    jump[:, onset:] *= 1e4  # spans 4 decades: linear below θ, logarithmic above
    drift = np.cumsum(rng.normal(size=(N, T)), axis=1)
    ramp = np.r_[np.zeros(onset), np.linspace(0, 20, T - onset)]
    return [
        ScoreTraces("stuck_actuator", "pedm", jump, clean, 1.5, onset, 0.97, examples=2),
        ScoreTraces("gradual_drift", "cusum", drift + ramp, drift, 5.0, onset, 0.8),
    ]


@pytest.mark.parametrize(
    "draw",
    [
        lambda results, sweep, path: plot_heatmap(results, path),
        lambda results, sweep, path: plot_severity_curves(sweep, path, results),
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
    assert [p.name for p in paths] == ["detectors.csv", "heatmap.csv", "sweep.csv"]
    with (tmp_path / "plots" / "sweep.csv").open() as handle:
        long_rows = list(csv.DictReader(handle))
    assert len(long_rows) == 9 * 8 * 5
    assert list(long_rows[0]) == [
        "injector",
        "detector",
        "severity",
        "matched_auroc",
        "ci_low",
        "ci_high",
        "headline_severity",
    ]
    assert {r["headline_severity"] for r in long_rows} == {"0.5"}
    with (tmp_path / "plots" / "heatmap.csv").open() as handle:
        assert len(list(csv.DictReader(handle))) == 8 * 9
    with (tmp_path / "plots" / "detectors.csv").open() as handle:
        aurocs = [float(r["matched_auroc"]) for r in csv.DictReader(handle)]
    assert aurocs == sorted(aurocs, reverse=True)
    again = write_dvc_plot_data(results, sweep, tmp_path / "again")
    for a, b in zip(paths, again, strict=True):
        assert a.read_bytes() == b.read_bytes()
    assert [p.name for p in write_dvc_plot_data(results, None, tmp_path / "x")] == [
        "detectors.csv",
        "heatmap.csv",
    ]


def test_headline_severity_comes_from_the_results(results):
    assert headline_severities(results) == dict.fromkeys(
        {r["injector"] for r in results["records"] if r["kind"] == "anomaly"}, 0.5
    )


def test_trace_axes_stay_linear_over_the_threshold_and_the_clean_scores():
    clean = np.r_[np.zeros(95), np.linspace(1, 3, 5)][None, :]
    # θ above the clean scores: linear up to θ.
    assert linear_range(clean, threshold=10.0) == 10.0
    # Clean scores above θ (a false alarm burst): linear over their 99th percentile.
    assert linear_range(clean, threshold=0.5) == pytest.approx(np.quantile(clean, 0.99))
    # Nothing but zeros: a unit range rather than a degenerate axis.
    assert linear_range(np.zeros((1, 10)), threshold=0.0) == 1.0


def test_trace_panels_use_symlog_only_when_scores_leave_the_linear_range(tmp_path):
    from matplotlib.figure import Figure

    figure = Figure()
    scaled = plot_score_traces_axes(figure, traces())
    assert [axes.get_yscale() for axes in scaled] == ["symlog", "linear"]
    assert scaled[0].yaxis.get_transform().linthresh == 1.5  # θ, above the clean scores


def plot_score_traces_axes(figure, trace_list):
    from oodrl.report.plots import _draw_traces

    axes = figure.subplots(1, len(trace_list))
    for panel, trace in zip(axes, trace_list, strict=True):
        _draw_traces(panel, trace)
    return list(axes)
