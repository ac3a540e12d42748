"""A run's results (SPEC §6, §7): one typed record per (detector, anomaly) headline cell and per
null baseline, and the severity sweep, computed from the score stores of a pipeline's score
stages (paths in `oodrl.io.layout`).

`results.yaml` holds `{"records": [record, ...]}`, each record as `ResultRecord.as_dict` writes
it; `sweep_results.yaml` holds `{"modes": {injector: mode}, "sweep": {injector: {severity:
{detector: summary}}}}`. A summary maps a metric to {mean, std, ci_low, ci_high, n_episodes}.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from oodrl.config import Params
from oodrl.core.spec import make_labels
from oodrl.errors import StoreError
from oodrl.io import yamlio
from oodrl.io.layout import (
    CLEAN_GROUP,
    HEADLINE_GROUP,
    detector_stage,
    score_store,
    sweep_score_store,
)
from oodrl.io.store import read_scores, restore_hint, severity_key
from oodrl.parallel import ordered_map
from oodrl.progress import progress_bar

Summary = dict[str, dict[str, float | int]]

#: Metrics whose per-episode values headline records keep, for the suite's leaderboard
#: (its stratified bootstrap resamples the episodes of every cell).
EPISODE_METRICS = ("matched_auroc",)


@dataclass(frozen=True)
class ResultRecord:
    """One detector's metric summaries on one condition: an injector's anomaly at its headline
    severity (`kind` "anomaly"), or the clean evaluation set against the counterfactual labels
    of one execution mode (`kind` "null": `injector` and `severity` None). Files written before
    `injector` held the name under `anomaly` (null records: "null"); readers take either
    (`oodrl.report.tables.record_injector`)."""

    kind: Literal["anomaly", "null"]
    detector: str
    injector: str | None
    mode: str
    severity: float | None
    latency: int
    metrics: Summary
    episodes: dict[str, list[float]] | None = None
    """Per-episode values of EPISODE_METRICS; anomaly records only."""

    def as_dict(self) -> dict[str, Any]:
        """The record as results.yaml holds it (a null record has no `episodes`).

        Not `dataclasses.asdict`: its deep copy would part the null records of two modes,
        which share one summary and so one YAML anchor in results.yaml.
        """
        record = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        if self.episodes is None:
            del record["episodes"]
        return record


@dataclass(frozen=True)
class Results:
    """Every record (sorted by kind, detector, injector, mode), each injector's execution mode,
    the sweep summaries by injector, severity and detector, and each detector's threshold rule
    with the false-alarm rate it promises on clean data (`nominal_false_alarms`), and the
    detectors not certified machine-independent (SPEC §14, §17)."""

    records: list[ResultRecord]
    modes: dict[str, str]
    sweep: dict[str, dict[float, dict[str, Summary]]]
    thresholds: dict[str, dict[str, Any]]
    uncertified: list[str] = dataclasses.field(default_factory=list)

    def results_document(self) -> dict[str, Any]:
        """results.yaml's content; the uncertified detectors' list only when there are some."""
        from oodrl.report.tables import UNCERTIFIED

        document = {
            "records": [record.as_dict() for record in self.records],
            "thresholds": self.thresholds,
        }
        if self.uncertified:
            document[UNCERTIFIED] = self.uncertified
        return document

    def sweep_document(self) -> dict[str, Any]:
        """sweep_results.yaml's content."""
        return {"modes": self.modes, "sweep": self.sweep}


def nominal_false_alarms(params: Params) -> dict[str, dict[str, Any]]:
    """Per detector: its threshold rule and the clean false-alarm rate the rule promises.

    "percentile" p: a share 1 − p/100 of clean steps; "max" (the largest of n held-out clean
    episodes' scores): an episode's maximum exceeds it with probability 1/(n + 1) when episodes
    are exchangeable; "episode_max": at most α of clean episodes (a conformal bound). The
    achieved rates are the null records' clean_alarm_rate and clean_episode_alarm.
    """
    from oodrl.protocol.streams import fit_calibration_split

    n = len(fit_calibration_split(params)[1])
    nominal = {}
    for name in params.benchmark.detectors:
        detector = params.detector(name)
        rule = detector.threshold_rule
        if rule == "percentile":
            rate, per = 1 - detector.threshold_percentile / 100, "step"
        elif rule == "max":
            rate, per = 1 / (n + 1), "episode"
        else:
            rate, per = detector.alpha, "episode"
        nominal[name] = {"rule": rule, "nominal_rate": round(rate, 6), "per": per,
                         "calibration_episodes": n}  # fmt: skip
    return nominal


def read_results_file(path: Path) -> Any:
    """results.yaml or sweep_results.yaml, as the metrics stage wrote it."""
    if not Path(path).is_file():
        raise StoreError(f"{path}: missing; {restore_hint(path, 'metrics')}.")
    return yamlio.load(Path(path).read_text())


def _summary(
    group: dict, clean: np.ndarray, threshold: float, spec: dict, params: Params, detector, latency
) -> tuple[Summary, dict[str, list[float]]]:
    """Mean, std and CI of every metric for one perturbed set against its matched clean set,
    and the per-episode values of EPISODE_METRICS."""
    from oodrl.metrics.aggregate import episode_metrics, summarise

    per_episode = episode_metrics(
        group["scores"], clean, group["labels"], threshold,
        spec["onset"], spec["offset"], params.metrics, detector, latency,
    )  # fmt: skip
    kept = {m: [round(float(v), 6) + 0.0 for v in per_episode[m]] for m in EPISODE_METRICS}
    return summarise(per_episode, params.metrics, seed=params.seed), kept


def _null_summary(params: Params, clean: np.ndarray, threshold: float, detector, latency):
    """The null baseline: clean scores judged against the counterfactual labels."""
    from oodrl.metrics.aggregate import null_episode_metrics, summarise

    T, onset, offset = params.env.T, params.env.resolved_onset, params.anomaly.offset
    labels = np.tile(make_labels(T, onset, offset), (clean.shape[0], 1))
    per_episode = null_episode_metrics(
        clean, labels, threshold, onset, offset, params.metrics, detector, latency
    )
    return summarise(per_episode, params.metrics, seed=params.seed)


def _detector_results(params: Params, scores_dir: Path, detector: str):
    """One detector's records, its sweep summaries, and the injectors' modes."""
    # The look-ahead follows from the detector's params alone (e.g. lyapunov's horizon).
    latency = params.detector(detector).latency
    eval_path = score_store(scores_dir, detector)
    clean_groups, clean_attrs = read_scores(
        eval_path, stage=detector_stage(detector, "score_clean")
    )
    clean = clean_groups[CLEAN_GROUP]["scores"]
    threshold = float(clean_attrs["threshold"])
    records, sweep, modes = [], {}, {}
    for injector in params.benchmark.injectors:
        path = score_store(scores_dir, detector, injector)
        groups, attrs = read_scores(path, stage=detector_stage(detector, "score"))
        sweep_path = sweep_score_store(scores_dir, detector, injector)
        sweep_groups, sweep_attrs = read_scores(
            sweep_path, stage=detector_stage(detector, "score_variants")
        )
        spec, modes[injector] = attrs["spec"], attrs["mode"]
        headline, episodes = _summary(
            groups[HEADLINE_GROUP], clean, threshold, spec, params, detector, latency
        )
        records.append(
            ResultRecord("anomaly", detector, injector, attrs["mode"], spec["severity"],
                         latency, headline, episodes)
        )  # fmt: skip
        for severity in sweep_attrs["severities"]:
            sweep[(injector, float(severity))], _ = _summary(
                sweep_groups[severity_key(severity)], clean, threshold,
                {**sweep_attrs["spec"], "severity": severity}, params, detector, latency,
            )  # fmt: skip
    null = _null_summary(params, clean, threshold, detector, latency)
    records.extend(
        ResultRecord("null", detector, None, mode, None, latency, null)
        for mode in sorted(set(modes.values()))
    )
    return records, sweep, modes


def compute_results(params: Params, scores_dir: Path) -> Results:
    """Every (detector, anomaly) headline record, the null baselines, and the sweep, of every
    benchmark detector's scores in `scores_dir` (the pipeline computes each detector's part in a
    stage of its own, `oodrl.metrics.cells`, and merges them with `assemble_results`).

    Detectors are summarised in parallel (executor.workers); each summary is seeded alone,
    so the results do not depend on the worker count. The clean evaluation set is the
    matched counterpart of both execution modes (online runs re-use its seeds), so each
    mode's null baseline is computed on the same clean scores.
    """
    detectors = params.benchmark.detectors
    with progress_bar(len(detectors), "metrics", params.executor.progress) as bar:
        jobs = [(params, scores_dir, detector) for detector in detectors]
        workers = params.executor.resolved_workers
        parts = ordered_map(_detector_results, jobs, workers, on_done=lambda _: bar.update())
    return assemble_results(params, list(zip(detectors, parts, strict=True)))


def assemble_results(params: Params, parts: list[tuple[str, tuple[list, dict, dict]]]) -> Results:
    """The results of every detector's part — (detector, (records, sweep, modes)) as
    `_detector_results` returns them, in benchmark.detectors order: the records sorted, the
    injectors' modes, the sweep by injector, severity (as the first detector lists it), then
    detector."""
    detectors = params.benchmark.detectors
    records: list[ResultRecord] = []
    sweep: dict[str, dict[float, dict[str, Summary]]] = {i: {} for i in params.benchmark.injectors}
    modes: dict[str, str] = {}
    for detector, (detector_records, detector_sweep, detector_modes) in parts:
        records.extend(detector_records)
        modes.update(detector_modes)
        for (injector, severity), summary in detector_sweep.items():
            sweep[injector].setdefault(severity, {})[detector] = summary
    records.sort(key=lambda r: (r.kind, r.detector, r.injector or "", r.mode))
    uncertified = sorted(d for d in detectors if not params.detector(d).machine_independent)
    return Results(records, modes, sweep, nominal_false_alarms(params), uncertified)
