"""Torch-free policies that drive real simulators in tests (never trained, never committed)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter


class HeuristicPolicy:
    """gymnasium's hand-written LunarLander controller: lands most episodes, like a trained
    policy would, so streams hold landings, crashes and resets."""

    state_dim = 8
    action_kind = "discrete"
    action_size = 4
    sha256 = "heuristic"
    mode = "greedy"

    def act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None = None
    ) -> np.ndarray:
        from gymnasium.envs.box2d.lunar_lander import heuristic

        return np.array([heuristic(_DISCRETE_ENV, o) for o in observations], dtype=np.int64)


class _DiscreteEnv:
    """Stands in for the env in gymnasium's heuristic(), which only asks `continuous`."""

    continuous = False

    @property
    def unwrapped(self):
        return self


_DISCRETE_ENV = _DiscreteEnv()


class LinearPolicy:
    """A fixed random linear policy of the environment's spaces, with seeded action noise.

    Discrete: argmax of W·s + b + noise·Gumbel; continuous: tanh(W·s + b + noise·N(0, 1))
    rescaled to the action bounds. The noise comes from the collector's per-stream generators
    (one draw per step whatever happens), so a faulty re-run repeats the clean run's actions
    until the fault changes a state; without it a random linear policy on LunarLander commands
    nearly one action throughout, and holding it would change nothing.
    """

    def __init__(self, adapter: EnvironmentAdapter, seed: int = 0, noise: float = 1.0) -> None:
        rng = np.random.default_rng(seed)
        self.state_dim, self.action_size = adapter.state_dim, adapter.action_size
        self.action_kind = adapter.action_kind
        self.weight = rng.standard_normal((self.action_size, self.state_dim)) / np.sqrt(
            self.state_dim
        )
        self.bias = 0.1 * rng.standard_normal(self.action_size)
        self.noise = noise
        self.mode = "noisy" if noise else "greedy"
        self.sha256 = f"linear-{adapter.env_id}-{seed}-{noise}"
        if self.action_kind == "continuous":
            self.low, self.high = adapter.action_low, adapter.action_high

    def act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None = None
    ) -> np.ndarray:
        x = np.asarray(observations, dtype=np.float64).reshape(-1, self.state_dim)
        z = x @ self.weight.T + self.bias
        if self.noise:
            z = z + self.noise * self._draws(rngs, len(x))
        if self.action_kind == "discrete":
            return z.argmax(axis=1).astype(np.int64)
        unit = (np.tanh(z) + 1.0) / 2.0
        return (self.low + unit * (self.high - self.low)).astype(np.float32)

    def _draws(self, rngs: Sequence[np.random.Generator] | None, n: int) -> np.ndarray:
        if rngs is None or len(rngs) != n:
            raise ValueError("a noisy LinearPolicy needs one Generator per observation row")
        if self.action_kind == "discrete":
            return np.stack([rng.gumbel(size=self.action_size) for rng in rngs])
        return np.stack([rng.standard_normal(self.action_size) for rng in rngs])
