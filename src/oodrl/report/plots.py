"""Figures of SPEC §7 (PNG) and the data files `dvc plots show` renders.

Figures are drawn on a bare `matplotlib.figure.Figure` with the Agg canvas — no pyplot, no
global backend switch — and saved without the PNG "Software" stamp, so the same data give the
same bytes. matplotlib is imported inside the functions: importing this module is cheap.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
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
    record_injector,
    stat,
    sweep_curves,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DPI = 120
#: Quantiles of the episode bands of the score traces: the middle 80% of episodes at each step.
BAND = (0.1, 0.9)


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


def headline_points(results: Mapping[str, Any]) -> dict[str, dict[str, tuple[float, float]]]:
    """injector -> detector -> (headline severity, its matched AUROC there), from results.yaml."""
    points: dict[str, dict[str, tuple[float, float]]] = {}
    for record in anomaly_records(results):
        value = stat(record, "matched_auroc")
        if value is not None and record["severity"] is not None:
            point = (float(record["severity"]), value)
            points.setdefault(record_injector(record), {})[record["detector"]] = point
    return points


def headline_severities(results: Mapping[str, Any]) -> dict[str, float]:
    """injector -> its headline severity σ (the severity of its records in results.yaml)."""
    return {
        injector: next(iter(per_detector.values()))[0]
        for injector, per_detector in headline_points(results).items()
    }


def plot_severity_curves(
    sweep: Mapping[str, Any], path: str | Path, results: Mapping[str, Any] | None = None
) -> Path:
    """One panel per injector: matched AUROC (95% CI band) against σ, one line per detector.

    With `results`, each panel marks the headline severity (dotted vertical line) and each
    detector's headline matched AUROC there (a star): the number the tables report, in context.
    """
    curves = sweep_curves(sweep)
    headline = headline_points(results or {})
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
        _mark_headline(axes, headline.get(injector, {}), colours)
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
        _severity_legend(figure, names, colours, with_headline=bool(headline))
    return _save(figure, path)


def _mark_headline(
    axes: Any, points: Mapping[str, tuple[float, float]], colours: Mapping[str, Any]
) -> None:
    """The headline severity as a dotted line, each detector's headline value as a star."""
    if not points:
        return
    axes.axvline(next(iter(points.values()))[0], color="black", linestyle=":", linewidth=1.0)
    for detector, (severity, value) in points.items():
        axes.plot(severity, value, marker="*", markersize=9, linestyle="none",
                  color=colours.get(detector, "0.5"), markeredgecolor="black",
                  markeredgewidth=0.5)  # fmt: skip


def _severity_legend(
    figure: Figure, names: Sequence[str], colours: Mapping[str, Any], with_headline: bool
) -> None:
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=colours[d], marker="o", markersize=3) for d in names]
    labels = [*names, "chance"]
    handles.append(Line2D([], [], color="0.4", linestyle="--", linewidth=0.8))
    if with_headline:
        handles.append(Line2D([], [], color="black", linestyle=":", linewidth=1.0, marker="*",
                              markersize=9, markerfacecolor="white"))  # fmt: skip
        labels.append("headline σ (star: its matched AUROC)")
    figure.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 5),
                  fontsize=8, frameon=False)  # fmt: skip


@dataclass(frozen=True, eq=False)
class ScoreTraces:
    """One detector's scores on one anomaly: every perturbed episode (N, T) and its matched
    clean episode (N, T), the alarm threshold θ, the onset t*, the detector's matched AUROC
    on that anomaly, and how many episodes to draw one by one besides the quantile bands."""

    anomaly: str
    detector: str
    perturbed: np.ndarray
    clean: np.ndarray
    threshold: float
    onset: int
    matched_auroc: float
    examples: int = 1


def plot_score_traces(traces: Sequence[ScoreTraces], path: str | Path) -> Path:
    """One panel per anomaly: how its detector's perturbed and clean scores separate after t*.

    Each panel shows, over all episodes, the median and the 10–90% band of the perturbed scores
    and of the matched clean scores at every step, `examples` episodes as thin lines, the onset
    t* and the threshold θ. The y-axis is linear over `linear_range` (θ and the clean scores)
    and logarithmic beyond it, so an accumulating score (CUSUM reaches 1e8) neither flattens
    the clean scores and θ to zero nor leaves the panel.
    """
    n_columns = min(3, max(len(traces), 1))
    n_rows = max(math.ceil(len(traces) / n_columns), 1)
    figure = _figure(4.3 * n_columns, 0.8 + 2.7 * n_rows)
    grid = figure.subplots(n_rows, n_columns, squeeze=False)
    for axes, trace in zip(grid.flat, traces, strict=False):
        _draw_traces(axes, trace)
    for axes in list(grid.flat)[len(traces) :]:
        axes.set_visible(False)
    if traces:
        figure.suptitle(
            "Scores of the best detector per anomaly (by matched AUROC), all episodes; the y-axis "
            "is linear up to θ and the clean scores, logarithmic above",
            fontsize=9,
        )
        handles, labels = grid.flat[0].get_legend_handles_labels()
        figure.legend(
            handles, labels, loc="outside lower center", ncols=3, fontsize=8, frameon=False
        )
    return _save(figure, path)


def _draw_traces(axes: Any, trace: ScoreTraces) -> None:
    perturbed = np.atleast_2d(np.asarray(trace.perturbed, dtype=np.float64))
    clean = np.atleast_2d(np.asarray(trace.clean, dtype=np.float64))
    steps = np.arange(perturbed.shape[1])
    axes.axvspan(trace.onset, steps[-1], color="C1", alpha=0.06, linewidth=0)
    for scores, colour, name in ((clean, "0.4", "clean (matched)"), (perturbed, "C3", "perturbed")):
        low, median, high = np.quantile(scores, [BAND[0], 0.5, BAND[1]], axis=0)
        band = f"{name}: 10–90% of {len(scores)} episodes"
        axes.fill_between(steps, low, high, color=colour, alpha=0.2, linewidth=0, label=band)
        axes.plot(steps, median, color=colour, linewidth=1.4, label=f"{name}: median")
        for episode in scores[: trace.examples]:
            axes.plot(steps, episode, color=colour, linewidth=0.5, alpha=0.7)
    axes.axvline(trace.onset, color="black", linestyle="--", linewidth=0.9, label="onset t*")
    axes.axhline(trace.threshold, color="C0", linestyle=":", linewidth=1.4, label="threshold θ")
    axes.annotate(f"θ = {trace.threshold:.3g}", (0.01, trace.threshold),
                  xycoords=("axes fraction", "data"), xytext=(0, 2), textcoords="offset points",
                  fontsize=7, color="C0", va="bottom")  # fmt: skip
    _linear_then_log(axes, linear_range(clean, trace.threshold), perturbed, clean)
    axes.set_xlim(0, steps[-1])
    title = f"{trace.anomaly}\n{trace.detector} (matched AUROC {trace.matched_auroc:.2f})"
    axes.set_title(title, fontsize=8)
    axes.set_xlabel("step t", fontsize=7)
    axes.set_ylabel("score", fontsize=7)
    axes.tick_params(labelsize=7)


def linear_range(clean: np.ndarray, threshold: float) -> float:
    """Where a trace panel's y-axis turns logarithmic: the larger of |θ| and the 99th
    percentile of the clean |scores| (1 if both are 0)."""
    scale = max(abs(threshold), float(np.quantile(np.abs(clean), 0.99)))
    return scale if scale > 0 else 1.0


def _linear_then_log(axes: Any, linear: float, *scores: np.ndarray) -> None:
    """A symlog y-axis, linear within ±`linear`, when some score lies 10× beyond it."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter, SymmetricalLogLocator

    low = min(float(s.min()) for s in scores)
    high = max(float(s.max()) for s in scores)
    axes.yaxis.set_major_formatter(FuncFormatter(_tick_label))  # never a "1e8" offset text
    if max(abs(low), abs(high)) <= 10 * linear:
        return
    # The linear part (θ and the clean scores) gets as much height as three decades.
    axes.set_yscale("symlog", linthresh=linear, linscale=3.0)
    axes.yaxis.set_major_locator(FixedLocator(_decade_ticks(linear, low, high)))
    axes.yaxis.set_minor_locator(SymmetricalLogLocator(linthresh=linear, base=10))
    axes.yaxis.set_minor_formatter(NullFormatter())
    if low >= 0:
        axes.set_ylim(bottom=0)


def _decade_ticks(linear: float, low: float, high: float, most: int = 4) -> list[float]:
    """0 and at most `most` powers of ten on each side beyond the linear range, evenly thinned,
    so that the labels of a short panel do not overlap."""
    ticks = [0.0]
    for sign, extreme in ((1.0, high), (-1.0, -low)):
        if extreme <= linear:
            continue
        first, last = math.ceil(math.log10(linear)), math.floor(math.log10(extreme))
        step = max(1, math.ceil((last - first + 1) / most))
        ticks += [sign * 10.0**k for k in range(last, first - 1, -step)]
    return sorted(ticks)


def _tick_label(value: float, _position: int) -> str:
    if abs(value) >= 1e4:
        return f"{value:.0e}".replace("e+0", "e").replace("e+", "e")
    return f"{value:g}"


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> Path:
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(
            [round(v, 6) + 0.0 if isinstance(v, float) else v for v in row] for row in rows
        )
    return path


#: Per-detector means over anomalies in detectors.csv (the bar chart draws matched_auroc).
DETECTOR_COLUMNS = (
    "matched_auroc",
    "matched_auprc",
    "matched_fpr95",
    "detection_delay",
    "clean_alarm_rate",
)


def write_dvc_plot_data(
    results: Mapping[str, Any], sweep: Mapping[str, Any] | None, directory: str | Path
) -> list[Path]:
    """Small CSV files for `dvc plots show` / `dvc plots diff`; returns the paths written.

    Drawn by the Vega-Lite templates of `oodrl.report.offline.PLOTS`:

    - `detectors.csv`: detector and its means over anomalies (DETECTOR_COLUMNS; matched_auprc
      is average precision), best matched AUROC first — bars from zero.
    - `heatmap.csv`: detector, anomaly, matched_auroc (long format) — a heatmap.
    - with a sweep, `sweep.csv`: injector, detector, severity, matched_auroc, ci_low, ci_high
      and the injector's headline_severity (long) — severity curves, one panel per injector,
      one colour per detector, the headline severity marked.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    records = anomaly_records(results)
    means = {m: detector_means(records, m) for m in DETECTOR_COLUMNS}
    order = best_first(means["matched_auroc"], "matched_auroc")
    written = [
        _write_csv(
            directory / "detectors.csv",
            ["detector", *DETECTOR_COLUMNS],
            [
                [d, *("" if means[m][d] is None else means[m][d] for m in DETECTOR_COLUMNS)]
                for d in order
            ],
        )  # fmt: skip
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
        headline = headline_severities(results)
        written.append(
            _write_csv(
                directory / "sweep.csv",
                [
                    "injector",
                    "detector",
                    "severity",
                    "matched_auroc",
                    "ci_low",
                    "ci_high",
                    "headline_severity",
                ],
                [
                    [injector, detector, x, mean, low, high, headline.get(injector, "")]
                    for injector, per_detector in sweep_curves(sweep).items()
                    for detector, series in per_detector.items()
                    for x, mean, low, high in zip(*series, strict=True)
                ],
            )  # fmt: skip
        )
    return written
