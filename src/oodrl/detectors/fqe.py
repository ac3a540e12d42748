"""`fqe_td`: temporal-difference errors of the agent's own policy's value (SPEC §20).

An ensemble of M small Q-networks Q_m(s, a) is fitted by fitted Q evaluation (FQE; Le et al.
2019) of the fixed policy π on the clean fit transitions: from Q_m ≡ 0, each of `iterations`
rounds regresses member m, on its own bootstrap resample, onto its own targets of the round,

    y_m,t = r̃_t + γ (1 − done_t) Q_m(s_{t+1}, π(s_{t+1})),

for `epochs` epochs of Adam (the round's targets fixed). π(s_{t+1}) is the policy's own action on
the next observation, recomputed from the policy file (`oodrl.detectors.policy_view`): the greedy
action of a discrete head, the deterministic action of an actor; the recorded a_{t+1} would give
the same for a deterministic policy, but is unknown at step t. Inputs are the standardised
(s_t, a_t), a discrete action one-hot over the policy's actions, a continuous one as given; the
rewards are divided by their fit-set standard deviation, so Q and the score are in units of the
clean reward's spread. `done` ends the bootstrap: the collector does not say whether an episode
was terminated or truncated, so a truncation is treated as a termination, alike in clean and
faulty streams.

The score of a transition, larger = more anomalous:

    z_t = (1/M) Σ_m |y_m,t − Q_m(s_t, a_t)| + w · sd_m Q_m(s_t, a_t),

the members' mean absolute TD error (the transition contradicts the value the clean data taught)
plus `disagreement_weight` w (default 1) times their spread at (s_t, a_t) (the ensemble has not
learned that state-action: epistemic uncertainty, as `ensemble_disagreement` on the dynamics).
Both terms are in the same units, so they add without a learned weight. z_t reads s_{t+1},
r_t and done_t: latency 1.

`gamma` defaults to 0.9, not the agent's 0.99: a round of FQE extends the evaluated horizon by
one step, and 20 rounds of γ = 0.9 leave γ²⁰ ≈ 0.12 of the initial error, where γ = 0.99 would
need hundreds of rounds.

Networks, and why they are the same bytes on every machine: `oodrl.detectors.neural`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from oodrl.core.detector import detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors import mlp
from oodrl.detectors.features import ActionEncoding, Standardizer, split_scores, stacked
from oodrl.detectors.neural import NeuralDetector, chunked_scores
from oodrl.detectors.policy_view import PolicyDetector, row_sum
from oodrl.errors import ConfigError
from oodrl.validation import Interval


def _rewards(trajectory: Trajectory) -> np.ndarray:
    """The rewards as a (T, 1) float64 column."""
    return trajectory.rewards.astype(np.float64)[:, None]


def member_values(weights: mlp.EnsembleWeights, inputs: np.ndarray) -> np.ndarray:
    """Every member's Q on the inputs: (N, M) float64."""
    return chunked_scores(weights, inputs, lambda outputs, rows: outputs[..., 0].T)


def policy_encoding(policy: Any, trajectories: Sequence[Trajectory]) -> ActionEncoding:
    """The encoding of the policy's actions (one-hot over its discrete actions, or its action
    vector), refused when the recorded actions are of another kind or size."""
    if policy.action_kind == "discrete":
        encoding = ActionEncoding(policy.action_size, policy.action_size)
    else:
        encoding = ActionEncoding(None, policy.action_size)
    recorded = ActionEncoding.fit(trajectories)
    if (recorded.n_actions is None) != (encoding.n_actions is None) or (
        recorded.dim > encoding.dim if encoding.n_actions else recorded.dim != encoding.dim
    ):
        raise ConfigError(
            f"The policy {policy.kind} acts with {policy.action_kind} actions of size "
            f"{policy.action_size}; the fit trajectories record actions of another kind or size."
        )
    return encoding


@detector_parameters
class FqeTd(PolicyDetector, NeuralDetector):
    """Mean absolute TD error of an FQE ensemble of the policy, plus the ensemble's spread.

    Parameters
    ----------
    policy : str, default "models/policy.pt"
        The agent's policy file (`PolicyDetector`): it gives π(s_{t+1}).
    n_members : int >= 2, default 5
        Ensemble size M.
    iterations : int >= 1, default 20
        FQE rounds (targets recomputed from the members' previous values).
    epochs : int >= 1, default 1
        Epochs of Adam per round.
    gamma : float in [0, 1), default 0.9
        Discount of the evaluated value.
    disagreement_weight : float >= 0, default 1.0
        w, the weight of the members' spread in the score.
    hidden_sizes : list of int, default [64]
        The Q-networks' hidden layers.
    batch_size, lr
        Training (`NeuralDetector`): defaults 256, 1e-3.
    """

    name: ClassVar[str] = "fqe_td"
    # z_t reads step t alone (s_t, a_t, r_t, s_{t+1}, done_t) by row-independent arithmetic.
    row_independent: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "n_members": [Interval(int, 2, None)],
        "iterations": [Interval(int, 1, None)],
        "gamma": [Interval(float, 0, 1, closed="left")],
        "disagreement_weight": [Interval(float, 0, None)],
    }

    n_members: int = 5
    hidden_sizes: Sequence[int] = (64,)
    iterations: int = 20
    epochs: int = 1
    gamma: float = 0.9
    disagreement_weight: float = 1.0

    @property
    def latency(self) -> int:
        return 1

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        policy = self._fit_policy(trajectories)
        self.action_encoding_ = policy_encoding(policy, trajectories)
        raw = stacked(trajectories, self._raw_inputs)
        self.input_standardizer_ = Standardizer.fit(raw)
        # The fit rewards' standard deviation (1 for constant rewards), as a Standardizer has it.
        self.reward_scale_ = float(Standardizer.fit(stacked(trajectories, _rewards)).scale[0])
        inputs = self.input_standardizer_.transform(raw)
        next_inputs = self._next_inputs(trajectories)
        rewards, continuation = self._rewards_and_continuation(trajectories)
        rng = np.random.default_rng(self.seed)
        sizes = (inputs.shape[1], *self.hidden_sizes, 1)
        weights = mlp.init_weights(self.n_members, sizes, rng)
        rows = mlp.member_indices(self.n_members, len(inputs), True, rng)
        settings = mlp.OptimiserSettings(self.epochs, self.batch_size, self.lr)
        next_values = np.zeros((len(inputs), self.n_members))  # Q_0 ≡ 0
        self.training_losses_ = []
        for round_ in range(self.iterations):
            if round_ > 0:
                next_values = member_values(weights, next_inputs)
            targets = rewards[:, None] + continuation[:, None] * next_values  # (N, M)
            weights, losses = mlp.train(
                weights, inputs, targets.T[..., None], mlp.mse, settings, rows, rng
            )
            self.training_losses_.append(losses[-1])
        self.weights_ = weights

    def _raw_inputs(self, trajectory: Trajectory) -> np.ndarray:
        """The unstandardised (s_t, encoded a_t) of each step."""
        actions = self.action_encoding_.encode(trajectory.actions)
        return np.hstack([trajectory.states.astype(np.float64), actions])

    def _next_inputs(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        """The standardised (s_{t+1}, encoded π(s_{t+1})) of each step."""
        next_states = stacked(trajectories, lambda t: t.next_states)
        actions = self.action_encoding_.encode(self._policy_actions(next_states))
        raw = np.hstack([next_states.astype(np.float64), actions])
        return self.input_standardizer_.transform(raw)

    def _policy_actions(self, observations: np.ndarray) -> np.ndarray:
        """π of each observation. A discrete head's greedy action is the argmax of its exactly
        rounded outputs, as the policy acts; computed here from the outputs, so that no cache a
        policy keeps for acting faster lands in the fitted detector or changes as it scores."""
        if self.action_encoding_.n_actions is None:
            return self.policy_.act(observations)
        return self.policy_.outputs(observations).argmax(axis=1)

    def _rewards_and_continuation(
        self, trajectories: Sequence[Trajectory]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The scaled rewards r̃_t and γ (1 − done_t) of each step."""
        rewards = stacked(trajectories, _rewards)[:, 0]
        dones = stacked(trajectories, lambda t: t.dones)
        return rewards / self.reward_scale_, np.where(dones, 0.0, self.gamma)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        inputs = self.input_standardizer_.transform(stacked(trajectories, self._raw_inputs))
        values = member_values(self.weights_, inputs)
        next_values = member_values(self.weights_, self._next_inputs(trajectories))
        rewards, continuation = self._rewards_and_continuation(trajectories)
        errors = rewards[:, None] + continuation[:, None] * next_values - values
        m = self.n_members
        mean = row_sum(values) / m
        deviations = values - mean[:, None]
        spread = np.sqrt(row_sum(deviations * deviations) / m)
        scores = row_sum(np.abs(errors)) / m + self.disagreement_weight * spread
        return split_scores(scores, trajectories)
