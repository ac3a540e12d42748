"""Scoring a fitted detector on trajectory sets: what the score stores hold (SPEC §9).

Score stores hold, per group, `scores` (N, T) float64 and, for perturbed sets, the `labels`
(N, T) bool they are judged against; the root attributes hold the detector's threshold, the
detector and injector names, the mode and the AnomalySpec. Groups (paths in `oodrl.io.layout`):
`clean` in `<detector>/eval.zarr`; `headline` in `<detector>/<injector>.zarr`; one
`severity_<σ>` per sweep severity in `<detector>/sweep/<injector>.zarr`.

The sets one stage scores (an injector's headline set, sweep and tiers) are the same seeded
episodes under different faults and severities: each stream equals its twins bit for bit until
its fault's onset. A `row_independent` detector's score at t reads step t alone, by arithmetic
that gives the same bits alone as in a batch (`oodrl.core.detector`; the streaming contract tests
it), so `SharedPrefixes` scores a stream only from the first step where it differs from the
first stream of its seed scored before it, and copies the earlier scores. Whether steps are
equal is compared, byte for byte, never assumed from the onset; other detectors (recursive
state, windows, whole-stream statistics) score every stream in full.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from oodrl.core.trajectory import Trajectory, TrajectorySet
from oodrl.errors import DetectorError
from oodrl.io.layout import CLEAN_GROUP, HEADLINE_GROUP
from oodrl.io.store import severity_key

Groups = dict[str, dict[str, np.ndarray]]


def clean_scores(detector, name: str, clean: TrajectorySet) -> tuple[Groups, dict]:
    """The groups and attributes of a detector's clean-set score store."""
    scores = score_set(detector, name, clean, "the clean evaluation set")
    return {CLEAN_GROUP: {"scores": scores}}, _detector_attrs(detector, name)


def headline_scores(
    detector, name: str, injector: str, headline: TrajectorySet,
    shared: SharedPrefixes | None = None,
) -> tuple[Groups, dict]:  # fmt: skip
    """The groups and attributes of a detector's score store of one injector's headline set."""
    condition = f"{injector} (headline)"
    groups = {HEADLINE_GROUP: _labelled(detector, name, headline, condition, shared)}
    return groups, _injector_attrs(detector, name, injector, headline)


def sweep_scores(
    detector, name: str, injector: str, sweep: Mapping[float, TrajectorySet],
    shared: SharedPrefixes | None = None,
) -> tuple[Groups, dict]:  # fmt: skip
    """The groups and attributes of a detector's score store of one injector's sweep."""
    groups = {
        severity_key(s): _labelled(detector, name, tset, f"{injector} (σ = {s})", shared)
        for s, tset in sweep.items()
    }
    attrs = _injector_attrs(detector, name, injector, sweep[min(sweep)])
    return groups, {**attrs, "severities": sorted(sweep)}


def tier_scores(
    detector, name: str, injector: str,
    tiers: tuple[Mapping[float, TrajectorySet], Mapping], shared: SharedPrefixes | None = None,
) -> tuple[Groups, dict]:  # fmt: skip
    """The groups and attributes of a detector's score store of one fault's tier streams (one
    group per reachable tier's severity; none when every tier is unreachable). `tiers`: the
    tier sets by severity and the tier store's attributes, as `oodrl.io.store.read_tier_sets`
    reads them."""
    sets, attrs = tiers
    groups = {
        severity_key(s): _labelled(detector, name, tset, f"{injector} (σ = {s})", shared)
        for s, tset in sets.items()
    }
    spec = sets[min(sets)].attrs["spec"] if sets else None
    return groups, {
        **_detector_attrs(detector, name), "injector": injector, "mode": attrs["mode"],
        "spec": spec, "tiers": dict(attrs["tiers"]), "unreachable": list(attrs["unreachable"]),
    }  # fmt: skip


def score_set(
    detector, name: str, tset: TrajectorySet, condition: str,
    shared: SharedPrefixes | None = None,
) -> np.ndarray:  # fmt: skip
    """Scores (N, T); a failure names the detector, the condition and the episode. With
    `shared`, a stream's steps equal to an earlier stream of its seed are not scored again."""
    trajectories = tset.trajectories()
    if shared is None or not detector.row_independent:
        return np.stack(_scored(detector, name, list(enumerate(trajectories)), condition))
    starts = [shared.first_new_step(t) for t in trajectories]
    todo = [
        (episode, suffix)
        for episode, (t, start) in enumerate(zip(trajectories, starts, strict=True))
        if (suffix := _steps_from(t, start)) is not None
    ]
    tails = dict(zip([e for e, _ in todo], _scored(detector, name, todo, condition), strict=True))
    rows = []
    for episode, (trajectory, start) in enumerate(zip(trajectories, starts, strict=True)):
        rows.append(shared.joined(trajectory, start, tails.get(episode, np.zeros(0))))
    return np.stack(rows)


class SharedPrefixes:
    """Per seed, the first stream scored in a stage and its scores (see the module docstring)."""

    def __init__(self) -> None:
        self.first: dict[int, tuple[Trajectory, np.ndarray]] = {}

    def first_new_step(self, trajectory: Trajectory) -> int:
        """The first step of `trajectory` that differs from the first stream of its seed (0
        when none was scored; T when it differs nowhere)."""
        known = self.first.get(trajectory.info.get("seed"))
        return 0 if known is None else first_difference(known[0], trajectory)

    def joined(self, trajectory: Trajectory, start: int, tail: np.ndarray) -> np.ndarray:
        """The scores of `trajectory`: its seed's first scores before `start`, then `tail`."""
        seed = trajectory.info.get("seed")
        if start == 0:
            self.first.setdefault(seed, (trajectory, tail))
            return tail
        return np.concatenate([self.first[seed][1][:start], tail])


def first_difference(a: Trajectory, b: Trajectory) -> int:
    """The first step at which the two streams' per-step arrays differ in any byte, or the
    shorter length when one is a prefix of the other (0 when their fields differ in kind)."""
    fields_a, fields_b = _step_arrays(a), _step_arrays(b)
    n = min(a.T, b.T)
    if fields_a.keys() != fields_b.keys():
        return 0
    differs = np.zeros(n, dtype=bool)
    for key, x in fields_a.items():
        y = fields_b[key]
        if x.dtype != y.dtype or x.shape[1:] != y.shape[1:]:
            return 0
        differs |= (_bytes(x[:n]) != _bytes(y[:n])).any(axis=1)
    return int(np.argmax(differs)) if differs.any() else n


def _step_arrays(trajectory: Trajectory) -> dict[str, np.ndarray]:
    arrays = {
        "states": trajectory.states, "actions": trajectory.actions,
        "rewards": trajectory.rewards, "next_states": trajectory.next_states,
        "dones": trajectory.dones,
    }  # fmt: skip
    per_step = {
        f"info.{key}": value
        for key, value in trajectory.info.items()
        if isinstance(value, np.ndarray) and value.ndim >= 1
    }
    return {**arrays, **per_step}


def _bytes(array: np.ndarray) -> np.ndarray:
    """(n, bytes per step) view of an array of n steps: equal rows are equal bits."""
    return np.ascontiguousarray(array).reshape(len(array), -1).view(np.uint8)


def _steps_from(trajectory: Trajectory, start: int) -> Trajectory | None:
    """The steps start.. of a stream (None when there are none), per-step info sliced too."""
    if start >= trajectory.T:
        return None
    if start == 0:
        return trajectory
    info = {
        key: value[start:] if isinstance(value, np.ndarray) and value.ndim >= 1 else value
        for key, value in trajectory.info.items()
    }
    return Trajectory(
        trajectory.states[start:], trajectory.actions[start:], trajectory.rewards[start:],
        trajectory.next_states[start:], trajectory.dones[start:], info,
    )  # fmt: skip


def _scored(
    detector, name: str, episodes: list[tuple[int, Trajectory]], condition: str
) -> list[np.ndarray]:
    """The scores (T,) of each (episode index, trajectory), from one batched call."""
    try:
        outputs = detector.score_many([t for _, t in episodes])
    except Exception:
        # Batched scoring hides which episode broke: find it one episode at a time.
        outputs = [_score_episode(detector, name, t, condition, i) for i, t in episodes]
    return [o.scores for o in outputs]


def _score_episode(detector, name: str, trajectory, condition: str, episode: int):
    try:
        return detector.score(trajectory)
    except Exception as error:
        raise DetectorError(
            f"Detector '{name}' failed scoring episode {episode} (seed "
            f"{trajectory.info.get('seed')}) of {condition}: {type(error).__name__}: {error}"
        ) from error


def _labelled(
    detector, name: str, tset: TrajectorySet, condition: str, shared: SharedPrefixes | None
) -> dict:
    return {"scores": score_set(detector, name, tset, condition, shared), "labels": tset.labels}


def _detector_attrs(detector, name: str) -> dict:
    # Onset, offset and severity come from the scored stores' specs, not from params, so a
    # score stage depends on no params key: only its detector and its data.
    return {"detector": name, "threshold": float(detector.threshold_)}


def _injector_attrs(detector, name: str, injector: str, tset: TrajectorySet) -> dict:
    attrs = tset.attrs
    return {**_detector_attrs(detector, name), "injector": injector, "mode": attrs["mode"],
            "spec": attrs["spec"]}  # fmt: skip
