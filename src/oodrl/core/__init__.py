"""The data contracts every oodrl component speaks (SPEC §1)."""

from oodrl.core.adapter import ActionKind, EnvironmentAdapter, SimulatorHandle
from oodrl.core.detector import BaseDetector, DetectorOutput, threshold_from_scores
from oodrl.core.injector import (
    BaseAnomalyInjector,
    Fault,
    OnlineInjector,
    PostHocInjector,
)
from oodrl.core.policy import Policy
from oodrl.core.spec import MODES, AnomalySpec, default_onset, make_labels
from oodrl.core.trajectory import Trajectory, TrajectorySet

__all__ = [
    "MODES",
    "ActionKind",
    "AnomalySpec",
    "BaseAnomalyInjector",
    "BaseDetector",
    "DetectorOutput",
    "EnvironmentAdapter",
    "Fault",
    "OnlineInjector",
    "Policy",
    "PostHocInjector",
    "SimulatorHandle",
    "Trajectory",
    "TrajectorySet",
    "default_onset",
    "make_labels",
    "threshold_from_scores",
]
