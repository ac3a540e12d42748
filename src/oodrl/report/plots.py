"""Figures of SPEC §7 (PNG) and the data files `dvc plots show` renders.

Figures are drawn on a bare `matplotlib.figure.Figure` with the Agg canvas — no pyplot, no
global backend switch — and saved without the PNG "Software" stamp, so the same data give the
same bytes. matplotlib is imported inside the functions: importing this module is cheap.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from oodrl.report.tables import (
    anomaly_key,
    anomaly_keys,
    anomaly_labels,
    anomaly_records,
    best_first,
    detector_means,
    stat,
    sweep_curves,
    sweep_grid,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DPI = 120
#: Score traces whose largest |score| exceeds this multiple of the median |score| get a log y-axis.
LOG_RANGE = 1e2


def _figure(width: float, height: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _save(figure: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, format="png", dpi=DPI, metadata={"Software": None})
    return path


def _colours(names: Sequence[str]) -> dict[str, Any]:
    """One fixed colour per detector (sorted names), the same in every figure."""
    from matplotlib import colormaps

    palette = colormaps["tab10" if len(names) <= 10 else "tab20"]
    return {name: palette(i % palette.N) for i, name in enumerate(sorted(names))}


def heatmap_matrix(results: Mapping[str, Any]) -> tuple[list[str], list[str], np.ndarray]:
    """Detectors (best mean first), anomaly labels and their (detector × anomaly) matched AUROC."""
    records = anomaly_records(results)
    rows = best_first(detector_means(records, "matched_auroc"), "matched_auroc")
    keys = anomaly_keys(records)
    labels = anomaly_labels(keys)
    matrix = np.full((len(rows), len(keys)), np.nan)
    for record in records:
        value = stat(record, "matched_auroc")
        if value is not None:
            matrix[rows.index(record["detector"]), keys.index(anomaly_key(record))] = value
    return rows, [labels[k] for k in keys], matrix


def plot_heatmap(results: Mapping[str, Any], path: str | Path) -> Path:
    """Detector × anomaly matched AUROC, annotated cells; 0.5 (chance) is white."""
    rows, columns, matrix = heatmap_matrix(results)
    modes = [k[1] for k in anomaly_keys(anomaly_records(results))]
    figure = _figure(2.6 + 0.95 * len(columns), 1.8 + 0.42 * len(rows))
    axes = figure.add_subplot()
    if matrix.size == 0:
        axes.text(0.5, 0.5, "no anomaly records", ha="center", va="center")
        axes.set_axis_off()
        return _save(figure, path)
    from matplotlib import colormaps

    colour_map = colormaps["RdBu"].with_extremes(bad="0.85")
    image = axes.imshow(
        np.ma.masked_invalid(matrix), cmap=colour_map, vmin=0.0, vmax=1.0, aspect="auto"
    )
    for (i, j), value in np.ndenumerate(matrix):
        text = "—" if np.isnan(value) else f"{value:.2f}"
        dark = not np.isnan(value) and abs(value - 0.5) > 0.3
        axes.text(
            j, i, text, ha="center", va="center", fontsize=8, color="white" if dark else "black"
        )
    axes.set_xticks(range(len(columns)), columns, rotation=35, ha="right", fontsize=8)
    axes.set_yticks(range(len(rows)), rows, fontsize=8)
    for mode in dict.fromkeys(modes):
        first, last = modes.index(mode), len(modes) - 1 - modes[::-1].index(mode)
        axes.text((first + last) / 2, -0.6, mode, ha="center", va="bottom", fontsize=8)
        if first > 0:
            axes.axvline(first - 0.5, color="black", linewidth=1.5)
    axes.set_title("Matched AUROC (perturbed vs. matched clean steps)", fontsize=10, pad=16)
    colourbar = figure.colorbar(image, ax=axes, fraction=0.05, pad=0.02)
    colourbar.set_label("matched AUROC (0.5 = chance)", fontsize=8)
    colourbar.ax.tick_params(labelsize=7)
    return _save(figure, path)


def plot_severity_curves(sweep: Mapping[str, Any], path: str | Path) -> Path:
    """One panel per injector: matched AUROC (95% CI band) against σ, one line per detector."""
    curves = sweep_curves(sweep)
    modes = sweep.get("modes", {})
    names = sorted({d for per_detector in curves.values() for d in per_detector})
    colours = _colours(names)
    n_columns = min(3, max(len(curves), 1))
    n_rows = max(math.ceil(len(curves) / n_columns), 1)
    figure = _figure(4.2 * n_columns, 3.0 * n_rows + 0.6)
    grid = figure.subplots(n_rows, n_columns, squeeze=False, sharey=True)
    for axes, (injector, per_detector) in zip(grid.flat, curves.items(), strict=False):
        for detector, (xs, means, lows, highs) in per_detector.items():
            colour = colours[detector]
            axes.fill_between(xs, lows, highs, color=colour, alpha=0.12, linewidth=0)
            axes.plot(xs, means, marker="o", markersize=3, color=colour, label=detector)
        axes.axhline(0.5, color="0.4", linestyle="--", linewidth=0.8)
        mode = f" ({modes[injector]})" if injector in modes else ""
        axes.set_title(f"{injector}{mode}", fontsize=9)
        axes.set_ylim(0.0, 1.02)
        axes.set_xlabel("severity σ", fontsize=8)
        axes.tick_params(labelsize=7)
        axes.grid(alpha=0.3, linewidth=0.5)
    for axes in grid[:, 0]:
        axes.set_ylabel("matched AUROC", fontsize=8)
    for axes in list(grid.flat)[len(curves) :]:
        axes.set_visible(False)
    if names:
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], color=colours[d], marker="o", markersize=3) for d in names]
        handles.append(Line2D([], [], color="0.4", linestyle="--", linewidth=0.8))
        figure.legend(
            handles,
            [*names, "chance"],
            loc="outside lower center",
            ncols=min(len(names) + 1, 5),
            fontsize=8,
            frameon=False,
        )
    return _save(figure, path)


def plot_score_traces(traces: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """One panel per trace (give one trace per anomaly): perturbed and matched clean scores of
    one episode, the onset t* and the alarm threshold θ; a log y-axis when the largest score
    is more than LOG_RANGE times the median one (symlog when some are ≤ 0)."""
    figure = _figure(9.0, 0.6 + 2.1 * max(len(traces), 1))
    panels = figure.subplots(max(len(traces), 1), 1, squeeze=False)[:, 0]
    for axes, trace in zip(panels, traces, strict=False):
        perturbed = np.asarray(trace["perturbed"], dtype=np.float64)
        clean = np.asarray(trace["clean"], dtype=np.float64)
        steps = np.arange(perturbed.size)
        onset, threshold = int(trace["onset"]), float(trace["threshold"])
        axes.axvspan(onset, perturbed.size - 1, color="C1", alpha=0.06, linewidth=0)
        axes.plot(steps, clean, color="0.55", linewidth=0.8, label="clean (matched)")
        axes.plot(steps, perturbed, color="C3", linewidth=0.9, label="perturbed")
        axes.axvline(onset, color="black", linestyle="--", linewidth=0.9, label="onset t*")
        axes.axhline(threshold, color="C0", linestyle=":", linewidth=1.1, label="threshold θ")
        _scale_y(axes, np.concatenate([perturbed, clean, [threshold]]))
        axes.set_xlim(0, perturbed.size - 1)
        axes.set_title(
            f"{trace['anomaly']} — {trace['detector']} (episode {trace['episode']})", fontsize=9
        )
        axes.set_ylabel("score", fontsize=8)
        axes.tick_params(labelsize=7)
    panels[-1].set_xlabel("step t", fontsize=8)
    if traces:
        handles, labels = panels[0].get_legend_handles_labels()
        figure.legend(
            handles, labels, loc="outside lower center", ncols=4, fontsize=8, frameon=False
        )
    return _save(figure, path)


def _scale_y(axes: Any, values: np.ndarray) -> None:
    """Log (all positive) or symlog y-axis when the largest |score| dwarfs the typical one."""
    magnitude = np.abs(values)
    positive = magnitude[magnitude > 0]
    if positive.size == 0:
        return
    # Zeros (e.g. CUSUM before any drift) must not drag the linear range down to nothing.
    typical = max(float(np.median(positive)), float(positive.max()) * 1e-6)
    if magnitude.max() / typical <= LOG_RANGE:
        return
    if (values > 0).all():
        axes.set_yscale("log")
    else:
        axes.set_yscale("symlog", linthresh=typical)
        if values.min() >= 0:
            axes.set_ylim(bottom=0)


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> Path:
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(
            [round(v, 6) + 0.0 if isinstance(v, float) else v for v in row] for row in rows
        )
    return path


def write_dvc_plot_data(
    results: Mapping[str, Any], sweep: Mapping[str, Any] | None, directory: str | Path
) -> list[Path]:
    """Small CSV files for `dvc plots show` / `dvc plots diff`; returns the paths written.

    - `detectors.csv`: detector and its means over anomalies (matched_auroc, matched_auprc,
      matched_fpr95, detection_delay, clean_alarm_rate); e.g. template `bar_horizontal_sorted`,
      x `matched_auroc`, y `detector`.
    - `heatmap.csv`: detector, anomaly, matched_auroc (long format).
    - with a sweep, `sweep.csv`: injector, detector, severity, matched_auroc, ci_low, ci_high
      (long), and `sweep_<injector>.csv`: severity and one matched-AUROC column per detector
      (template `linear`, x `severity`, y the detector columns).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    records = anomaly_records(results)
    columns = [
        "matched_auroc",
        "matched_auprc",
        "matched_fpr95",
        "detection_delay",
        "clean_alarm_rate",
    ]
    means = {m: detector_means(records, m) for m in columns}
    order = best_first(means["matched_auroc"], "matched_auroc")
    written = [
        _write_csv(
            directory / "detectors.csv",
            ["detector", *columns],
            [[d, *("" if means[m][d] is None else means[m][d] for m in columns)] for d in order],
        )
    ]
    rows, anomalies, matrix = heatmap_matrix(results)
    written.append(
        _write_csv(
            directory / "heatmap.csv",
            ["detector", "anomaly", "matched_auroc"],
            [
                [d, a, float(matrix[i, j])]
                for i, d in enumerate(rows)
                for j, a in enumerate(anomalies)
                if not np.isnan(matrix[i, j])
            ],
        )
    )
    if sweep:
        curves = sweep_curves(sweep)
        long_rows = [
            [injector, detector, x, mean, low, high]
            for injector, per_detector in curves.items()
            for detector, series in per_detector.items()
            for x, mean, low, high in zip(*series, strict=True)
        ]
        written.append(
            _write_csv(
                directory / "sweep.csv",
                ["injector", "detector", "severity", "matched_auroc", "ci_low", "ci_high"],
                long_rows,
            )
        )
        for injector, per_detector in curves.items():
            severities, names, lookup = sweep_grid(per_detector)
            written.append(
                _write_csv(
                    directory / f"sweep_{injector}.csv",
                    ["severity", *names],
                    [[x, *(lookup.get((d, x), "") for d in names)] for x in severities],
                )
            )
    return written
