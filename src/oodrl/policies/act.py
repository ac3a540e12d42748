"""Policies that act in numpy with machine-independent arithmetic (SPEC §14).

Collection calls ``act`` once per block step; every layer is correctly rounded
(:class:`oodrl.numerics.Affine`, :func:`oodrl.numerics.linear`'s bits), so the same weights and
observations give the same actions on every x86-64 machine, whatever kernel its BLAS picks (a
greedy ReLU argmax head gets the same actions faster: :class:`oodrl.numerics.ReluArgmax`).
Torch is needed only to read a checkpoint, never to act.

Architectures (the ``kind`` of a checkpoint's ``architecture`` mapping):

- ``mlp`` — Linear/ReLU layers ending in one Q-value (or logit) per action; acts by argmax.
- ``noisy_dqn`` — NoisyNet layers (mean weights ``*_mu``, noise scales ``*_sigma``); argmax of the
  mean network in ``greedy`` mode, of a per-row noise sample in ``noisy`` mode.
- ``tanh_actor`` — Linear/ReLU layers, then ``tanh`` rescaled to ``[action_low, action_high]``:
  the deterministic action of a SAC actor (continuous control).
- ``clipped_actor`` — layers ending in the action vector, clipped to ``[action_low,
  action_high]``: the deterministic action (the Gaussian's mean) of a PPO or A2C actor.

Two optional keys hold what converted Stable-Baselines3 policies need (SPEC §18):
``activation`` (``relu``, the default, or ``tanh``) between layers, and
``observation_normalization`` (``mean``, ``var``, ``epsilon``, ``clip``: VecNormalize's
statistics), applied to each observation first, in float64 as VecNormalize does.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from oodrl import numerics
from oodrl.errors import PolicyError

PolicyMode = Literal["greedy", "noisy"]
ARCHITECTURE_KINDS = ("noisy_dqn", "mlp", "tanh_actor", "clipped_actor")
ACTIVATIONS = {"relu": numerics.relu, "tanh": numerics.tanh}


@dataclass(frozen=True)
class Layer:
    """One affine layer in float32; ``weight_sigma``/``bias_sigma`` only for NoisyNet layers."""

    weight: np.ndarray
    bias: np.ndarray
    weight_sigma: np.ndarray | None = None
    bias_sigma: np.ndarray | None = None


class LayeredPolicy:
    """A feed-forward network acting on a batch of observations, one action per row."""

    action_kind: Literal["discrete", "continuous"]

    def __init__(
        self,
        layers: Sequence[Layer],
        *,
        kind: str,
        mode: PolicyMode = "greedy",
        sha256: str = "",
        activation: str = "relu",
        normalization: Mapping[str, Any] | None = None,
    ) -> None:
        self.layers = list(layers)
        self.kind = kind
        self.mode = mode
        self.sha256 = sha256
        self.activation = ACTIVATIONS[activation]
        self.normalization = normalization
        self.state_dim = int(self.layers[0].weight.shape[1])
        #: Discrete: the number of actions; continuous: the action vector's dimension.
        self.action_size = int(self.layers[-1].weight.shape[0])

    def outputs(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None = None
    ) -> np.ndarray:
        """The last layer's outputs (n, action_size) float32, before any argmax or squashing."""
        x = self._inputs(observations)
        noise = self._row_noise(rngs, len(x)) if self.mode == "noisy" else None
        last = len(self.layers) - 1
        for i, (layer, affine) in enumerate(zip(self.layers, self._affine, strict=True)):
            y = affine(x)
            if noise is not None:
                eps_in, eps_out = noise[i]
                y = y + eps_out * numerics.linear(x * eps_in, layer.weight_sigma, layer.bias_sigma)
            x = self.activation(y) if i < last else y
        return x

    @functools.cached_property
    def _affine(self) -> list[numerics.Affine]:
        """The layers' mean weights, prepared once for the many small batches of a rollout."""
        return [numerics.Affine(layer.weight, layer.bias) for layer in self.layers]

    def __getstate__(self) -> dict[str, Any]:
        """The policy without what `functools.cached_property` prepared: derived from the
        weights, it would only change the bytes of a pickle (a fitted detector) that holds it."""
        return {k: v for k, v in self.__dict__.items() if k not in _PREPARED}

    def _inputs(self, observations: np.ndarray) -> np.ndarray:
        """The network's input rows (n, state_dim) float32: the observations, normalised."""
        x = np.asarray(observations, dtype=np.float32).reshape(-1, self.state_dim)
        return x if self.normalization is None else self._normalized(x)

    def _normalized(self, x: np.ndarray) -> np.ndarray:
        """VecNormalize's ``clip((obs − mean) / √(var + ε), ±clip)``: elementwise float64 IEEE
        operations (exact, so machine-independent), then float32 as the network takes it."""
        stats = self.normalization
        mean, var = np.asarray(stats["mean"]), np.asarray(stats["var"])
        scaled = (x.astype(np.float64) - mean) / np.sqrt(var + float(stats["epsilon"]))
        clip = float(stats["clip"])
        return np.clip(scaled, -clip, clip).astype(np.float32)

    def _row_noise(
        self, rngs: Sequence[np.random.Generator] | None, n: int
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Factorised NoisyNet noise, one sample per row: row i draws from ``rngs[i]`` alone."""
        if rngs is None or len(rngs) != n:
            raise ValueError("noisy mode needs one numpy Generator per observation row")
        shapes = [layer.weight.shape[::-1] for layer in self.layers]  # (in, out) per layer
        total = sum(n_in + n_out for n_in, n_out in shapes)
        z = np.stack([rng.standard_normal(total, dtype=np.float32) for rng in rngs])
        eps = np.sign(z) * np.sqrt(np.abs(z))
        noise, start = [], 0
        for n_in, n_out in shapes:
            noise.append(
                (eps[:, start : start + n_in], eps[:, start + n_in : start + n_in + n_out])
            )
            start += n_in + n_out
        return noise


class ArgmaxPolicy(LayeredPolicy):
    """Acts by the argmax of its outputs: actions (n,) int64.

    Only the argmax is acted on and recorded, so a greedy ReLU network need not round every
    output exactly: `numerics.ReluArgmax` decides most rows in plain float64, and only the rows
    whose top two outputs lie within its error bound take the exact outputs (`exact_act`), with
    the same answer.
    """

    action_kind = "discrete"

    def act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None = None
    ) -> np.ndarray:
        if self._certified_argmax is None:
            return self.exact_act(observations, rngs)
        observations = np.asarray(observations, dtype=np.float32).reshape(-1, self.state_dim)
        actions, decided = self._certified_argmax(self._inputs(observations))
        undecided = ~decided
        if undecided.any():
            actions[undecided] = self.exact_act(observations[undecided])
        return actions

    def exact_act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None = None
    ) -> np.ndarray:
        """The argmax of the exactly rounded outputs: `act`'s answer, computed the slow way."""
        return self.outputs(observations, rngs).argmax(axis=1).astype(np.int64)

    @functools.cached_property
    def _certified_argmax(self) -> numerics.ReluArgmax | None:
        """The float64 network with its error bound; None where its analysis does not apply
        (NoisyNet noise in `noisy` mode, tanh activations)."""
        if self.mode == "noisy" or self.activation is not numerics.relu:
            return None
        return numerics.ReluArgmax(self._affine)


#: The attributes `LayeredPolicy.__getstate__` leaves out.
_PREPARED = ("_affine", "_certified_argmax")


class TanhActorPolicy(LayeredPolicy):
    """``low + (tanh(outputs) + 1) / 2 · (high − low)``: actions (n, d_a) float32."""

    action_kind = "continuous"

    def __init__(
        self, layers: Sequence[Layer], *, low: np.ndarray, high: np.ndarray, **kwargs: Any
    ) -> None:
        super().__init__(layers, **kwargs)
        self.low = np.asarray(low, dtype=np.float32)
        self.high = np.asarray(high, dtype=np.float32)

    def act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None = None
    ) -> np.ndarray:
        squashed = numerics.tanh(self.outputs(observations))
        # The same expression as Stable-Baselines3's unscale_action, in float32.
        return self.low + (np.float32(0.5) * (squashed + np.float32(1.0))) * (self.high - self.low)


class ClippedActorPolicy(TanhActorPolicy):
    """``clip(outputs, low, high)``: actions (n, d_a) float32 (SB3's clipping of a PPO action)."""

    def act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None = None
    ) -> np.ndarray:
        return np.clip(self.outputs(observations), self.low, self.high)


def policy_from_checkpoint(
    architecture: Mapping[str, Any],
    state_dict: Mapping[str, Any],
    mode: PolicyMode = "greedy",
    sha256: str = "",
) -> LayeredPolicy:
    """The numpy policy for a checkpoint's ``architecture`` and (torch or numpy) weights."""
    kind = architecture.get("kind")
    if kind not in ARCHITECTURE_KINDS:
        raise PolicyError(f"unknown architecture kind {kind!r}; known: {list(ARCHITECTURE_KINDS)}")
    if mode not in ("greedy", "noisy"):
        raise PolicyError(f"policy mode must be 'greedy' or 'noisy'; got {mode!r}")
    if mode == "noisy" and kind != "noisy_dqn":
        raise PolicyError(f"mode 'noisy' needs a noisy_dqn network, not {kind!r}")
    activation = architecture.get("activation", "relu")
    if activation not in ACTIVATIONS:
        raise PolicyError(f"unknown activation {activation!r}; known: {list(ACTIVATIONS)}")
    common = {
        "kind": kind,
        "mode": mode,
        "sha256": sha256,
        "activation": activation,
        "normalization": architecture.get("observation_normalization"),
    }
    arrays = {k: np.asarray(_numpy(v), dtype=np.float32) for k, v in state_dict.items()}
    layers = _noisy_layers(arrays) if kind == "noisy_dqn" else _plain_layers(arrays)
    for before, after in zip(layers[:-1], layers[1:], strict=True):
        if before.weight.shape[0] != after.weight.shape[1]:
            raise PolicyError(
                f"weights do not chain: a layer gives {before.weight.shape[0]} outputs, the next "
                f"takes {after.weight.shape[1]} inputs"
            )
    hidden = [int(layer.weight.shape[0]) for layer in layers[:-1]]
    declared = architecture.get("hidden_sizes")
    if declared is not None and [int(h) for h in declared] != hidden:
        raise PolicyError(
            f"weights do not fit architecture {dict(architecture)} (their hidden sizes: {hidden})"
        )
    if kind in ("tanh_actor", "clipped_actor"):
        actor = TanhActorPolicy if kind == "tanh_actor" else ClippedActorPolicy
        low, high = architecture["action_low"], architecture["action_high"]
        return actor(layers, low=low, high=high, **common)
    return ArgmaxPolicy(layers, **common)


def _numpy(value: Any) -> np.ndarray:
    return value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)


def _plain_layers(arrays: Mapping[str, np.ndarray]) -> list[Layer]:
    """Layers from ``<prefix>.weight``/``<prefix>.bias`` pairs, in state_dict order."""
    prefixes = [k[: -len(".weight")] for k, v in arrays.items() if k.endswith(".weight")]
    if not prefixes:
        raise PolicyError("no weight matrices in the state_dict")
    try:
        return [Layer(arrays[f"{p}.weight"], arrays[f"{p}.bias"]) for p in prefixes]
    except KeyError as missing:
        raise PolicyError(f"state_dict has no bias {missing} for a weight matrix") from None


def _noisy_layers(arrays: Mapping[str, np.ndarray]) -> list[Layer]:
    prefixes = [k[: -len(".weight_mu")] for k in arrays if k.endswith(".weight_mu")]
    if not prefixes:
        raise PolicyError("a noisy_dqn state_dict needs '*.weight_mu' entries")
    try:
        return [
            Layer(
                arrays[f"{p}.weight_mu"],
                arrays[f"{p}.bias_mu"],
                arrays[f"{p}.weight_sigma"],
                arrays[f"{p}.bias_sigma"],
            )
            for p in prefixes
        ]
    except KeyError as missing:
        raise PolicyError(f"noisy_dqn state_dict lacks {missing}") from None
