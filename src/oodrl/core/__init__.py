"""The data contracts every oodrl component speaks (SPEC §1)."""

from oodrl.core.detector import BaseDetector, DetectorOutput, threshold_from_scores
from oodrl.core.injector import (
    BaseAnomalyInjector,
    Fault,
    OnlineInjector,
    PostHocInjector,
    SimulatorHandle,
)
from oodrl.core.spec import MODES, AnomalySpec, default_onset, make_labels
from oodrl.core.trajectory import Trajectory, TrajectorySet

__all__ = [
    "MODES",
    "AnomalySpec",
    "BaseAnomalyInjector",
    "BaseDetector",
    "DetectorOutput",
    "Fault",
    "OnlineInjector",
    "PostHocInjector",
    "SimulatorHandle",
    "Trajectory",
    "TrajectorySet",
    "default_onset",
    "make_labels",
    "threshold_from_scores",
]
