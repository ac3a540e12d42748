"""Scoring stages: one fitted detector on the clean sets (stage score_clean: the ID set its
time-aware rule standardises by, the evaluation set and the held-out calibration, audit and twin
streams), on every injector's headline set (stage score) or on every injector's sweep and tier
streams (stage score_variants). A stage per kind of set rather than one per injector or set: a
stage process and DVC's bookkeeping cost more than scoring a set (SPEC §12), and a changed
headline severity re-scores the headline sets alone (SPEC §23). Each set is scored by a freshly
loaded detector, as when every set had a process of its own; an injector's sets in one stage share
the scores of their equal pre-onset steps (`oodrl.protocol.scoring.SharedPrefixes`), which are the
same bits as scoring them again. What the
score stores hold: `oodrl.protocol.scoring`; where: `oodrl.io.layout`."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from oodrl.io.layout import (
    detector_stage,
    heldout_score_store,
    id_score_store,
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
    heldout: Mapping[str, Path | None], id_path: Path | None = None,
) -> None:  # fmt: skip
    """Stage score_clean: the sets given of the ID set (`id_path`, `data/id.zarr`, every stream
    of it: the time-aware rule's fit streams, SPEC §24), the clean evaluation set and the
    held-out clean sets (`heldout`: set name -> store, `oodrl.protocol.streams.HELDOUT_SETS`),
    each into its store's clean group. Every input is read, and the model loaded, before any
    store is written: a damaged one is named with no scores left behind (SPEC §22)."""
    sets = [
        (read_trajectories(path, stage=stage), out)
        for path, stage, out in [
            (id_path, "collect_id", id_score_store(scores_dir, name)),
            (eval_path, "collect_eval", score_store(scores_dir, name)),
            *(
                (path, f"collect_{which}", heldout_score_store(scores_dir, name, which))
                for which, path in heldout.items()
            ),
        ]
        if path is not None
    ]
    _fitted(detector_path, name)
    for clean, out in sets:
        write_scores(out, *scoring.clean_scores(_fitted(detector_path, name), name, clean))


def score_injector_sets(
    name: str, injector: str, detector_path: Path, scores_dir: Path, ood_dir: Path | None,
    sweep_dir: Path | None, tiers_dir: Path | None,
) -> None:  # fmt: skip
    """The sets given of one injector: its headline set (`ood_dir/<injector>.zarr`, stage
    score), its sweep and its tier streams (`sweep_dir`, `tiers_dir`: stage score_variants)."""
    shared = scoring.SharedPrefixes()
    for directory, stage, read, score, out in [
        (ood_dir, "collect_ood", read_trajectories, scoring.headline_scores,
         score_store(scores_dir, name, injector)),
        (sweep_dir, "collect_sweep", read_sweep, scoring.sweep_scores,
         sweep_score_store(scores_dir, name, injector)),
        (tiers_dir, "collect_tiers", read_tier_sets, scoring.tier_scores,
         tier_score_store(scores_dir, name, injector)),
    ]:  # fmt: skip
        if directory is not None:
            sets = read(Path(directory) / f"{injector}.zarr", stage=f"{stage}@{injector}")
            detector = _fitted(detector_path, name)
            write_scores(out, *score(detector, name, injector, sets, shared))


def _fitted(detector_path: Path, name: str):
    return load_detector(detector_path, stage=detector_stage(name, "fit"))
