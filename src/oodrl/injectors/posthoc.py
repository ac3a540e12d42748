"""Post-hoc injectors: perturb the observation stream of a copy of a clean trajectory (SPEC §4).

Each injector rewrites the labelled rows of the (T + 1, d) observation stream; the base class
keeps `states` and `next_states` consistent and refuses changes to unlabelled rows. Random draws
do not depend on the severity (common random numbers): the noise is scaled, the dropped entries
and permuted coordinates at a severity are a subset of those at any larger one, and severity 0
returns the stream bit for bit. Stream statistics (sd_i, means) are taken over the whole
(T + 1)-row observation stream of the clean trajectory, reset observations included.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from oodrl.core.injector import PostHocInjector
from oodrl.core.spec import AnomalySpec
from oodrl.errors import ContractError
from oodrl.validation import Interval


class GaussianStateNoise(PostHocInjector):
    """Adds N(0, (σ·sd_i)²) to coordinate i; sd_i is its std over the clean observation stream."""

    name: ClassVar[str] = "gaussian_state_noise"

    def _perturb(
        self, stream: np.ndarray, labels: np.ndarray, spec: AnomalySpec, rng: np.random.Generator
    ) -> np.ndarray:
        clean = stream.astype(np.float64)
        noise = rng.standard_normal(stream.shape) * (spec.severity * clean.std(axis=0))
        stream[labels] = clean[labels] + noise[labels]
        return stream


class StateFeatureDropout(PostHocInjector):
    """Sets each coordinate of each labelled step to 0 independently with probability 0.8σ."""

    name: ClassVar[str] = "state_feature_dropout"

    def _perturb(
        self, stream: np.ndarray, labels: np.ndarray, spec: AnomalySpec, rng: np.random.Generator
    ) -> np.ndarray:
        dropped = rng.random(stream.shape) < 0.8 * spec.severity
        dropped[~labels] = False
        stream[dropped] = 0.0
        return stream


class CorrelationBreak(PostHocInjector):
    """Permutes ⌈σ·d⌉ randomly chosen coordinates over the labelled window, each independently.

    Each chosen coordinate keeps its post-onset values (its marginal), but their order — and so
    their coupling to the other coordinates and to time — is broken.
    """

    name: ClassVar[str] = "correlation_break"

    def _perturb(
        self, stream: np.ndarray, labels: np.ndarray, spec: AnomalySpec, rng: np.random.Generator
    ) -> np.ndarray:
        d = stream.shape[1]
        rows = np.flatnonzero(labels)
        order = rng.permutation(d)
        permutations = [rng.permutation(rows) for _ in range(d)]
        for i in order[: math.ceil(spec.severity * d)]:
            stream[rows, i] = stream[permutations[i], i]
        return stream


class RegimeSwitch(PostHocInjector):
    """Shifts the labelled window by 2σ pre-onset stds and widens its spread by sqrt(1 + 2σ).

    x' = m + sqrt(1 + 2σ)(x − m) + 2σ·sd_pre, with m the post-onset mean and sd_pre the std of
    each coordinate over the steps before onset: the post-onset mean moves by exactly
    2σ·sd_pre and the post-onset variance is multiplied by exactly (1 + 2σ). Deterministic;
    the trajectory is not re-simulated.
    """

    name: ClassVar[str] = "regime_switch"

    def _perturb(
        self, stream: np.ndarray, labels: np.ndarray, spec: AnomalySpec, rng: np.random.Generator
    ) -> np.ndarray:
        rows = np.flatnonzero(labels)
        if rows.size == 0:
            return stream
        if rows[0] == 0:
            raise ContractError(
                "regime_switch needs steps before the onset to measure their spread; "
                "use an onset >= 1."
            )
        clean = stream.astype(np.float64)
        window = clean[rows]
        mean = window.mean(axis=0)
        sd_pre = clean[: rows[0]].std(axis=0)
        widening = math.sqrt(1.0 + 2.0 * spec.severity) - 1.0
        # Written as x + (...) so that severity 0 returns x bit for bit.
        stream[rows] = window + widening * (window - mean) + 2.0 * spec.severity * sd_pre
        return stream


class ObservationDelay(PostHocInjector):
    """Replaces the observation at step t by the clean observation at t − k, k = ⌈σ·max_delay⌉.

    The delay line is the sensor's: it runs over the deployment stream and is not flushed when
    an episode resets, so for k steps after a reset the policy-facing stream still shows the end
    of the previous episode (the terminal `next_states` row of the done step is kept, as for
    every post-hoc injector). Before the first step the delay line holds the first observation.
    """

    name: ClassVar[str] = "observation_delay"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "max_delay": [Interval(int, 1, None)],
    }

    def __init__(self, *, severity: float | None = None, max_delay: int = 10) -> None:
        super().__init__(severity=severity)
        self.max_delay = max_delay

    def delay(self, severity: float) -> int:
        """The delay k in steps at a severity."""
        return math.ceil(severity * self.max_delay)

    def _perturb(
        self, stream: np.ndarray, labels: np.ndarray, spec: AnomalySpec, rng: np.random.Generator
    ) -> np.ndarray:
        rows = np.flatnonzero(labels)
        source = np.maximum(rows - self.delay(spec.severity), 0)
        stream[rows] = stream[source]
        return stream
