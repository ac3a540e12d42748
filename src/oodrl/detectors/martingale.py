"""`conformal_martingale`: a conformal test martingale of a base detector's scores (SPEC §20).

Vovk, Nouretdinov and Gammerman (2003), "Testing exchangeability on-line"; Vovk et al.,
*Algorithmic Learning in a Random World*, ch. 7. Three steps per stream:

1. **Base score** a_t of a registered detector (`base`, its params `base_params`; default
   `mahalanobis_distance` on states) as its nonconformity score. `fit` splits the fit
   trajectories: the base detector is fitted on the first ones and scores every step of the
   last ⌈`reference_fraction` · n⌉ (at least one, at least one left to fit), the reference
   scores r_1..r_n. (The protocol's calibration set sets the alarm threshold, as for every
   detector; the reference set is the conformal calibration set and is part of the fit.)
2. **Online smoothed conformal p-value** of a_t against the reference scores and the stream's
   own earlier scores a_0..a_{t−1} (N = n + t of them):

       p_t = (#{b > a_t} + U_t (#{b = a_t} + 1)) / (N + 1),

   U_t ∈ (0, 1] a seeded uniform indexed by the step t (common random numbers: a perturbed
   stream and its matched clean one share them). If the reference steps and the stream's steps
   are exchangeable, p_0, p_1, … are independent and uniform (Vovk et al., thm 8.1, for
   p-values against all earlier observations); a fixed reference set alone would not make them
   independent, so the stream's earlier scores join it.
3. **Power martingale**, mixed over a grid of exponents ε (`epsilons`; default 0.05, 0.15, …,
   0.95, a discretised simple mixture martingale — one value gives a fixed ε):

       M_t = (1/K) Σ_k Π_{u ≤ t} ε_k p_u^{ε_k − 1},     z_t = log M_t.

   Each factor has mean 1 under uniform p, so M is a test martingale (M_{−1} = 1), and by
   Ville's inequality P(sup_t M_t ≥ 1/α) ≤ α: the default threshold rule "ville" alarms at
   z_t ≥ log(1/α), with no held-out scores. The mixture keeps members with ε near 1, whose
   product barely decays on clean data, so the martingale does not sink so low on a long clean
   prefix that it cannot rise again after an onset.

**The guarantee assumes exchangeable steps, which trajectories are not**: consecutive states are
strongly dependent, episodes reset, and a clean stream's steps are not exchangeable with the
reference steps of other streams in any exact sense. Runs of unusually high (or low) base scores
that are normal for the dynamics then push the martingale up as evidence against exchangeability.
The alarm rate achieved on clean streams is measured and reported (`clean_episode_alarm`), as
for every detector; the nominal α is what the rule would give on exchangeable data. The
martingale runs over the whole stream: it is not reset at `dones` (faults persist across
resets).

Latency: the base detector's. Streaming: the base detector's own stream, and for each base
score it releases the p-value and the running sums of log factors (the same additions in the
same order as `score`), so `stream()` equals `score` bit for bit. It keeps the stream's earlier
base scores (a sorted list): memory and work grow with the stream by one float and one sorted
insertion per step. Logs and exps are `numerics.log` / `numerics.exp`: certified
machine-independent when the base detector is, which `base` must be.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import field
from typing import Any, ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.errors import ConfigError, ContractError
from oodrl.validation import Interval, IsType, SequenceOf

#: The default ε grid: midpoints of ten equal bins of (0, 1).
DEFAULT_EPSILONS = tuple(round(0.05 + 0.1 * k, 2) for k in range(10))


def conformal_p_values(
    reference: np.ndarray, scores: np.ndarray, uniforms: np.ndarray
) -> np.ndarray:
    """Online smoothed conformal p-values of a stream's scores (see the module docstring).

    `reference` sorted; p_t compares scores[t] with the reference and scores[:t]. Counts are
    integers, so the p-values do not depend on how the comparisons are batched.
    """
    n, T = len(reference), len(scores)  # noqa: N806 - T is the protocol's name
    greater = n - np.searchsorted(reference, scores, side="right")
    equal = n - greater - np.searchsorted(reference, scores, side="left")
    earlier = np.tril(np.ones((T, T), dtype=bool), k=-1)
    greater = greater + (earlier & (scores[None, :] > scores[:, None])).sum(axis=1)
    equal = equal + (earlier & (scores[None, :] == scores[:, None])).sum(axis=1)
    return (greater + uniforms * (equal + 1)) / (n + np.arange(T) + 1.0)


def log_mixture(log_factors_sum: np.ndarray) -> np.ndarray:
    """log((1/K) Σ_k exp(S_k)) of each row of (n, K) running sums S, stable and summed over k
    in index order (the same bits for a row alone and in a batch)."""
    top = log_factors_sum.max(axis=1)
    terms = numerics.exp(log_factors_sum - top[:, None])
    total = terms[:, 0].copy()
    for k in range(1, terms.shape[1]):
        total += terms[:, k]
    return top + numerics.log(total) - numerics.log(np.array([float(terms.shape[1])]))[0]


@detector_parameters
class ConformalMartingale(BaseDetector):
    """log of a conformal power martingale of a base detector's scores, alarm at 1/α (Ville).

    Parameters
    ----------
    base : str, default "mahalanobis_distance"
        A registered detector, certified machine-independent, whose score is the
        nonconformity score.
    base_params : dict, default {}
        Its parameters (its `seed` defaults to this detector's).
    reference_fraction : float in (0, 1), default 0.25
        The share of fit trajectories (rounded up; at least one, and one left to fit the base
        detector) whose base scores are the conformal reference.
    epsilons : list of floats in (0, 1), default [0.05, 0.15, …, 0.95]
        The exponents of the power martingales averaged into M_t.
    threshold_rule : default "ville"
        Alarm at M_t ≥ 1/α (`alpha`); the other rules apply to z_t as for any detector.
    """

    name: ClassVar[str] = "conformal_martingale"
    scores_are_log_martingales: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "base": [IsType(str)],
        "base_params": [IsType(dict)],
        "reference_fraction": [Interval(float, 0, 1, closed="neither")],
        "epsilons": [SequenceOf(Interval(float, 0, 1, closed="neither"))],
    }

    base: str = "mahalanobis_distance"
    base_params: Mapping[str, Any] = field(default_factory=dict)
    reference_fraction: float = 0.25
    epsilons: Sequence[float] = DEFAULT_EPSILONS
    threshold_rule: str = "ville"

    def _new_base(self) -> BaseDetector:
        from oodrl.detectors import DETECTORS

        if self.base == self.name:
            raise ConfigError(f"{self.name}: 'base' must name another detector.")
        cls = DETECTORS.get(self.base)
        if not cls.machine_independent:
            raise ConfigError(
                f"{self.name}: base detector '{self.base}' is not certified machine-independent "
                "(SPEC §14); choose one of oodrl's detectors."
            )
        return cls.from_params({"seed": self.seed, **self.base_params})

    def _validate_extra(self) -> None:
        self._new_base()

    @property
    def latency(self) -> int:
        base = getattr(self, "base_", None)
        return (base if base is not None else self._new_base()).latency

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        n = len(trajectories)
        if n < 2:
            raise ContractError(
                f"{self.name}.fit needs at least 2 trajectories (one to fit the base detector, "
                f"one for the conformal reference); got {n}."
            )
        n_reference = min(max(math.ceil(self.reference_fraction * n), 1), n - 1)
        self.base_ = self._new_base().fit(trajectories[: n - n_reference])
        scores = self.base_.score_many(trajectories[n - n_reference :])
        self.reference_ = np.sort(np.concatenate([o.scores for o in scores]))
        epsilons = np.asarray(self.epsilons, dtype=np.float64)
        self.log_epsilons_ = numerics.log(epsilons)
        self.exponents_ = epsilons - 1.0

    def _uniforms(self, rng: np.random.Generator, steps: int) -> np.ndarray:
        """U of the next `steps` steps, in (0, 1]: a generator drawn step by step gives the
        values of one draw of them all."""
        return 1.0 - rng.random(steps)

    def _log_factors(self, p_values: np.ndarray) -> np.ndarray:
        """(n, K) log(ε_k p^{ε_k − 1}) of each p-value."""
        return self.log_epsilons_ + self.exponents_ * numerics.log(p_values)[:, None]

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        base_scores = [o.scores for o in self.base_.score_many(trajectories)]
        uniforms = self._uniforms(np.random.default_rng(self.seed), max(t.T for t in trajectories))
        scores = []
        for a in base_scores:
            p_values = conformal_p_values(self.reference_, a, uniforms[: len(a)])
            # cumsum adds row after row, as a stream does.
            scores.append(log_mixture(np.cumsum(self._log_factors(p_values), axis=0)))
        return scores

    def stream(self) -> DetectorStream:
        return ConformalMartingaleStream(self)


class ConformalMartingaleStream(DetectorStream):
    """The base detector's stream; per released base score its p-value against the reference
    and the stream's earlier base scores (kept sorted), and the martingale's running sums."""

    def __init__(self, detector: ConformalMartingale) -> None:
        super().__init__(detector)
        self.base_stream = detector.base_.stream()
        self._restart()

    def _restart(self) -> None:
        self.uniform_rng = np.random.default_rng(self.detector.seed)
        self.earlier: list[float] = []
        self.sums = np.zeros(len(self.detector.log_epsilons_))

    def _martingale(self, records: StepScores) -> StepScores:
        detector = self.detector
        reference = detector.reference_
        out = []
        for record in records:
            a = record.score
            greater = len(reference) - int(np.searchsorted(reference, a, side="right"))
            below = int(np.searchsorted(reference, a, side="left"))
            equal = len(reference) - greater - below
            later = bisect.bisect_right(self.earlier, a)
            greater += len(self.earlier) - later
            equal += later - bisect.bisect_left(self.earlier, a)
            u = detector._uniforms(self.uniform_rng, 1)[0]
            p = (greater + u * (equal + 1)) / (len(reference) + len(self.earlier) + 1.0)
            bisect.insort(self.earlier, a)
            self.sums = self.sums + detector._log_factors(np.array([p]))[0]
            out.extend(self.scored(record.step, log_mixture(self.sums[None])))
        return tuple(out)

    def _update(self, step: Trajectory, t: int) -> StepScores:
        released = self.base_stream.update(
            step.states[0], step.actions[0], step.rewards[0], step.next_states[0], step.dones[0]
        )
        return self._martingale(released)

    def _flush(self) -> StepScores:
        pending = self._martingale(self.base_stream.flush())
        self._restart()
        return pending
