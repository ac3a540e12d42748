"""A run's figures: the matched-AUROC heatmap, the severity curves, and the score traces of the
detector worth looking at per anomaly (the best by matched AUROC)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from oodrl.config import Params
from oodrl.io.layout import CLEAN_GROUP, HEADLINE_GROUP, score_store
from oodrl.io.store import read_scores
from oodrl.report.plots import (
    ScoreTraces,
    plot_heatmap,
    plot_score_traces,
    plot_severity_curves,
)
from oodrl.report.tables import record_injector


def best_detectors(results: dict[str, Any]) -> dict[str, tuple[float, str]]:
    """Anomaly -> (mean matched AUROC, detector) of its best detector; a tie goes to the name
    that sorts last."""
    best: dict[str, tuple[float, str]] = {}
    for record in results["records"]:
        if record["kind"] == "anomaly":
            auroc = record["metrics"]["matched_auroc"]["mean"]
            injector = record_injector(record)
            best[injector] = max(best.get(injector, (-1.0, "")), (auroc, record["detector"]))
    return best


def score_traces(params: Params, results: dict[str, Any], scores_dir: Path) -> list[ScoreTraces]:
    """Per anomaly, its best detector's scores on every perturbed episode and every matched
    clean one."""
    best, traces = best_detectors(results), []
    for anomaly in params.benchmark.injectors:
        auroc, detector = best[anomaly]
        clean_groups, attrs = read_scores(score_store(scores_dir, detector))
        groups, ood_attrs = read_scores(score_store(scores_dir, detector, anomaly))
        traces.append(
            ScoreTraces(
                anomaly=anomaly,
                detector=detector,
                perturbed=groups[HEADLINE_GROUP]["scores"],
                clean=clean_groups[CLEAN_GROUP]["scores"],
                threshold=float(attrs["threshold"]),
                onset=int(ood_attrs["spec"]["onset"]),
                matched_auroc=auroc,
                examples=params.metrics.traces_per_anomaly,
            )
        )
    return traces


def write_figures(
    params: Params, results: dict[str, Any], sweep: dict[str, Any], scores_dir: Path, out: Path
) -> None:
    """matched_auroc_heatmap.png, severity_curves.png and score_traces.png under `out`."""
    out.mkdir(parents=True, exist_ok=True)
    plot_heatmap(results, out / "matched_auroc_heatmap.png")
    plot_severity_curves(sweep, out / "severity_curves.png", results)
    plot_score_traces(score_traces(params, results, scores_dir), out / "score_traces.png")
