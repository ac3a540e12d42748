"""Where a pipeline keeps its score stores and its detectors' stages: spelled once.

Paths are relative to the pipeline's directory (the root, or `pipeline/<env>/`), where every
stage command runs. Each detector's fit and scoring stages live in their own DVC file,
`detectors/<detector>/dvc.yaml` (see pipeline.yaml for why), so a stage's DVC address is
`detectors/<detector>/dvc.yaml:<stage>`; the environment's other stages are in `dvc.yaml`.
"""

from __future__ import annotations

from pathlib import Path

#: One DVC file per detector under here: its fit, clean scoring, and per-injector scoring.
DETECTOR_PIPELINES = "detectors"
#: Group names inside score stores.
CLEAN_GROUP = "clean"
HEADLINE_GROUP = "headline"


def detector_pipeline(detector: str) -> str:
    """The DVC file holding `detector`'s fit and scoring stages."""
    return f"{DETECTOR_PIPELINES}/{detector}/dvc.yaml"


def detector_stage(detector: str, stage: str) -> str:
    """The DVC address of one of a detector's stages: 'fit', 'score_clean' (the clean sets),
    'score' (the injectors' headline sets), 'score_variants' (their sweeps and tier streams) or
    'cells' (its results cells)."""
    return f"{detector_pipeline(detector)}:{stage}"


def score_store(scores_dir: Path, detector: str, injector: str | None = None) -> Path:
    """`detector`'s scores of the clean evaluation set (`injector` None) or of one injector's
    headline set."""
    return Path(scores_dir) / detector / f"{injector or 'eval'}.zarr"


def sweep_score_store(scores_dir: Path, detector: str, injector: str) -> Path:
    """`detector`'s scores of one injector's sweep sets (one group per severity)."""
    return Path(scores_dir) / detector / "sweep" / f"{injector}.zarr"


def tier_score_store(scores_dir: Path, detector: str, fault: str) -> Path:
    """`detector`'s scores of one fault's tier streams (one group per tier severity)."""
    return Path(scores_dir) / detector / "tiers" / f"{fault}.zarr"


def heldout_score_store(scores_dir: Path, detector: str, which: str) -> Path:
    """`detector`'s scores of a held-out clean set (`oodrl.protocol.streams.HELDOUT_SETS`: the
    per-stream alarm rule's calibration streams, the audit streams, the tier cells' twins)."""
    return Path(scores_dir) / detector / f"{which}.zarr"


def id_score_store(scores_dir: Path, detector: str) -> Path:
    """`detector`'s scores of the ID set (`data/id.zarr`: the streams it was fitted and
    calibrated on), whose per-step law the time-aware rule standardises by (SPEC §24)."""
    return Path(scores_dir) / detector / "id.zarr"


def calibration_score_store(scores_dir: Path, detector: str) -> Path:
    """`detector`'s scores of the clean calibration streams (the per-stream alarm rule's)."""
    return heldout_score_store(scores_dir, detector, "calibration")
