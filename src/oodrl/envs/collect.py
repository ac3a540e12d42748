"""The batched collector: deployment streams of exactly T steps (SPEC §1, §3).

Streams run in fixed blocks; within a block the policy's forward pass is batched across the
block's environments. Blocks are the unit of parallel work, so results do not depend on the
number of workers. Online faults hook into the live rollout on labelled steps only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from oodrl.core.injector import Fault
from oodrl.core.policy import Policy
from oodrl.core.trajectory import TrajectorySet

#: Streams per block; part of the protocol (it fixes the policy's batch shapes).
BLOCK_SIZE = 16


def episode_seed(stream_seed: int, episode: int) -> int:
    """Reset seed of the `episode`-th episode of a stream: the stream seed first, then derived.

    Derived seeds never collide with the next stream's seed (seed + i + 1), unlike seed + k.
    """
    if episode == 0:
        return int(stream_seed)
    return int(np.random.SeedSequence([int(stream_seed), episode]).generate_state(1)[0])


def noise_rng(policy_seed: int, stream_seed: int) -> np.random.Generator:
    """The policy-noise generator of one stream (used by `noisy` mode policies)."""
    return np.random.default_rng([int(policy_seed), int(stream_seed)])


@dataclass(frozen=True)
class _Block:
    seeds: tuple[int, ...]
    faults: tuple[Fault | None, ...]


def _rollout_block(adapter, policy: Policy, block: _Block, T: int, labels, policy_seed: int):  # noqa: N803
    n, d = len(block.seeds), adapter.state_dim
    envs = [adapter.make() for _ in range(n)]
    handles = [adapter.handle(env) for env in envs]
    rngs = [noise_rng(policy_seed, s) for s in block.seeds]
    out = {
        "states": np.zeros((n, T, d), np.float32),
        "actions": np.zeros((n, T), np.int64),
        "executed_actions": np.zeros((n, T), np.int64),
        "rewards": np.zeros((n, T), np.float32),
        "next_states": np.zeros((n, T, d), np.float32),
        "dones": np.zeros((n, T), bool),
        "episode_index": np.zeros((n, T), np.int32),
    }
    episodes = [0] * n
    obs = np.stack([env.reset(seed=s)[0] for env, s in zip(envs, block.seeds, strict=True)])
    for t in range(T):
        commanded = np.asarray(policy.act(obs, rngs), dtype=np.int64)
        out["states"][:, t] = obs
        out["actions"][:, t] = commanded
        out["episode_index"][:, t] = episodes
        for i, env in enumerate(envs):
            fault = block.faults[i] if labels[t] else None
            action = commanded[i] if fault is None else fault.executed_action(t, commanded[i])
            nxt, reward, terminated, truncated, _ = env.step(action)
            if fault is not None:
                nxt = fault.after_step(t, obs[i], nxt, commanded[i], handles[i])
            done = terminated or truncated
            out["executed_actions"][i, t] = action
            out["rewards"][i, t] = reward
            out["next_states"][i, t] = nxt
            out["dones"][i, t] = done
            if done:
                episodes[i] += 1
                nxt = env.reset(seed=episode_seed(block.seeds[i], episodes[i]))[0]
            obs[i] = nxt
    for env in envs:
        env.close()
    return out


def collect(
    adapter,
    policy: Policy,
    seeds: Sequence[int],
    T: int,  # noqa: N803
    *,
    policy_seed: int = 0,
    labels: np.ndarray | None = None,
    faults: Sequence[Fault] | None = None,
    workers: int = 1,
    attrs: dict | None = None,
    progress: Callable[[int], None] | None = None,
) -> TrajectorySet:
    """Roll out one deployment stream per seed; `faults[i]` acts on stream i where `labels`."""
    seeds = [int(s) for s in seeds]
    if faults is not None and (labels is None or len(faults) != len(seeds)):
        raise ValueError("faults need labels and one fault per seed.")
    step_labels = np.zeros(T, bool) if labels is None else np.asarray(labels, bool)
    stream_faults = list(faults) if faults is not None else [None] * len(seeds)
    blocks = [
        _Block(tuple(seeds[i : i + BLOCK_SIZE]), tuple(stream_faults[i : i + BLOCK_SIZE]))
        for i in range(0, len(seeds), BLOCK_SIZE)
    ]
    args = (T, step_labels, policy_seed)
    if workers > 1 and len(blocks) > 1:
        import multiprocessing

        context = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(min(workers, len(blocks)), mp_context=context) as pool:
            futures = [pool.submit(_rollout_block, adapter, policy, b, *args) for b in blocks]
            parts = []
            for block, future in zip(blocks, futures, strict=True):
                parts.append(future.result())
                if progress:
                    progress(len(block.seeds))
    else:
        parts = []
        for block in blocks:
            parts.append(_rollout_block(adapter, policy, block, *args))
            if progress:
                progress(len(block.seeds))
    merged = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    return TrajectorySet(
        **merged,
        seeds=np.array(seeds, dtype=np.int64),
        labels=None if labels is None else np.tile(step_labels, (len(seeds), 1)),
        attrs=dict(attrs or {}),
    )
