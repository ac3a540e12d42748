"""`riqn`: a recurrent implicit quantile network of the dynamics (Danesh and Fern 2021,
"Out-of-distribution dynamics detection: RL-relevant benchmarks and results"; SPEC §20).

A GRU reads the stream's (state, action) history and an implicit quantile network (IQN; Dabney
et al. 2018) head predicts quantiles of the next state from its hidden state:

    h_t = GRU(h_{t−1}, x_t),   x_t = standardised (s_t, one-hot a_t),   h = 0 at an episode start
    φ(τ) = ReLU(W_φ [cos(π j τ)]_{j=0..n_cos−1} + b_φ)
    q_t(τ) = W_2 ReLU(W_1 (h_t ∘ φ(τ)) + b_1) + b_2       (the τ-quantile of the increment)

The target is the increment s_{t+1} − s_t standardised per coordinate on the fit set, so every
coordinate counts in units of its typical change. Training minimises the quantile (pinball) loss
ρ_τ(u) = u (τ − 1[u < 0]), u = y − q, at `n_quantiles` levels per step drawn uniformly from the
grid τ = i/32 (i = 1..31), by truncated backpropagation through time: the fit trajectories are
read side by side in chunks of `chunk_length` steps, the hidden state carried from chunk to
chunk, one Adam step per chunk, for `epochs` passes.

Score: the mean pinball loss of the observed increment at the fixed levels τ = 1/8, …, 7/8,

    z_t = (1/(7 d_s)) Σ_τ Σ_i ρ_τ(y_{t,i} − q_{t,i}(τ)),

large when s_{t+1} falls outside the predicted quantiles. It uses s_{t+1}: latency 1. The hidden
state restarts at 0 on the first step after a `done`.

Machine independence (SPEC §14), as for the other neural detectors (`oodrl.detectors.mlp`):
training and scoring run in numpy; every matrix product, forward and backward, is
`numerics.linear` (correctly rounded float32); tanh is `numerics.tanh` (correctly rounded) and
the sigmoid is ½ + ½ tanh(x/2) of it; the cosine features are computed in `decimal` once; the
rest is elementwise float32 / float64 arithmetic and sums in a fixed order. So a fitted
detector and its scores are the same bytes on every x86-64 machine. The same correctly rounded
products make the recurrence row-independent: a stream carrying h step by step gives `score`'s
bits exactly. The backward pass is written out by hand (checked against torch's autograd in
tests/detectors/test_riqn.py).
"""

from __future__ import annotations

import decimal
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from fractions import Fraction
from typing import ClassVar

import numpy as np

from oodrl import numerics
from oodrl.core.detector import BaseDetector, detector_parameters
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    ActionEncoding,
    Standardizer,
    increments,
    trajectory_features,
)
from oodrl.detectors.mlp import Adam
from oodrl.validation import Interval

#: The quantile levels training draws from: i/32, i = 1..31.
TRAINING_LEVELS = tuple(Fraction(i, 32) for i in range(1, 32))
#: The fixed quantile levels of the score: 1/8, …, 7/8.
SCORE_LEVELS = tuple(Fraction(k, 8) for k in range(1, 8))

_PI = decimal.Decimal("3.14159265358979323846264338327950288419716939937510582097494459")
_HALF = np.float32(0.5)
_ONE = np.float32(1)


def cos_pi(fraction: Fraction) -> float:
    """cos(π · fraction) from its Taylor series in 50-digit `decimal`, the same on every machine
    (libm's cos may differ in the last bit between CPUs)."""
    turn = fraction % 2
    if turn > 1:
        turn = 2 - turn  # cos(π(2 − f)) = cos(πf)
    with decimal.localcontext() as context:
        context.prec = 50
        x = _PI * turn.numerator / turn.denominator
        term = total = decimal.Decimal(1)
        k = 0
        while abs(term) > decimal.Decimal("1e-45"):
            k += 2
            term = -term * x * x / (k * (k - 1))
            total += term
    return float(total)


def cosine_features(levels: Sequence[Fraction], n_cos: int) -> np.ndarray:
    """(len(levels), n_cos) float32: cos(π j τ) for j = 0..n_cos − 1, one row per level τ."""
    return np.array([[cos_pi(j * tau) for j in range(n_cos)] for tau in levels], np.float32)


def sigmoid(x: np.ndarray) -> np.ndarray:
    """σ(x) = ½ + ½ tanh(x/2) in float32, from the correctly rounded tanh."""
    return _HALF + _HALF * numerics.tanh(_HALF * x)


@dataclass(frozen=True)
class RiqnWeights:
    """The network's float32 weights; `weight` (out, in), `bias` (out,), torch's GRU layout
    for the gates (reset, update, new)."""

    input_weight: np.ndarray  # (3H, d_in)
    input_bias: np.ndarray  # (3H,)
    hidden_weight: np.ndarray  # (3H, H)
    hidden_bias: np.ndarray  # (3H,)
    embedding_weight: np.ndarray  # (H, n_cos)
    embedding_bias: np.ndarray  # (H,)
    head_weight: np.ndarray  # (H, H)
    head_bias: np.ndarray  # (H,)
    output_weight: np.ndarray  # (d_s, H)
    output_bias: np.ndarray  # (d_s,)

    def arrays(self) -> list[np.ndarray]:
        return [getattr(self, f.name) for f in fields(self)]

    @classmethod
    def of(cls, arrays: Sequence[np.ndarray]) -> RiqnWeights:
        return cls(*arrays)

    @classmethod
    def initial(
        cls, d_in: int, hidden: int, n_cos: int, d_out: int, rng: np.random.Generator
    ) -> RiqnWeights:
        """U(−1/√fan_in, 1/√fan_in) for every weight and bias, as torch initialises its GRU
        (fan_in = H) and its Linear layers."""
        shapes = [
            ((3 * hidden, d_in), hidden),
            ((3 * hidden,), hidden),
            ((3 * hidden, hidden), hidden),
            ((3 * hidden,), hidden),
            ((hidden, n_cos), n_cos),
            ((hidden,), n_cos),
            ((hidden, hidden), hidden),
            ((hidden,), hidden),
            ((d_out, hidden), hidden),
            ((d_out,), hidden),
        ]
        arrays = []
        for shape, fan_in in shapes:
            bound = 1.0 / math.sqrt(fan_in)
            arrays.append(rng.uniform(-bound, bound, shape).astype(np.float32))
        return cls.of(arrays)

    @property
    def hidden_size(self) -> int:
        return self.hidden_weight.shape[1]


@dataclass
class GruCache:
    """What one GRU step keeps for its backward pass."""

    previous: np.ndarray
    reset: np.ndarray
    update: np.ndarray
    new: np.ndarray
    hidden_new_part: np.ndarray


def gru_step(
    w: RiqnWeights, gates_in: np.ndarray, previous: np.ndarray
) -> tuple[np.ndarray, GruCache]:
    """h_t from h_{t−1} (n, H) and the input's gate pre-activations W_i x_t + b_i (n, 3H):
    r, u = σ(·), n = tanh(a_n + r ∘ (W_hn h + b_hn)), h = n + u ∘ (h_{t−1} − n) (torch's GRU)."""
    hidden = w.hidden_size
    gates_hidden = numerics.linear(previous, w.hidden_weight, w.hidden_bias)
    reset_update = sigmoid(gates_in[:, : 2 * hidden] + gates_hidden[:, : 2 * hidden])
    reset, update = reset_update[:, :hidden], reset_update[:, hidden:]
    hidden_new_part = gates_hidden[:, 2 * hidden :]
    new = numerics.tanh(gates_in[:, 2 * hidden :] + reset * hidden_new_part)
    h = new + update * (previous - new)
    return h, GruCache(previous, reset, update, new, hidden_new_part)


def quantiles(w: RiqnWeights, h: np.ndarray, embedding: np.ndarray) -> list[np.ndarray]:
    """The head's layers for rows h (m, H) paired with τ embeddings φ (m, H): the product,
    the hidden layer after ReLU, and the quantile predictions (m, d_s), float32."""
    product = h * embedding
    layer = numerics.relu(numerics.linear(product, w.head_weight, w.head_bias))
    return [product, layer, numerics.linear(layer, w.output_weight, w.output_bias)]


def embed(w: RiqnWeights, cosines: np.ndarray) -> np.ndarray:
    """φ(τ) (m, H) of cosine feature rows (m, n_cos)."""
    return numerics.relu(numerics.linear(cosines, w.embedding_weight, w.embedding_bias))


def _weight_gradient(grad: np.ndarray, inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dW = gradᵀ inputs and db = gradᵀ 1 for a layer y = x Wᵀ + b, as one correctly rounded
    product with [x, 1] (as `oodrl.detectors.mlp.gradients` does)."""
    augmented = np.concatenate([inputs, np.ones((len(inputs), 1), np.float32)], axis=1)
    both = numerics.linear(grad.T, augmented.T)  # views: the layouts `linear` runs fastest on
    return both[:, :-1], np.ascontiguousarray(both[:, -1])


@dataclass(frozen=True)
class Chunk:
    """A chunk of the fit streams side by side: B rows of L steps.

    `inputs` (B, L, d_in) and `targets` (B, L, d_s) float32; `starts` (B, L) marks the first
    step of an episode (h restarts at 0 before it); `valid` (B, L) the steps that exist (a
    shorter stream is padded); `levels` (B, L, K) the indices of the training levels drawn for
    each step.
    """

    inputs: np.ndarray
    targets: np.ndarray
    starts: np.ndarray
    valid: np.ndarray
    levels: np.ndarray


def chunk_gradients(
    w: RiqnWeights, chunk: Chunk, h0: np.ndarray, cosines: np.ndarray, taus: np.ndarray
) -> tuple[float, RiqnWeights, np.ndarray]:
    """The mean pinball loss of one chunk, its gradient with respect to every weight, and the
    hidden state after its last step (the next chunk's h0; no gradient flows across chunks).

    `cosines` (n_levels, n_cos) and `taus` (n_levels,) are the training levels' features and
    values; the loss averages over the valid steps, their K levels and the d_s coordinates.
    """
    n_rows, length, _ = chunk.inputs.shape
    hidden = w.hidden_size
    k = chunk.levels.shape[2]
    gates_in = numerics.linear(chunk.inputs.reshape(n_rows * length, -1), w.input_weight,
                               w.input_bias).reshape(n_rows, length, -1)  # fmt: skip
    zero = np.zeros((n_rows, hidden), np.float32)
    h = h0
    caches, states = [], np.empty((n_rows, length, hidden), np.float32)
    for t in range(length):
        h = np.where(chunk.starts[:, t, None], zero, h)
        h, cache = gru_step(w, gates_in[:, t], h)
        caches.append(cache)
        states[:, t] = h
    # The head on every (step, drawn level) pair: rows ordered (b, t, k).
    level_index = chunk.levels.reshape(-1)
    embedding_pre = numerics.linear(cosines[level_index], w.embedding_weight, w.embedding_bias)
    embedding = numerics.relu(embedding_pre)
    h_rows = np.repeat(states.reshape(n_rows * length, hidden), k, axis=0)
    product, layer, q = quantiles(w, h_rows, embedding)
    targets = np.repeat(chunk.targets.reshape(n_rows * length, -1), k, axis=0)
    valid = np.repeat(chunk.valid.reshape(-1), k)[:, None]
    tau = taus[level_index][:, None]
    residual = targets.astype(np.float64) - q
    count = max(int(chunk.valid.sum()), 1) * k * q.shape[1]
    loss = float(np.where(valid, residual * (tau - (residual < 0)), 0.0).sum()) / count
    # d/dq of ρ_τ(y − q) = 1[y < q] − τ.
    grad_q = np.where(valid, ((residual < 0) - tau) / count, 0.0).astype(np.float32)
    output_w, output_b = _weight_gradient(grad_q, layer)
    grad_layer = numerics.linear(grad_q, w.output_weight.T)
    grad_layer = np.where(layer > 0, grad_layer, np.float32(0))
    head_w, head_b = _weight_gradient(grad_layer, product)
    grad_product = numerics.linear(grad_layer, w.head_weight.T)
    grad_embedding = np.where(embedding_pre > 0, grad_product * h_rows, np.float32(0))
    embedding_w, embedding_b = _weight_gradient(grad_embedding, cosines[level_index])
    grad_h_rows = (grad_product * embedding).reshape(n_rows, length, k, hidden)
    grad_states = grad_h_rows[:, :, 0].copy()
    for j in range(1, k):
        grad_states += grad_h_rows[:, :, j]
    # Backpropagation through time.
    grad_gates_in = np.empty((n_rows, length, 3 * hidden), np.float32)
    grad_gates_hidden = np.empty((n_rows, length, 3 * hidden), np.float32)
    previous = np.empty((n_rows, length, hidden), np.float32)
    grad_h = zero
    hidden_weight_t = w.hidden_weight.T
    for t in reversed(range(length)):
        c = caches[t]
        grad_h = grad_h + grad_states[:, t]
        grad_new = grad_h * (_ONE - c.update)
        grad_update = grad_h * (c.previous - c.new)
        grad_new_pre = grad_new * (_ONE - c.new * c.new)
        grad_reset = grad_new_pre * c.hidden_new_part
        grad_reset_pre = grad_reset * c.reset * (_ONE - c.reset)
        grad_update_pre = grad_update * c.update * (_ONE - c.update)
        grad_gates_in[:, t] = np.concatenate([grad_reset_pre, grad_update_pre, grad_new_pre], 1)
        grad_gates_hidden[:, t] = np.concatenate(
            [grad_reset_pre, grad_update_pre, grad_new_pre * c.reset], 1
        )
        previous[:, t] = c.previous
        grad_previous = grad_h * c.update + numerics.linear(
            grad_gates_hidden[:, t], hidden_weight_t
        )
        grad_h = np.where(chunk.starts[:, t, None], zero, grad_previous)
    flat = n_rows * length
    input_w, input_b = _weight_gradient(
        grad_gates_in.reshape(flat, -1), chunk.inputs.reshape(flat, -1)
    )
    hidden_w, hidden_b = _weight_gradient(
        grad_gates_hidden.reshape(flat, -1), previous.reshape(flat, -1)
    )
    grads = RiqnWeights(input_w, input_b, hidden_w, hidden_b, embedding_w, embedding_b,
                        head_w, head_b, output_w, output_b)  # fmt: skip
    return loss, grads, h


def mean_pinball(q: np.ndarray, targets: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """(n,) mean over levels and coordinates of ρ_τ(y − q), q (n, K, d) float32, targets (n, d)
    float64, summed level by level and coordinate by coordinate in index order."""
    residual = targets[:, None, :] - q
    loss = residual * (taus[None, :, None] - (residual < 0))
    per_level = loss[:, 0].copy()
    for k in range(1, loss.shape[1]):
        per_level += loss[:, k]
    total = per_level[:, 0].copy()
    for i in range(1, per_level.shape[1]):
        total += per_level[:, i]
    return total / (loss.shape[1] * loss.shape[2])


@detector_parameters
class Riqn(BaseDetector):
    """Quantile-weighted next-state prediction error of a recurrent implicit quantile network.

    Parameters
    ----------
    hidden_size : int >= 1, default 32
        Width of the GRU's hidden state, of the τ embedding and of the head's hidden layer.
    n_cos : int >= 1, default 16
        Cosine features cos(π j τ), j = 0..n_cos − 1, of a quantile level τ.
    n_quantiles : int >= 1, default 4
        Quantile levels drawn per step while training.
    epochs : int >= 1, default 10
        Passes over the fit streams.
    chunk_length : int >= 1, default 20
        Steps per truncated-backpropagation chunk (one Adam step each).
    lr : float > 0, default 1e-2
        Adam's learning rate.
    """

    name: ClassVar[str] = "riqn"

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "hidden_size": [Interval(int, 1, None)],
        "n_cos": [Interval(int, 1, None)],
        "n_quantiles": [Interval(int, 1, None)],
        "epochs": [Interval(int, 1, None)],
        "chunk_length": [Interval(int, 1, None)],
        "lr": [Interval(float, 0, None, closed="neither")],
    }

    hidden_size: int = 32
    n_cos: int = 16
    n_quantiles: int = 4
    epochs: int = 10
    chunk_length: int = 20
    lr: float = 1e-2

    @property
    def latency(self) -> int:
        # z_t compares the observed s_{t+1} with the predicted quantiles.
        return 1

    # -- data ----------------------------------------------------------------------------
    def _inputs(self, trajectory: Trajectory) -> np.ndarray:
        x = trajectory_features(trajectory, "state_action", self.action_encoding_)
        return self.input_standardizer_.transform(x).astype(np.float32)

    def _targets(self, trajectory: Trajectory) -> np.ndarray:
        return self.target_standardizer_.transform(increments(trajectory))

    @staticmethod
    def _starts(trajectory: Trajectory) -> np.ndarray:
        starts = np.zeros(trajectory.T, dtype=bool)
        starts[0] = True
        starts[1:] = trajectory.dones[:-1]
        return starts

    @staticmethod
    def _side_by_side(arrays: list[np.ndarray], fill: float | bool) -> np.ndarray:
        """Per-stream arrays (T_i, ...) padded to the longest: (B, T_max, ...)."""
        longest = max(len(a) for a in arrays)
        out = np.full((len(arrays), longest, *arrays[0].shape[1:]), fill, arrays[0].dtype)
        for row, a in enumerate(arrays):
            out[row, : len(a)] = a
        return out

    # -- fit -----------------------------------------------------------------------------
    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        self.action_encoding_ = ActionEncoding.fit(trajectories)
        inputs = [trajectory_features(t, "state_action", self.action_encoding_)
                  for t in trajectories]  # fmt: skip
        self.input_standardizer_ = Standardizer.fit(np.concatenate(inputs))
        self.target_standardizer_ = Standardizer.fit(
            np.concatenate([increments(t) for t in trajectories])
        )
        rng = np.random.default_rng(self.seed)
        x = self._side_by_side([self._inputs(t) for t in trajectories], 0.0)
        y = self._side_by_side([self._targets(t).astype(np.float32) for t in trajectories], 0.0)
        starts = self._side_by_side([self._starts(t) for t in trajectories], True)
        valid = self._side_by_side([np.ones(t.T, bool) for t in trajectories], False)
        weights = RiqnWeights.initial(x.shape[2], self.hidden_size, self.n_cos, y.shape[2], rng)
        params = weights.arrays()
        optimiser = Adam(params, self.lr)
        cosines = cosine_features(TRAINING_LEVELS, self.n_cos)
        taus = np.array([float(tau) for tau in TRAINING_LEVELS])
        self.training_losses_ = []
        for _ in range(self.epochs):
            h = np.zeros((len(trajectories), self.hidden_size), np.float32)
            losses = []
            for first in range(0, x.shape[1], self.chunk_length):
                steps = slice(first, first + self.chunk_length)
                shape = (*valid[:, steps].shape, self.n_quantiles)
                chunk = Chunk(x[:, steps], y[:, steps], starts[:, steps], valid[:, steps],
                              rng.integers(len(TRAINING_LEVELS), size=shape))  # fmt: skip
                loss, grads, h = chunk_gradients(RiqnWeights.of(params), chunk, h, cosines, taus)
                optimiser.step(params, grads.arrays())
                losses.append(loss)
            self.training_losses_.append(math.fsum(losses) / len(losses))
        self.weights_ = RiqnWeights.of(params)
        # φ(τ) of the score's levels, computed once (row-independent: as in a batch).
        self.score_embedding_ = embed(self.weights_, cosine_features(SCORE_LEVELS, self.n_cos))
        self.score_taus_ = np.array([float(tau) for tau in SCORE_LEVELS])

    # -- score ---------------------------------------------------------------------------
    def _step_scores(self, h: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """z of rows with hidden states h (n, H) and standardised increments (n, d_s)."""
        n, levels = len(h), len(self.score_taus_)
        h_rows = np.repeat(h, levels, axis=0)
        embedding = np.tile(self.score_embedding_, (n, 1))
        q = quantiles(self.weights_, h_rows, embedding)[-1].reshape(n, levels, -1)
        return mean_pinball(q, targets, self.score_taus_)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        w = self.weights_
        x = self._side_by_side([self._inputs(t) for t in trajectories], 0.0)
        starts = self._side_by_side([self._starts(t) for t in trajectories], True)
        n_rows, longest, _ = x.shape
        gates_in = numerics.linear(x.reshape(n_rows * longest, -1), w.input_weight,
                                   w.input_bias).reshape(n_rows, longest, -1)  # fmt: skip
        states = np.empty((n_rows, longest, self.hidden_size), np.float32)
        h = zero = np.zeros((n_rows, self.hidden_size), np.float32)
        for t in range(longest):
            h = np.where(starts[:, t, None], zero, h)
            h = gru_step(w, gates_in[:, t], h)[0]
            states[:, t] = h
        return [
            self._step_scores(states[row, : t.T], self._targets(t))
            for row, t in enumerate(trajectories)
        ]

    def stream(self) -> DetectorStream:
        return RiqnStream(self)


class RiqnStream(DetectorStream):
    """Carries the GRU's hidden state from step to step; restarts it after a `done`."""

    def __init__(self, detector: Riqn) -> None:
        super().__init__(detector)
        self._flush()

    def _flush(self) -> StepScores:
        self.h: np.ndarray | None = None
        return ()

    def _update(self, step: Trajectory, t: int) -> StepScores:
        detector, w = self.detector, self.detector.weights_
        if self.h is None:
            self.h = np.zeros((1, detector.hidden_size), np.float32)
        gates_in = numerics.linear(detector._inputs(step), w.input_weight, w.input_bias)
        self.h = gru_step(w, gates_in, self.h)[0]
        score = detector._step_scores(self.h, detector._targets(step))
        if step.dones[0]:
            self.h = None
        return self.scored(t, score)
