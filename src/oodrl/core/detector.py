"""DetectorOutput and the BaseDetector contract (SPEC §1, §5).

Score direction: a larger score means more anomalous, for every detector.
Subclasses implement `_fit` and one of `_score` (one trajectory) or `_score_many` (a batch);
the base class owns `fit`, `calibrate`, `score`, the threshold rules and the alarms,
so no detector can forget its threshold or mutate itself while scoring.

Parameters are keyword-only dataclass fields (`@detector_parameters`): the generated `__init__`
stores each keyword argument under its own name and does nothing else, which is scikit-learn's
contract, so `get_params` (it reads the signature), `from_params` and validation work unchanged.
A plugin may instead write an `__init__(self, *, my_param=..., **base)` that calls
`super().__init__(**base)` and stores its arguments.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from oodrl.core.trajectory import Trajectory
from oodrl.errors import ContractError, DetectorError, NotFittedError
from oodrl.validation import Component, Interval, Options

THRESHOLD_RULES = ("percentile", "max")

#: Declares a detector class's parameters as keyword-only fields. Equality stays identity (as
#: for any estimator: two equal-parameter detectors fitted on different data are not equal) and
#: the repr stays Component's, which lists `get_params()`.
detector_parameters = dataclass(kw_only=True, eq=False, repr=False)


@dataclass(frozen=True, eq=False)
class DetectorOutput:
    """Scores (T,) float64, larger = more anomalous; alarms = scores >= threshold if calibrated."""

    scores: np.ndarray
    alarms: np.ndarray | None = None
    threshold: float | None = None

    def __post_init__(self) -> None:
        scores = np.asarray(self.scores, dtype=np.float64)
        if scores.ndim != 1:
            raise ContractError(f"DetectorOutput.scores must be 1-D; got shape {scores.shape}.")
        if not np.isfinite(scores).all():
            raise ContractError("DetectorOutput.scores contains NaN or inf.")
        object.__setattr__(self, "scores", scores)
        if self.alarms is not None:
            alarms = np.asarray(self.alarms)
            if alarms.shape != scores.shape or alarms.dtype != bool:
                raise ContractError(
                    f"DetectorOutput.alarms must be bool with shape {scores.shape}; "
                    f"got {alarms.dtype} {alarms.shape}."
                )


def threshold_from_scores(scores: np.ndarray, rule: str, percentile: float) -> float:
    """The alarm threshold from held-out clean scores: a percentile, or the maximum."""
    if rule == "max":
        return float(np.max(scores))
    return float(np.percentile(scores, percentile))


@detector_parameters
class BaseDetector(Component):
    """Fit once on in-distribution trajectories, calibrate on held-out ones, then score.

    Learned state ends in `_` (`state_dim_`, `threshold_`): `state_dim_` set means fitted.
    `name` is the detector's one name (its registry name; a class that declares none is named
    after itself): errors say it, and the pipeline's params key is the stage's to say.
    """

    name: ClassVar[str] = ""
    #: Whether fitting the detector needs torch (its fit stage then pays the import).
    uses_torch: ClassVar[bool] = False

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "threshold_rule": [Options(THRESHOLD_RULES)],
        "threshold_percentile": [Interval(float, 0, 100, closed="both")],
        "seed": [Interval(int, 0, None)],
    }

    threshold_rule: str = "percentile"
    threshold_percentile: float = 99.0
    seed: int = 0

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:
            cls.name = cls.__name__

    # -- what subclasses write -------------------------------------------------------------
    @abstractmethod
    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        """Learn from in-distribution trajectories; store learned state in attributes ending `_`."""

    def _score(self, trajectory: Trajectory) -> np.ndarray:
        """Scores (T,) for one trajectory. Must not change `self`."""
        return self._score_many([trajectory])[0]

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        """Scores for many trajectories; override to batch (e.g. one network pass)."""
        return [self._score(t) for t in trajectories]

    # -- the public contract ---------------------------------------------------------------
    @property
    def latency(self) -> int:
        """How many steps of the future the score at t uses: z_t is known at step t + latency.

        0 when z_t uses only s_≤t and a_t (the action is chosen at t); 1 when it uses s_{t+1}
        (`next_states[t]`: transition features or residuals); H for an H-step look-ahead.
        Subclasses override it from their params. A detection delay counts an alarm at t as
        raised at t + latency, so that look-ahead cannot make a detector look early (SPEC §6).
        """
        return 0

    def fit(self, trajectories: Sequence[Trajectory]) -> BaseDetector:
        cls = type(self)
        if cls._score is BaseDetector._score and cls._score_many is BaseDetector._score_many:
            # Each default calls the other: a detector must override at least one.
            raise TypeError(f"{cls.__name__} must implement _score or _score_many.")
        self.validate_params()
        trajectories = list(trajectories)
        if not trajectories:
            raise ContractError(f"{self.name}.fit needs at least one trajectory.")
        dims = {t.state_dim for t in trajectories}
        if len(dims) != 1:
            raise ContractError(f"{self.name}.fit got mixed state dimensions {dims}.")
        self.state_dim_ = dims.pop()
        self._fit(trajectories)
        return self

    def calibrate(self, trajectories: Sequence[Trajectory]) -> BaseDetector:
        """Set `threshold_` from held-out clean trajectories by the declared rule."""
        scores = np.concatenate([o.scores for o in self._checked_scores(list(trajectories))])
        self.threshold_ = threshold_from_scores(
            scores, self.threshold_rule, self.threshold_percentile
        )
        return self

    def score(self, trajectory: Trajectory) -> DetectorOutput:
        return self.score_many([trajectory])[0]

    def score_many(self, trajectories: Sequence[Trajectory]) -> list[DetectorOutput]:
        outputs = self._checked_scores(list(trajectories))
        threshold = getattr(self, "threshold_", None)
        if threshold is None:
            return outputs
        return [DetectorOutput(o.scores, o.scores >= threshold, threshold) for o in outputs]

    def _checked_scores(self, trajectories: list[Trajectory]) -> list[DetectorOutput]:
        if not hasattr(self, "state_dim_"):
            raise NotFittedError(f"{self.name} is not fitted: call fit() before scoring.")
        if not trajectories:
            return []
        for t in trajectories:
            if t.state_dim != self.state_dim_:
                raise ContractError(
                    f"{self.name} was fitted on state dimension {self.state_dim_}; "
                    f"got a trajectory with state dimension {t.state_dim}."
                )
        outputs = []
        for index, (t, raw) in enumerate(
            zip(trajectories, self._score_many(trajectories), strict=True)
        ):
            scores = np.asarray(raw, dtype=np.float64)
            if scores.shape != (t.T,) or not np.isfinite(scores).all():
                raise DetectorError(
                    f"Detector '{self.name}' returned invalid scores for trajectory "
                    f"{index} (shape {scores.shape}, expected ({t.T},), finite)."
                )
            outputs.append(DetectorOutput(scores))
        return outputs
