"""Evaluate a policy on whole episodes (the policy bars of SPEC §2 and §11)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def evaluate_policy(
    policy: Any,
    episodes: int,
    seed: int,
    env_id: str = "LunarLander-v3",
    rngs: Sequence[np.random.Generator] | None = None,
) -> np.ndarray:
    """Undiscounted returns (episodes,) float64 of full episodes seeded seed..seed+episodes-1.

    The episodes run side by side, one environment each, with one batched ``act`` per step.
    In ``noisy`` mode episode ``i`` draws its noise from ``rngs[i]``; by default from
    ``np.random.default_rng(seed + i)``.
    """
    from oodrl.envs import make

    if policy.mode == "noisy" and rngs is None:
        rngs = [np.random.default_rng(seed + i) for i in range(episodes)]
    if rngs is not None and len(rngs) != episodes:
        raise ValueError(f"need one generator per episode ({episodes}); got {len(rngs)}")
    envs = [make(env_id) for _ in range(episodes)]
    try:
        obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)]).astype(
            np.float32
        )
        returns = np.zeros(episodes)
        active = np.ones(episodes, dtype=bool)
        while active.any():
            rows = np.flatnonzero(active)
            actions = policy.act(obs[rows], None if rngs is None else [rngs[i] for i in rows])
            for i, action in zip(rows, actions, strict=True):
                step_action = int(action) if policy.action_kind == "discrete" else action
                next_obs, reward, terminated, truncated, _ = envs[i].step(step_action)
                returns[i] += float(reward)
                obs[i] = next_obs
                active[i] = not (terminated or truncated)
    finally:
        for env in envs:
            env.close()
    return returns
