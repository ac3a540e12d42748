"""DetectorOutput and the BaseDetector contract (SPEC §1, §5).

Score direction: a larger score means more anomalous, for every detector.
Subclasses implement `_fit` and one of `_score` (one trajectory) or `_score_many` (a batch);
the base class owns `fit`, `calibrate`, `score`, the threshold rules and the alarms,
so no detector can forget its threshold or mutate itself while scoring. `stream()` scores one
step at a time (`oodrl.core.stream`); a detector overrides it for constant work per step.

Threshold rules (`threshold_rule`), from the scores of held-out clean trajectories:

- ``"percentile"``: the `threshold_percentile`-th percentile of all their step scores, a
  per-step false-alarm rate of about 1 − percentile/100, with no guarantee per trajectory;
- ``"max"``: the largest of their step scores;
- ``"episode_max"``: the conformal quantile of their n per-trajectory maxima, the
  ⌈(n + 1)(1 − α)⌉-th smallest (`alpha`), so that a new clean trajectory of the same length,
  exchangeable with them, raises any false alarm with probability at most α. The threshold is
  the next float above that maximum: alarms are `score >= threshold`, and a tie with it must not
  alarm. It needs n ≥ 1/α − 1 trajectories (else no finite threshold bounds the rate).
- ``"ville"``: log(1/α), whatever the held-out scores, for a detector whose score is the log
  of a test martingale (`scores_are_log_martingales`, e.g. `conformal_martingale`): by Ville's
  inequality a stream on which the martingale's assumptions hold reaches 1/α with probability
  at most α. Other detectors refuse it. The log is `numerics.log` (32 significant bits, the
  same on every machine), so the alarm level is 1/α to a relative 2⁻³².

Parameters are keyword-only dataclass fields (`@detector_parameters`): the generated `__init__`
stores each keyword argument under its own name and does nothing else, which is scikit-learn's
contract, so `get_params` (it reads the signature), `from_params` and validation work unchanged.
A plugin may instead write an `__init__(self, *, my_param=..., **base)` that calls
`super().__init__(**base)` and stores its arguments.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, ClassVar

import numpy as np

from oodrl.core.stream import DetectorStream, ReplayStream, RowStream
from oodrl.core.trajectory import Trajectory
from oodrl.errors import ConfigError, ContractError, DetectorError, NotFittedError
from oodrl.numerics import log as machine_independent_log
from oodrl.validation import Component, Interval, Options

THRESHOLD_RULES = ("percentile", "max", "episode_max", "ville")

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


def threshold_from_scores(
    scores: Sequence[np.ndarray], rule: str, percentile: float, alpha: float
) -> float:
    """The alarm threshold from held-out clean scores, one array per trajectory, by a rule of
    THRESHOLD_RULES (see the module docstring)."""
    if rule == "episode_max":
        return episode_max_threshold(np.array([np.max(s) for s in scores]), alpha)
    if rule == "ville":
        return ville_threshold(alpha)
    steps = np.concatenate(scores)
    if rule == "max":
        return float(np.max(steps))
    return float(np.percentile(steps, percentile))


def episode_max_threshold(maxima: np.ndarray, alpha: float) -> float:
    """Just above the ⌈(n + 1)(1 − α)⌉-th smallest of n per-trajectory maxima.

    Split conformal prediction: for a new maximum exchangeable with the n, P(new > that order
    statistic) ≤ α, the finite-sample correction being the n + 1 in place of n.
    """
    n = len(maxima)
    # Fractions: (n + 1)(1 − α) in floats can land a hair above an integer and skip a rank.
    rank = math.ceil(Fraction(n + 1) * (1 - Fraction(str(alpha))))
    if rank > n:
        raise ConfigError(
            f"threshold_rule='episode_max' with alpha={alpha} needs at least "
            f"{math.ceil(1 / alpha) - 1} held-out trajectories; got {n}. "
            "Calibrate on more trajectories or raise 'alpha'."
        )
    return float(np.nextafter(np.sort(maxima)[rank - 1], np.inf))


def ville_threshold(alpha: float) -> float:
    """log(1/α) = −log α: where a test martingale started at 1 alarms (Ville's inequality,
    P(sup_t M_t ≥ 1/α) ≤ α), in the log scale its detector scores."""
    return float(-machine_independent_log(alpha))


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
    #: Whether z_t is a function of step t alone (s_t, a_t, s_{t+1}), computed by
    #: row-independent arithmetic: `stream()` then scores each step on its own.
    row_independent: ClassVar[bool] = False
    #: Whether its outputs are certified byte-identical on every x86-64 machine (SPEC §14): its
    #: arithmetic is oodrl's own (`oodrl.numerics`). A class that does not say is certified when
    #: it is defined in the oodrl package and its base class is, not when it is a plugin's; one
    #: that runs a library's own kernels says False (`oodrl.detectors.library`).
    machine_independent: ClassVar[bool]
    #: Whether the scores depend on the fit set. False only for a baseline that ignores it by
    #: design (`random_scores`): the contract then does not ask that refitting moves them.
    learns_from_data: ClassVar[bool] = True
    #: Whether z_t is the log of a test martingale, which the "ville" threshold rule needs.
    scores_are_log_martingales: ClassVar[bool] = False

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "threshold_rule": [Options(THRESHOLD_RULES)],
        "threshold_percentile": [Interval(float, 0, 100, closed="both")],
        "alpha": [Interval(float, 0, 1, closed="neither")],
        "seed": [Interval(int, 0, None)],
    }

    threshold_rule: str = "percentile"
    threshold_percentile: float = 99.0
    #: The bound on the clean-trajectory false-alarm probability of "episode_max".
    alpha: float = 0.05
    seed: int = 0

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:
            cls.name = cls.__name__
        if "machine_independent" not in cls.__dict__:
            inherited = getattr(cls, "machine_independent", True)
            cls.machine_independent = inherited and cls.__module__.split(".")[0] == "oodrl"

    def validate_params(self) -> None:
        super().validate_params()
        if self.threshold_rule == "ville" and not self.scores_are_log_martingales:
            raise ConfigError(
                f"threshold_rule='ville' needs scores that are the log of a test martingale; "
                f"{self.name}'s are not. Use 'percentile', 'max' or 'episode_max'."
            )

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
        scores = [o.scores for o in self._checked_scores(list(trajectories))]
        self.threshold_ = threshold_from_scores(
            scores, self.threshold_rule, self.threshold_percentile, self.alpha
        )
        return self

    def stream(self) -> DetectorStream:
        """A streaming scorer: one step in, the scores that became known out (SPEC §13).

        A `row_independent` detector scores each step on its own; otherwise this default
        re-scores the stream so far at every step (exact when z_t reads no step after
        t + latency, but not constant work), and a detector overrides it (`oodrl.core.stream`).
        """
        return RowStream(self) if self.row_independent else ReplayStream(self)

    def score(self, trajectory: Trajectory) -> DetectorOutput:
        return self.score_many([trajectory])[0]

    def score_many(self, trajectories: Sequence[Trajectory]) -> list[DetectorOutput]:
        outputs = self._checked_scores(list(trajectories))
        threshold = getattr(self, "threshold_", None)
        if threshold is None:
            return outputs
        return [DetectorOutput(o.scores, o.scores >= threshold, threshold) for o in outputs]

    def _require_fitted(self) -> None:
        if not hasattr(self, "state_dim_"):
            raise NotFittedError(f"{self.name} is not fitted: call fit() before scoring.")

    def _require_state_dim(self, trajectory: Trajectory) -> None:
        if trajectory.state_dim != self.state_dim_:
            raise ContractError(
                f"{self.name} was fitted on state dimension {self.state_dim_}; "
                f"got a trajectory with state dimension {trajectory.state_dim}."
            )

    def _checked_scores(self, trajectories: list[Trajectory]) -> list[DetectorOutput]:
        self._require_fitted()
        if not trajectories:
            return []
        for t in trajectories:
            self._require_state_dim(t)
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
