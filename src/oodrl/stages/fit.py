"""The fit stage: fit one detector on the ID fit part, calibrate it on the held-out part."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params
from oodrl.stages.common import save_detector
from oodrl.store import read_trajectories


def fit_detector(params: Params, detector_name: str, id_path: Path, out: Path):
    id_set = read_trajectories(id_path, stage="collect_id")
    split = id_set.attrs["split"]
    detector = params.detector(detector_name)
    detector.fit(id_set.subset(split["fit"]).trajectories())
    detector.calibrate(id_set.subset(split["calibration"]).trajectories())
    save_detector(out, detector, detector_name, dict(params.detectors[detector_name]))
    return detector
