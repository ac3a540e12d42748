"""The metrics stage: score stores -> results.yaml, sweep_results.yaml, metrics.json, tables.md.

It reads the score stores dvc.yaml's score stages write, laid out as
`<scores>/<detector>/eval.zarr` and `<scores>/<detector>/<injector>.zarr`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from oodrl import yamlio
from oodrl.config import Params
from oodrl.core.spec import make_labels
from oodrl.fileio import atomic_write_text
from oodrl.progress import progress_bar
from oodrl.stages.score import CLEAN_GROUP, HEADLINE_GROUP
from oodrl.store import read_scores, severity_key


def score_store(scores_dir: Path, detector: str, scored_set: str) -> Path:
    """Where a score stage writes `detector`'s scores of `scored_set` ('eval' or an injector)."""
    return Path(scores_dir) / detector / f"{scored_set}.zarr"


def _settings(params: Params):
    from oodrl.metrics.aggregate import MetricSettings

    m = params.metrics
    return MetricSettings(
        n_boot=m.n_boot,
        ci=m.ci,
        tpr_target=m.tpr_target,
        temporal_buffer=m.temporal_buffer,
        seed=params.seed,
    )


#: Metrics whose per-episode values headline records keep, for the suite's leaderboard
#: (its stratified bootstrap resamples the episodes of every cell).
EPISODE_METRICS = ("matched_auroc",)


def _summary(
    group: dict, clean: np.ndarray, threshold: float, spec: dict, settings, detector, latency
) -> tuple[dict, dict[str, list[float]]]:
    """Mean, std and CI of every metric for one perturbed set against its matched clean set,
    and the per-episode values of EPISODE_METRICS."""
    from oodrl.metrics.aggregate import episode_metrics, summarise

    per_episode = episode_metrics(
        group["scores"], clean, group["labels"], threshold,
        spec["onset"], spec["offset"], settings, detector, latency,
    )  # fmt: skip
    kept = {m: [round(float(v), 6) + 0.0 for v in per_episode[m]] for m in EPISODE_METRICS}
    return summarise(per_episode, settings), kept


def _null_metrics(params: Params, clean: np.ndarray, threshold: float, settings, detector, latency):
    """The null baseline: clean scores judged against the counterfactual labels."""
    from oodrl.metrics.aggregate import null_episode_metrics, summarise

    T, onset, offset = params.env.T, params.env.resolved_onset, params.anomaly.offset
    labels = np.tile(make_labels(T, onset, offset), (clean.shape[0], 1))
    per_episode = null_episode_metrics(
        clean, labels, threshold, onset, offset, settings, detector, latency
    )
    return summarise(per_episode, settings)


def _detector_results(params: Params, scores_dir: Path, detector: str):
    """One detector's anomaly records, its sweep summaries, and the injectors' modes."""
    settings = _settings(params)
    # The look-ahead follows from the detector's params alone (e.g. lyapunov's horizon).
    latency = params.detector(detector).latency
    eval_path = score_store(scores_dir, detector, "eval")
    clean_groups, clean_attrs = read_scores(eval_path, stage=f"score_clean@{detector}")
    clean = clean_groups[CLEAN_GROUP]["scores"]
    threshold = float(clean_attrs["threshold"])
    records, sweep, modes = [], {}, {}
    for injector in params.benchmark.injectors:
        path = score_store(scores_dir, detector, injector)
        groups, attrs = read_scores(path, stage=f"score@{detector}-{injector}")
        spec, modes[injector] = attrs["spec"], attrs["mode"]
        headline, episodes = _summary(
            groups[HEADLINE_GROUP], clean, threshold, spec, settings, detector, latency
        )
        records.append({
            "kind": "anomaly", "detector": detector, "anomaly": injector,
            "mode": attrs["mode"], "severity": spec["severity"], "latency": latency,
            "metrics": headline, "episodes": episodes,
        })  # fmt: skip
        for severity in attrs["severities"]:
            sweep[(injector, float(severity))], _ = _summary(
                groups[severity_key(severity)], clean, threshold,
                {**spec, "severity": severity}, settings, detector, latency,
            )  # fmt: skip
    null = _null_metrics(params, clean, threshold, settings, detector, latency)
    records.extend(
        {"kind": "null", "detector": detector, "anomaly": "null", "mode": mode,
         "severity": None, "latency": latency, "metrics": null}
        for mode in sorted(set(modes.values()))
    )  # fmt: skip
    return records, sweep, modes


def compute_results(params: Params, scores_dir: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Every (detector, anomaly) headline record, the null baselines, and the sweep.

    Detectors are summarised in parallel (executor.workers); each summary is seeded alone,
    so the results do not depend on the worker count. The clean evaluation set is the
    matched counterpart of both execution modes (online runs re-use its seeds), so each
    mode's null baseline is computed on the same clean scores.
    """
    detectors = params.benchmark.detectors
    workers = min(params.executor.resolved_workers, len(detectors))
    with progress_bar(len(detectors), "metrics", params.executor.progress) as bar:
        if workers > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            context = multiprocessing.get_context("fork")
            with ProcessPoolExecutor(workers, mp_context=context) as pool:
                futures = [pool.submit(_detector_results, params, scores_dir, d) for d in detectors]
                parts = []
                for future in futures:
                    parts.append(future.result())
                    bar.update()
        else:
            parts = []
            for detector in detectors:
                parts.append(_detector_results(params, scores_dir, detector))
                bar.update()
    records: list[dict[str, Any]] = []
    sweep: dict[str, dict[float, dict[str, Any]]] = {i: {} for i in params.benchmark.injectors}
    modes: dict[str, str] = {}
    for detector, (detector_records, detector_sweep, detector_modes) in zip(
        detectors, parts, strict=True
    ):
        records.extend(detector_records)
        modes.update(detector_modes)
        for (injector, severity), summary in detector_sweep.items():
            sweep[injector].setdefault(severity, {})[detector] = summary
    records.sort(key=lambda r: (r["kind"], r["detector"], r["anomaly"], r["mode"]))
    return {"records": records}, {"modes": modes, "sweep": sweep}


def run_metrics(
    params: Params,
    scores_dir: Path,
    results_path: Path,
    sweep_path: Path,
    metrics_path: Path,
    tables_path: Path,
) -> None:
    from oodrl.report.tables import metrics_json, render_tables

    results, sweep = compute_results(params, scores_dir)
    atomic_write_text(results_path, yamlio.dump(results))
    atomic_write_text(sweep_path, yamlio.dump(sweep))
    atomic_write_text(
        metrics_path, json.dumps(metrics_json(results), indent=2, sort_keys=True) + "\n"
    )
    atomic_write_text(tables_path, render_tables(results, sweep))
