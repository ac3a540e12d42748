"""Scoring a fitted detector on trajectory sets: what the score stores hold (SPEC §9).

Score stores hold, per group, `scores` (N, T) float64 and, for perturbed sets, the `labels`
(N, T) bool they are judged against; the root attributes hold the detector's threshold, the
detector and injector names, the mode and the AnomalySpec. Groups (paths in `oodrl.layout`):
`clean` in `<detector>/eval.zarr`; `headline` in `<detector>/<injector>.zarr`; one
`severity_<σ>` per sweep severity in `<detector>/sweep/<injector>.zarr`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from oodrl.core.trajectory import TrajectorySet
from oodrl.errors import DetectorError
from oodrl.layout import CLEAN_GROUP, HEADLINE_GROUP
from oodrl.store import severity_key

Groups = dict[str, dict[str, np.ndarray]]


def clean_scores(detector, name: str, clean: TrajectorySet) -> tuple[Groups, dict]:
    """The groups and attributes of a detector's clean-set score store."""
    scores = score_set(detector, name, clean, "the clean evaluation set")
    return {CLEAN_GROUP: {"scores": scores}}, _detector_attrs(detector, name)


def headline_scores(
    detector, name: str, injector: str, headline: TrajectorySet
) -> tuple[Groups, dict]:
    """The groups and attributes of a detector's score store of one injector's headline set."""
    groups = {HEADLINE_GROUP: _labelled(detector, name, headline, f"{injector} (headline)")}
    return groups, _injector_attrs(detector, name, injector, headline)


def sweep_scores(
    detector, name: str, injector: str, sweep: Mapping[float, TrajectorySet]
) -> tuple[Groups, dict]:
    """The groups and attributes of a detector's score store of one injector's sweep."""
    groups = {
        severity_key(s): _labelled(detector, name, tset, f"{injector} (σ = {s})")
        for s, tset in sweep.items()
    }
    attrs = _injector_attrs(detector, name, injector, sweep[min(sweep)])
    return groups, {**attrs, "severities": sorted(sweep)}


def tier_scores(
    detector, name: str, injector: str, sets: Mapping[float, TrajectorySet], attrs: Mapping
) -> tuple[Groups, dict]:
    """The groups and attributes of a detector's score store of one fault's tier streams (one
    group per reachable tier's severity; none when every tier is unreachable)."""
    groups = {
        severity_key(s): _labelled(detector, name, tset, f"{injector} (σ = {s})")
        for s, tset in sets.items()
    }
    spec = sets[min(sets)].attrs["spec"] if sets else None
    return groups, {
        **_detector_attrs(detector, name), "injector": injector, "mode": attrs["mode"],
        "spec": spec, "tiers": dict(attrs["tiers"]), "unreachable": list(attrs["unreachable"]),
    }  # fmt: skip


def score_set(detector, name: str, tset: TrajectorySet, condition: str) -> np.ndarray:
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


def _labelled(detector, name: str, tset: TrajectorySet, condition: str) -> dict:
    return {"scores": score_set(detector, name, tset, condition), "labels": tset.labels}


def _detector_attrs(detector, name: str) -> dict:
    # Onset, offset and severity come from the scored stores' specs, not from params, so a
    # score stage depends on no params key: only its detector and its data.
    return {"detector": name, "threshold": float(detector.threshold_)}


def _injector_attrs(detector, name: str, injector: str, tset: TrajectorySet) -> dict:
    attrs = tset.attrs
    return {**_detector_attrs(detector, name), "injector": injector, "mode": attrs["mode"],
            "spec": attrs["spec"]}  # fmt: skip
