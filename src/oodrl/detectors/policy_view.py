"""The policy view (SPEC §20): what the agent's own policy computed at each step.

`PolicyDetector` is the base of the detectors that read the agent: its `policy` parameter names
the policy file, read once by `fit` (`oodrl.policies.load`) and kept in the fitted detector as
its numpy network (`policy_`), so scoring and streaming need no file and no torch. The default,
``models/policy.pt``, is the file every pipeline's commands name (`oodrl.suite.pipeline.POLICY`),
relative to the pipeline's directory, where its stages run. The network is recomputed by the
machine-independent policy code (`oodrl.policies.act`, SPEC §14) in greedy mode: the mean
network of a NoisyNet, whatever `policy.mode` the streams were collected in (a noise sample
belongs to the rollout, not to the state).

The observation the agent saw: `Trajectory.states[t]`, by SPEC §1 and by the collector, which
records in `states[t]` the very array the policy acted on. Under a live observation fault
(`oodrl.injectors.live_observation`) that is the sensor's corrupted report, never the
simulator's true state, so the view is the policy's output on what it actually saw.

Detectors on the view of a discrete head (Q-values, or the logits of a converted actor-critic),
each a function of the tempered values Q/T of step t alone (latency 0):

- `q_margin`: −(Q₍₁₎ − Q₍₂₎)/T, the negative gap between the two largest values (the temperature
  only sets the unit; the ranking is the raw margin's);
- `q_entropy`: the entropy of softmax(Q/T);
- `q_energy`: −T·logsumexp(Q/T), the energy score (Liu et al. 2020, as OpenOOD orients it);
- `max_softmax`: −max softmax(Q/T) (Hendrycks and Gimpel 2017).

Larger = more anomalous throughout. The temperature: Q-values are in units of return, which
differ between environments, so T is fitted on the clean fit steps, deterministically: the T at
which their mean softmax entropy is `target_entropy` (default 0.5) times its maximum log K,
found by bisection (the mean entropy grows with T). Maximising the likelihood of the recorded
actions is no option: a greedy policy's action is the argmax, whose likelihood grows as T → 0.
A `temperature` parameter fixes T instead.

A policy without a value head (the deterministic actor of SAC, TD3, PPO on continuous actions)
has no Q-values to read: these detectors refuse it at `fit` with the reason, which
`policy_support` also returns for whoever lists the detectors an environment cannot support.

Arithmetic: the values are correctly rounded float32 (`numerics.linear`), exp and log are the
certified `numerics` functions, sums over actions run left to right: a step's score is the same
bits alone or in a batch, on every machine.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import split_scores, stacked
from oodrl.errors import ConfigError, PolicyError
from oodrl.validation import Interval, IsNone, IsType

#: The policy file of every pipeline, relative to its directory (`oodrl.suite.pipeline.POLICY`, not
#: imported: a detector's module must stay light, and its imports are its stages' code deps).
DEFAULT_POLICY = "models/policy.pt"

#: Bisection steps of the fitted temperature: each halves log(T_high / T_low), from log 10^12
#: ≈ 27.6, so that 40 leave T within a factor 1 + 3·10^−11.
TEMPERATURE_STEPS = 40
#: Exponents (Q − max Q)/T below this are taken at it: e^−600 ≈ 3·10^−261 changes no sum that
#: holds the best action's e^0 = 1, and `numerics.exp` certifies results near the bottom of the
#: float64 range (below e^−680 or so) digit by digit, a thousand times slower.
EXPONENT_FLOOR = -600.0


def row_sum(x: np.ndarray) -> np.ndarray:
    """The sum of each row of an (n, k) array, left to right: the same bits for a row alone or
    in a batch (numpy may reduce a row pairwise, in an order that depends on the layout)."""
    total = np.array(x[:, 0], dtype=np.float64)
    for column in range(1, x.shape[1]):
        total += x[:, column]
    return total


def greedy_network(policy: Any) -> Any:
    """The policy's greedy network: NoisyNet noise scales dropped (a fitted detector keeps only
    the mean weights it computes with)."""
    from oodrl.policies.act import Layer

    network = copy.copy(policy)
    network.layers = [Layer(layer.weight, layer.bias) for layer in policy.layers]
    network.mode = "greedy"
    return network


@detector_parameters
class PolicyDetector(BaseDetector):
    """A detector that reads the agent's policy (see the module docstring).

    Parameters
    ----------
    policy : str, default "models/policy.pt"
        The policy file (an oodrl checkpoint, as every pipeline's `models/policy.pt`), relative
        to the working directory: a pipeline's stages run in its directory.
    """

    # Reading a checkpoint is torch.load; the fitted detector holds numpy arrays only.
    uses_torch: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {"policy": [IsType(str)]}

    policy: str = DEFAULT_POLICY

    @classmethod
    def policy_support(cls, policy: Any) -> str | None:
        """None where the detector can read `policy` (a loaded policy), else why not."""
        return None

    def _fit_policy(self, trajectories: Sequence[Trajectory]) -> Any:
        """Load `policy` and check it against the fit trajectories; sets `policy_`."""
        from oodrl.policies.act import LayeredPolicy
        from oodrl.policies.load import load_policy

        try:
            policy = load_policy(self.policy)
        except PolicyError as error:
            raise ConfigError(f"The 'policy' parameter of {self.name}: {error}") from None
        if not isinstance(policy, LayeredPolicy):
            raise ConfigError(
                f"{self.name} recomputes the policy with oodrl's machine-independent code, which "
                f"reads oodrl checkpoints; {self.policy} is a {policy.kind} policy: convert it "
                "(`oodrl new --policy` converts Stable-Baselines3 files)."
            )
        reason = self.policy_support(policy)
        if reason is not None:
            raise ConfigError(f"{self.name} cannot use {self.policy}: {reason}.")
        if policy.state_dim != trajectories[0].state_dim:
            raise ConfigError(
                f"The 'policy' parameter of {self.name} names {self.policy}, a policy of "
                f"observation dimension {policy.state_dim}; the fit trajectories have dimension "
                f"{trajectories[0].state_dim}. Name the policy that collected them."
            )
        self.policy_ = greedy_network(policy)
        return self.policy_

    def policy_view(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        """The policy view: the fitted policy's outputs (ΣT, action_size) float32 on the
        observations it saw (`states`), trajectory after trajectory."""
        return self.policy_.outputs(stacked(trajectories, lambda t: t.states))


@dataclass(frozen=True)
class TemperedValues:
    """The softmax of Q/T, row by row, as the view's scores read it (float64).

    `top` is max Q; `shifted` is u = (Q − top)/T ≤ 0 and `exponentials` e^u; `partition` is
    Z = Σ e^u ≥ 1 and `log_partition` its logarithm.
    """

    temperature: float
    top: np.ndarray
    shifted: np.ndarray
    exponentials: np.ndarray
    partition: np.ndarray
    log_partition: np.ndarray

    @classmethod
    def of(cls, values: np.ndarray, temperature: float) -> TemperedValues:
        q = np.asarray(values, dtype=np.float64)
        top = q.max(axis=1)
        shifted = (q - top[:, None]) / temperature
        exponentials = numerics.exp(np.maximum(shifted, EXPONENT_FLOOR))
        partition = row_sum(exponentials)
        return cls(temperature, top, shifted, exponentials, partition, numerics.log(partition))

    def entropy(self) -> np.ndarray:
        """H = log Z − Σ_k p_k u_k, with p = e^u / Z."""
        probabilities = self.exponentials / self.partition[:, None]
        return self.log_partition - row_sum(probabilities * self.shifted)


def fitted_temperature(values: np.ndarray, target_entropy: float) -> float:
    """The T at which the mean entropy of softmax(Q/T) over the rows of `values` is
    `target_entropy`·log K, by bisection on a geometric scale (machine-independent: IEEE
    arithmetic, certified exp and log, exact sums). 1 when every row's values are all equal
    (the entropy is log K whatever T)."""
    q = np.asarray(values, dtype=np.float64)
    spread = math.fsum((q.max(axis=1, keepdims=True) - q).ravel()) / q.size
    if spread == 0.0:
        return 1.0
    goal = target_entropy * float(numerics.log(np.float64(q.shape[1])))
    low, high = spread * 1e-6, spread * 1e6
    for _ in range(TEMPERATURE_STEPS):
        middle = math.sqrt(low * high)
        entropy = TemperedValues.of(q, middle).entropy()
        if math.fsum(entropy) / len(entropy) < goal:
            low = middle
        else:
            high = middle
    return math.sqrt(low * high)


@detector_parameters
class PolicyView(PolicyDetector):
    """Base of the detectors on the tempered values Q/T of a discrete head (module docstring).

    Parameters
    ----------
    policy : str, default "models/policy.pt"
        The agent's policy file; it needs a discrete head (Q-values or logits).
    temperature : float > 0 or None, default None
        T; None fits it on the clean fit steps (`target_entropy`).
    target_entropy : float in (0, 1), default 0.5
        The fitted T's mean softmax entropy on the fit steps, as a fraction of log K.
    """

    # z_t reads s_t alone, by row-independent arithmetic: a stream scores each step on its own.
    row_independent: ClassVar[bool] = True

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "temperature": [IsNone(), Interval(float, 0, None, closed="neither")],
        "target_entropy": [Interval(float, 0, 1, closed="neither")],
    }

    temperature: float | None = None
    target_entropy: float = 0.5

    @classmethod
    def policy_support(cls, policy: Any) -> str | None:
        if policy.action_kind != "discrete":
            return (
                f"it reads the values (Q-values or logits) of a discrete action head, and the "
                f"policy is a {policy.kind}, a deterministic actor of continuous actions, "
                "which has none"
            )
        if policy.action_size < 2:
            return "it compares the values of several actions, and the policy has one"
        return None

    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self._fit_policy(trajectories)
        if self.temperature is not None:
            self.temperature_ = float(self.temperature)
        else:
            values = self.policy_view(trajectories)
            self.temperature_ = fitted_temperature(values, self.target_entropy)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        tempered = TemperedValues.of(self.policy_view(trajectories), self.temperature_)
        return split_scores(self._view_scores(tempered), trajectories)

    def _view_scores(self, tempered: TemperedValues) -> np.ndarray:
        """The scores (n,) of n steps' tempered values."""
        raise NotImplementedError


@detector_parameters
class QMargin(PolicyView):
    """−(Q₍₁₎ − Q₍₂₎)/T: a small gap between the two best actions is anomalous."""

    name: ClassVar[str] = "q_margin"

    def _view_scores(self, tempered: TemperedValues) -> np.ndarray:
        # The second largest of (Q − top)/T is −(Q₍₁₎ − Q₍₂₎)/T.
        return np.sort(tempered.shifted, axis=1)[:, -2]


@detector_parameters
class QEntropy(PolicyView):
    """The entropy of softmax(Q/T)."""

    name: ClassVar[str] = "q_entropy"

    def _view_scores(self, tempered: TemperedValues) -> np.ndarray:
        return tempered.entropy()


@detector_parameters
class QEnergy(PolicyView):
    """The energy −T·logsumexp(Q/T) = −(max Q + T·log Σ exp((Q − max Q)/T))."""

    name: ClassVar[str] = "q_energy"

    def _view_scores(self, tempered: TemperedValues) -> np.ndarray:
        return -(tempered.top + tempered.temperature * tempered.log_partition)


@detector_parameters
class MaxSoftmax(PolicyView):
    """−max softmax(Q/T) = −1/Σ exp((Q − max Q)/T)."""

    name: ClassVar[str] = "max_softmax"

    def _view_scores(self, tempered: TemperedValues) -> np.ndarray:
        return -1.0 / tempered.partition
