"""Scoring stages: one fitted detector on the clean evaluation set, on one injector's headline
set, on its sweep (separate stages, so a changed headline severity does not re-score the
sweep), on the clean calibration streams, or on a fault's tier streams. What the score stores
hold: `oodrl.scoring`."""

from __future__ import annotations

from pathlib import Path

from oodrl import scoring
from oodrl.layout import detector_stage
from oodrl.store import (
    load_detector,
    read_sweep,
    read_tier_sets,
    read_trajectories,
    write_scores,
)


def _fitted(detector_path: Path, name: str):
    return load_detector(detector_path, stage=detector_stage(name, "fit"))


def score_clean(name: str, detector_path: Path, eval_path: Path, out: Path):
    clean = read_trajectories(eval_path, stage="collect_eval")
    write_scores(out, *scoring.clean_scores(_fitted(detector_path, name), name, clean))


def score_headline(name: str, injector: str, detector_path: Path, ood_path: Path, out: Path):
    headline = read_trajectories(ood_path, stage=f"collect_ood@{injector}")
    detector = _fitted(detector_path, name)
    write_scores(out, *scoring.headline_scores(detector, name, injector, headline))


def score_sweep(name: str, injector: str, detector_path: Path, sweep_path: Path, out: Path):
    sweep = read_sweep(sweep_path, stage=f"collect_sweep@{injector}")
    detector = _fitted(detector_path, name)
    write_scores(out, *scoring.sweep_scores(detector, name, injector, sweep))


def score_calibration(name: str, detector_path: Path, calibration_path: Path, out: Path):
    calibration = read_trajectories(calibration_path, stage="collect_calibration")
    write_scores(out, *scoring.clean_scores(_fitted(detector_path, name), name, calibration))


def score_tiers(name: str, injector: str, detector_path: Path, tiers_path: Path, out: Path):
    sets, attrs = read_tier_sets(tiers_path, stage=f"collect_tiers@{injector}")
    detector = _fitted(detector_path, name)
    write_scores(out, *scoring.tier_scores(detector, name, injector, sets, attrs))
