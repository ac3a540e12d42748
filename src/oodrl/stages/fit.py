"""The fit stage: fit one detector on the ID fit part, calibrate it on the held-out part."""

from __future__ import annotations

import time
from pathlib import Path

from oodrl.config import Params
from oodrl.io.store import read_trajectories, save_detector


def fit_detector(params: Params, detector_name: str, id_path: Path, out: Path) -> float:
    """Fit, calibrate and save `detector_name`; returns the seconds that fit and calibrate took
    (the fit time run_meta.yaml reports beside accuracy, SPEC §13)."""
    id_set = read_trajectories(id_path, stage="collect_id")
    split = id_set.attrs["split"]
    detector = params.detector(detector_name)
    fit_set = id_set.subset(split["fit"]).trajectories()
    calibration_set = id_set.subset(split["calibration"]).trajectories()
    start = time.perf_counter()
    detector.fit(fit_set)
    detector.calibrate(calibration_set)
    seconds = time.perf_counter() - start
    save_detector(out, detector, detector_name, dict(params.detectors[detector_name]))
    return seconds
