"""Scoring stages: one fitted detector on the clean evaluation set, or on one injector's sets.

Score stores hold, per group, `scores` (N, T) float64 and, for perturbed sets, the `labels`
(N, T) bool they are judged against; the root attributes hold the detector's threshold,
the detector and injector names, the mode and the headline AnomalySpec. Groups: `clean` in
`<detector>/eval.zarr`; `headline` and one `severity_<σ>` per sweep severity in
`<detector>/<injector>.zarr`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oodrl.core.trajectory import TrajectorySet
from oodrl.errors import DetectorError
from oodrl.registry import _project_dir_on_path
from oodrl.stages.common import load_detector
from oodrl.store import read_sweep, read_trajectories, severity_key, write_scores

HEADLINE_GROUP = "headline"
CLEAN_GROUP = "clean"


def _scores(detector, name: str, tset: TrajectorySet, condition: str) -> np.ndarray:
    """Scores (N, T); a failure names the detector, the condition and the episode."""
    trajectories = tset.trajectories()
    try:
        outputs = detector.score_many(trajectories)
    except Exception:
        # Batched scoring hides which episode broke: find it one episode at a time.
        outputs = [
            _score_episode(detector, name, t, condition, i) for i, t in enumerate(trajectories)
        ]
    return np.stack([o.scores for o in outputs])


def _score_episode(detector, name: str, trajectory, condition: str, episode: int):
    try:
        return detector.score(trajectory)
    except Exception as error:
        raise DetectorError(
            f"Detector '{name}' failed scoring episode {episode} (seed "
            f"{trajectory.info.get('seed')}) of {condition}: {type(error).__name__}: {error}"
        ) from error


def _fitted(detector_path: Path, detector_name: str):
    """The fitted detector; a plugin's pickle refers to its module beside params.yaml, which
    the `oodrl` command finds only with the project directory on sys.path (as the registry
    adds it when params name the plugin)."""
    _project_dir_on_path()
    return load_detector(detector_path, stage=f"fit@{detector_name}")


def _root_attrs(detector, name: str) -> dict:
    # Onset, offset and severity come from the scored stores' specs, not from params, so a
    # score stage depends on no params key: only its detector and its data.
    return {"detector": name, "threshold": float(detector.threshold_)}


def score_clean(detector_name: str, detector_path: Path, eval_path: Path, out: Path):
    detector = _fitted(detector_path, detector_name)
    clean = read_trajectories(eval_path, stage="collect_eval")
    scores = _scores(detector, detector_name, clean, "the clean evaluation set")
    write_scores(out, {CLEAN_GROUP: {"scores": scores}}, _root_attrs(detector, detector_name))


def score_injector(
    detector_name: str,
    injector_name: str,
    detector_path: Path,
    ood_path: Path,
    sweep_path: Path,
    out: Path,
):
    detector = _fitted(detector_path, detector_name)
    headline = read_trajectories(ood_path, stage=f"collect_ood@{injector_name}")
    sweep = read_sweep(sweep_path, stage=f"collect_sweep@{injector_name}")
    groups = {}
    for group, tset in [(HEADLINE_GROUP, headline)] + [
        (severity_key(s), t) for s, t in sweep.items()
    ]:
        condition = f"{injector_name} ({group})"
        groups[group] = {
            "scores": _scores(detector, detector_name, tset, condition),
            "labels": tset.labels,
        }
    attrs = {
        **_root_attrs(detector, detector_name),
        "injector": injector_name,
        "mode": headline.attrs["mode"],
        "spec": headline.attrs["spec"],
        "severities": sorted(sweep),
    }
    write_scores(out, groups, attrs)
