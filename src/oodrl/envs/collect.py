"""The batched collector: deployment streams of exactly T steps (SPEC §1, §3).

Streams run in fixed blocks; within a block the policy's forward pass is batched across the
block's environments. Blocks are the unit of parallel work, so results do not depend on the
number of workers. Online faults hook into the live rollout on labelled steps only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.injector import Fault
from oodrl.core.policy import Policy
from oodrl.core.trajectory import TrajectorySet
from oodrl.errors import PolicyError
from oodrl.parallel import ordered_map

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


def _step_arrays(adapter: EnvironmentAdapter, n: int, T: int) -> dict[str, np.ndarray]:  # noqa: N803
    """Zeroed per-step arrays of n streams; actions as SPEC §1 stores them for the action kind."""
    d = adapter.state_dim
    action_shape = (n, T, *adapter.action_shape)
    return {
        "states": np.zeros((n, T, d), np.float32),
        "actions": np.zeros(action_shape, adapter.action_dtype),
        "executed_actions": np.zeros(action_shape, adapter.action_dtype),
        "rewards": np.zeros((n, T), np.float32),
        "next_states": np.zeros((n, T, d), np.float32),
        "dones": np.zeros((n, T), bool),
        "episode_index": np.zeros((n, T), np.int32),
    }


def _commanded(
    adapter: EnvironmentAdapter,
    policy: Policy,
    obs: np.ndarray,
    rngs: list[np.random.Generator],
) -> np.ndarray:
    """The policy's actions for a block, refused unless shaped as the action space needs."""
    commanded = np.asarray(policy.act(obs, rngs))
    expected = (len(obs), *adapter.action_shape)
    if commanded.shape != expected:
        raise PolicyError(
            f"The policy returned actions of shape {commanded.shape} for {len(obs)} observations; "
            f"{adapter.env_id} has {adapter.describe_actions()}, so expected {expected}."
        )
    # Casting, never rounding: discrete policies return integers already (SPEC §1).
    return commanded.astype(adapter.action_dtype, copy=False)


def _rollout_block(
    adapter: EnvironmentAdapter,
    policy: Policy,
    block: _Block,
    T: int,  # noqa: N803
    labels: np.ndarray,
    policy_seed: int,
) -> dict[str, np.ndarray]:
    """Roll out one block of streams in lock step, the policy batched across them."""
    n = len(block.seeds)
    envs = [adapter.make() for _ in range(n)]
    handles = [adapter.handle(env) for env in envs]
    rngs = [noise_rng(policy_seed, s) for s in block.seeds]
    out = _step_arrays(adapter, n, T)
    episodes = [0] * n
    obs = np.stack([env.reset(seed=s)[0] for env, s in zip(envs, block.seeds, strict=True)])
    obs = obs.astype(np.float32, copy=False)
    for t in range(T):
        commanded = _commanded(adapter, policy, obs, rngs)
        out["states"][:, t] = obs
        out["actions"][:, t] = commanded
        out["episode_index"][:, t] = episodes
        for i, env in enumerate(envs):
            fault = block.faults[i] if labels[t] else None
            action = commanded[i]
            if fault is not None:
                action = fault.before_step(t, action, handles[i])
            nxt, reward, terminated, truncated, _ = env.step(action)
            if fault is not None:
                nxt = fault.after_step(t, nxt, commanded[i], handles[i])
            done = terminated or truncated
            out["executed_actions"][i, t] = action
            out["rewards"][i, t] = reward
            out["next_states"][i, t] = nxt
            out["dones"][i, t] = done
            if done:
                episodes[i] += 1
                nxt = env.reset(seed=episode_seed(block.seeds[i], episodes[i]))[0]
                if fault is not None:
                    nxt = fault.after_reset(t, nxt, handles[i])
            obs[i] = nxt
    for env in envs:
        env.close()
    return out


@dataclass(frozen=True)
class Request:
    """One trajectory set to collect: a stream per seed; `faults[i]` acts on stream i where
    `labels` (labels None = a clean set)."""

    seeds: tuple[int, ...]
    labels: np.ndarray | None = None
    faults: tuple[Fault, ...] | None = None
    attrs: dict | None = None

    def blocks(self) -> list[_Block]:
        faults = self.faults if self.faults is not None else (None,) * len(self.seeds)
        return [
            _Block(self.seeds[i : i + BLOCK_SIZE], faults[i : i + BLOCK_SIZE])
            for i in range(0, len(self.seeds), BLOCK_SIZE)
        ]


def collect_many(
    adapter: EnvironmentAdapter,
    policy: Policy,
    requests: Sequence[Request],
    T: int,  # noqa: N803
    *,
    policy_seed: int = 0,
    workers: int = 1,
    progress: Callable[[int], None] | None = None,
) -> list[TrajectorySet]:
    """Collect several sets at once: all their blocks share one pool of worker processes."""
    adapter.check_policy(policy)
    jobs = []
    for index, request in enumerate(requests):
        if request.faults is not None and (
            request.labels is None or len(request.faults) != len(request.seeds)
        ):
            raise ValueError("faults need labels and one fault per seed.")
        labels = np.zeros(T, bool) if request.labels is None else np.asarray(request.labels, bool)
        jobs.extend((index, block, labels) for block in request.blocks())
    parts = _run_blocks(adapter, policy, jobs, T, policy_seed, workers, progress)
    sets = []
    for index, request in enumerate(requests):
        mine = [part for (owner, _, _), part in zip(jobs, parts, strict=True) if owner == index]
        merged = {key: np.concatenate([p[key] for p in mine]) for key in mine[0]}
        labels = None
        if request.labels is not None:
            labels = np.tile(np.asarray(request.labels, bool), (len(request.seeds), 1))
        sets.append(
            TrajectorySet(
                **merged,
                seeds=np.array(request.seeds, dtype=np.int64),
                labels=labels,
                attrs=dict(request.attrs or {}),
            )
        )
    return sets


def _run_blocks(
    adapter: EnvironmentAdapter,
    policy: Policy,
    jobs: list[tuple[int, _Block, np.ndarray]],
    T: int,  # noqa: N803
    policy_seed: int,
    workers: int,
    progress: Callable[[int], None] | None,
) -> list[dict[str, np.ndarray]]:
    def done(job: tuple) -> None:
        if progress:
            progress(len(job[2].seeds))

    blocks = [(adapter, policy, block, T, labels, policy_seed) for _, block, labels in jobs]
    return ordered_map(_rollout_block, blocks, workers, on_done=done)


def collect(
    adapter: EnvironmentAdapter,
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
    request = Request(
        tuple(int(s) for s in seeds),
        labels,
        None if faults is None else tuple(faults),
        attrs,
    )
    return collect_many(
        adapter, policy, [request], T, policy_seed=policy_seed, workers=workers, progress=progress
    )[0]
