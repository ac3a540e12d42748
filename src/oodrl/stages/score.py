"""Scoring stages: one fitted detector on the clean sets (stage score_clean: the evaluation set and
the held-out calibration, audit and twin streams) or on one injector's sets (stage
score@<injector>: its headline set, its sweep and its tier streams). One stage per detector and
injector rather than one per set: a stage process and DVC's bookkeeping cost more than scoring a
set (SPEC §12). Each set is scored by a freshly loaded detector, as when every set had a process
of its own; an injector's sets share the scores of their equal pre-onset steps
(`oodrl.protocol.scoring.SharedPrefixes`), which are the same bits as scoring them again. What the
score stores hold: `oodrl.protocol.scoring`; where: `oodrl.io.layout`."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from oodrl.io.layout import (
    detector_stage,
    heldout_score_store,
    score_store,
    sweep_score_store,
    tier_score_store,
)
from oodrl.io.store import (
    load_detector,
    read_sweep,
    read_tier_sets,
    read_trajectories,
    write_scores,
)
from oodrl.protocol import scoring


def score_clean_sets(
    name: str, detector_path: Path, scores_dir: Path, eval_path: Path | None,
    heldout: Mapping[str, Path | None],
) -> None:  # fmt: skip
    """Stage score_clean: the sets given of the clean evaluation set and the held-out clean
    sets (`heldout`: set name -> store, `oodrl.protocol.streams.HELDOUT_SETS`)."""
    for path, stage, out in [
        (eval_path, "collect_eval", score_store(scores_dir, name)),
        *(
            (path, f"collect_{which}", heldout_score_store(scores_dir, name, which))
            for which, path in heldout.items()
        ),
    ]:
        if path is not None:
            clean = read_trajectories(path, stage=stage)
            write_scores(out, *scoring.clean_scores(_fitted(detector_path, name), name, clean))


def score_injector_sets(
    name: str, injector: str, detector_path: Path, scores_dir: Path, ood_path: Path | None,
    sweep_path: Path | None, tiers_path: Path | None,
) -> None:  # fmt: skip
    """Stage score@<injector>: the sets given of the injector's headline set, sweep and tiers."""
    shared = scoring.SharedPrefixes()
    for path, stage, read, score, out in [
        (ood_path, "collect_ood", read_trajectories, scoring.headline_scores,
         score_store(scores_dir, name, injector)),
        (sweep_path, "collect_sweep", read_sweep, scoring.sweep_scores,
         sweep_score_store(scores_dir, name, injector)),
        (tiers_path, "collect_tiers", read_tier_sets, scoring.tier_scores,
         tier_score_store(scores_dir, name, injector)),
    ]:  # fmt: skip
        if path is not None:
            sets = read(path, stage=f"{stage}@{injector}")
            detector = _fitted(detector_path, name)
            write_scores(out, *score(detector, name, injector, sets, shared))


def _fitted(detector_path: Path, name: str):
    return load_detector(detector_path, stage=detector_stage(name, "fit"))
