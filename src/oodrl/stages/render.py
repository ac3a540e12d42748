"""The render stage: figures, DVC plot data, the README headline table, and run_meta.yaml."""

from __future__ import annotations

import hashlib
import json
import platform
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING, Any

from oodrl import yamlio
from oodrl.config import Params
from oodrl.fileio import atomic_write_text, library_versions
from oodrl.stages.common import TIMINGS_DIR
from oodrl.stages.metrics import score_store
from oodrl.stages.score import CLEAN_GROUP, HEADLINE_GROUP
from oodrl.store import read_scores, rerun_hint

if TYPE_CHECKING:
    from oodrl.report.plots import ScoreTraces


def _load_yaml(path: Path) -> Any:
    from oodrl.errors import StoreError

    if not Path(path).is_file():
        raise StoreError(f"{path}: missing; {rerun_hint('metrics')}.")
    return yamlio.load(Path(path).read_text())


def score_traces(params: Params, results: dict, scores_dir: Path) -> list[ScoreTraces]:
    """Per anomaly, the detector worth looking at — the best by matched AUROC — with its scores
    on every perturbed episode and every matched clean one."""
    from oodrl.report.plots import ScoreTraces

    best: dict[str, tuple[float, str]] = {}
    for record in results["records"]:
        if record["kind"] == "anomaly":
            auroc = record["metrics"]["matched_auroc"]["mean"]
            best[record["anomaly"]] = max(best.get(record["anomaly"], (-1.0, "")),
                                          (auroc, record["detector"]))  # fmt: skip
    traces = []
    for anomaly in params.benchmark.injectors:
        auroc, detector = best[anomaly]
        clean_groups, attrs = read_scores(score_store(scores_dir, detector, "eval"))
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


def _git_commit() -> str:
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True)
    except OSError:
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 else "unknown"


def _device() -> str:
    import os

    return f"cpu ({len(os.sched_getaffinity(0))} cores available)"


def run_meta(params: Params, policy_path: Path) -> dict[str, Any]:
    """Provenance of this run. Not a DVC output: it holds timings and host facts by design."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.protocol import eval_seeds, id_seeds

    timings = {}
    for path in sorted(TIMINGS_DIR.glob("*.json")):
        record = json.loads(path.read_text())
        timings[record["stage"]] = record["wall_s"]
    return {
        "oodrl_version": library_versions()["oodrl"],
        "git_commit": _git_commit(),
        "versions": library_versions(),
        "platform": platform.platform(),
        "device": _device(),
        "stage_wall_s": timings,
        "total_stage_wall_s": round(sum(timings.values()), 3),
        "params": params.model_dump(mode="json"),
        "seeds": {"id": id_seeds(params), "eval": eval_seeds(params)},
        "env": {"id": params.env.id, "version": ENVIRONMENTS.get(params.env.id).version()},
        "policy_sha256": hashlib.sha256(Path(policy_path).read_bytes()).hexdigest(),
    }


def run_render(
    params: Params,
    results_path: Path,
    sweep_path: Path,
    scores_dir: Path,
    policy_path: Path,
    figures_dir: Path,
    plots_dir: Path,
    headline_path: Path,
    meta_path: Path,
) -> None:
    from oodrl.report.plots import (
        plot_heatmap,
        plot_score_traces,
        plot_severity_curves,
        write_dvc_plot_data,
    )
    from oodrl.report.tables import headline_table

    results, sweep = _load_yaml(results_path), _load_yaml(sweep_path)
    figures_dir.mkdir(parents=True, exist_ok=True)
    plot_heatmap(results, figures_dir / "matched_auroc_heatmap.png")
    plot_severity_curves(sweep, figures_dir / "severity_curves.png", results)
    plot_score_traces(score_traces(params, results, scores_dir), figures_dir / "score_traces.png")
    write_dvc_plot_data(results, sweep, plots_dir)
    atomic_write_text(headline_path, headline_table(results))
    meta = run_meta(params, policy_path)
    atomic_write_text(meta_path, yamlio.dump(meta))
