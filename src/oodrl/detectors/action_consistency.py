"""`action_consistency`: how often small observation perturbations change the policy's action.

A return-free detector in the spirit of STAC: a policy is taken to act consistently on the
observations it was trained on, and less so on unfamiliar ones, so the sensitivity of its action
to a fixed set of small perturbations of the observation it saw is the score. No reward, no
model of the environment: only the agent's policy (`oodrl.detectors.policy_view.PolicyDetector`:
the `policy` file, read once at `fit`; the greedy network, recomputed with the certified
machine-independent code).

The perturbations, fixed at `fit`: with σ the per-feature standard deviation of the fit
observations (`states`; 0 for a feature constant on the fit set, which is then not perturbed)
and ε_1..ε_4 ∈ {−1, +1}^d random sign vectors drawn from `seed`, the 8 perturbations are

    δ_j = ± scale · σ ⊙ ε_i     (j = 1..8: each sign vector and its negative),

every one of the same size, every feature moved by exactly `scale` of its clean spread (default
0.1: a tenth of a feature's spread), and each in an antithetic pair, so no direction is favoured.
Perturbations are added to the observation in float64 (then rounded to the network's float32),
before the policy's own observation normalisation.

The score of step t, with π the policy's greedy action:

- discrete actions: the share of the 8 perturbed observations whose greedy action differs from
  π(s_t), z_t ∈ {0, 1/8, …, 1}. Near a decision boundary the antithetic pairs give about ½;
  far from every boundary 0;
- continuous actions: the RMS action change, z_t = √((1/(8 d_a)) Σ_j Σ_i (π(s_t + δ_j)_i −
  π(s_t)_i)²), in the action's own units (after the policy's squashing or clipping).

Larger = more anomalous. Latency 0 (z_t reads s_t alone, row-independent: a stream scores each
step on its own, the same bits as a batch). Sums run left to right in fixed order.

Cost: every scored step runs the policy 9 times (s_t and its 8 perturbations), `CHUNK_STEPS`
steps to a batch, so that scoring a set of any size holds one chunk's arrays (tens of MB), not the
whole set's (about 0.14 MB a step on a 400-unit network: gigabytes for a set of streams).

**The premise does not always hold.** STAC's premise is that an out-of-distribution observation
makes the policy less consistent. On some policies a live observation fault made the policy
*more* consistent instead: the score fell below its clean level (one way this can happen: the
faulty observations land far from every decision boundary, or where a continuous action is
clipped). The method is kept as defined (larger = more anomalous): such faults are missed by it,
not flagged by a reversed score.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from oodrl.core.detector import detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import split_scores, stacked
from oodrl.detectors.policy_view import PolicyDetector
from oodrl.validation import Interval

#: The number of perturbations: 4 random sign vectors and their negatives.
N_PERTURBATIONS = 8
#: A feature standard deviation at or below this counts as a constant feature (not perturbed).
_MIN_SCALE = 1e-12
#: Steps scored per policy batch (9 rows a step: 2,304 rows). Memory grows with the batch, about
#: 0.14 MB a step on LunarLanderContinuous's actor (400 and 300 units): a chunk of 256 steps peaks
#: near 40 MB, where one batch of a whole set took gigabytes; larger chunks were no faster. Any
#: size gives the same bits: each action is correctly rounded (`oodrl.numerics`), a function of
#: its row alone whatever the batch (a plain BLAS product's bits can depend on the batch shape),
#: and a step's score is elementwise arithmetic on its own rows. Scoring draws no random numbers
#: (the perturbations are fixed at `fit`), so none are consumed in a chunk-dependent order.
CHUNK_STEPS = 256


def perturbations(spread: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """The (8, d) float64 perturbations ± scale · spread ⊙ ε_i of 4 sign vectors ε_i from seed."""
    signs = np.random.default_rng(seed).choice(
        [-1.0, 1.0], size=(N_PERTURBATIONS // 2, len(spread))
    )
    directions = np.concatenate([signs, -signs])
    return directions * (scale * np.where(spread > _MIN_SCALE, spread, 0.0))


@detector_parameters
class ActionConsistency(PolicyDetector):
    """The share of 8 fixed small observation perturbations that change the greedy action
    (discrete), or the RMS action change over them (continuous); see the module docstring.

    Parameters
    ----------
    policy : str, default "models/policy.pt"
        The agent's policy file (discrete actions with at least 2 of them, or a continuous actor).
    scale : float > 0, default 0.1
        The perturbations' size per feature, in units of the feature's standard deviation on the
        fit observations: small against the clean spread (a tenth), yet well above float32
        rounding, so that clean steps near a decision boundary flip and the clean scores are not
        all 0.
    """

    name: ClassVar[str] = "action_consistency"
    # z_t reads s_t alone, by row-independent arithmetic: a stream scores each step on its own.
    row_independent: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "scale": [Interval(float, 0, None, closed="neither")],
    }

    scale: float = 0.1

    @classmethod
    def policy_support(cls, policy: Any) -> str | None:
        if policy.action_kind == "discrete" and policy.action_size < 2:
            return "it counts changes of the greedy action, and the policy has one action"
        return None

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self._fit_policy(trajectories)
        spread = stacked(trajectories, lambda t: t.states.astype(np.float64)).std(axis=0)
        self.perturbations_ = perturbations(spread, self.scale, self.seed)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        states = stacked(trajectories, lambda t: t.states.astype(np.float64))
        chunks = range(0, len(states), CHUNK_STEPS)
        scores = [self._step_scores(states[start : start + CHUNK_STEPS]) for start in chunks]
        return split_scores(np.concatenate(scores), trajectories)

    def _step_scores(self, states: np.ndarray) -> np.ndarray:
        """The scores (n,) float64 of n steps' observations (n, d) float64: one policy batch."""
        n = len(states)
        perturbed = states[None, :, :] + self.perturbations_[:, None, :]
        actions = self.policy_.act(np.concatenate([states, perturbed.reshape(-1, states.shape[1])]))
        clean, moved = actions[:n], actions[n:].reshape(N_PERTURBATIONS, n, *actions.shape[1:])
        if self.policy_.action_kind == "discrete":
            changed = np.zeros(n, dtype=np.int64)
            for j in range(N_PERTURBATIONS):
                changed += moved[j] != clean
            return changed / N_PERTURBATIONS
        total = np.zeros(n)
        clean64 = clean.astype(np.float64)
        for j in range(N_PERTURBATIONS):
            difference = moved[j].astype(np.float64) - clean64
            for i in range(difference.shape[1]):
                total += difference[:, i] ** 2
        return np.sqrt(total / (N_PERTURBATIONS * clean.shape[1]))
