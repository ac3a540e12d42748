"""The batched collector: deployment streams of exactly T steps (SPEC §1, §3).

The streams of every requested set are dealt to a few jobs; a job steps its streams in lock
step, one batched policy call per step for all of them, and jobs are the unit of parallel work.
Each stream has its own environment, noise generator and fault, and a policy's rows never
influence each other, so a stream's bytes do not depend on which streams share its job, nor on
the number of workers (tests/envs/test_lockstep.py). Online faults hook into the live rollout
on labelled steps only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.injector import Fault
from oodrl.core.policy import Policy
from oodrl.core.trajectory import TrajectorySet
from oodrl.errors import PolicyError
from oodrl.parallel import ordered_map

#: The most streams one job steps in lock step, one policy call per step for all of them. It
#: fixes nothing in the results, only the speed (it was 16 and part of the protocol while it
#: fixed the policy's batch shapes): a policy's rows never influence each other (the `Policy`
#: protocol; the committed policies round every output, or certify every argmax, exactly, so a
#: row's answer is the same in any batch: `oodrl.numerics`), and each stream has its own
#: environment, noise generator and fault. A batch of 128 rows costs the policy a third of what
#: 16 did per row (LunarLander, CartPole); more gains a few per cent of a step while each job
#: holds more live environments (a MuJoCo one takes 1-2 MB).
BLOCK_SIZE = 128


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
class _Job:
    """Streams stepped together: a reset seed, a fault (or None) and labels (T,) per stream."""

    seeds: tuple[int, ...]
    faults: tuple[Fault | None, ...]
    labels: np.ndarray  # (n, T) bool
    #: Stop each stream when its first episode ends (the steps after it left zero): what
    #: impact calibration counts, without simulating the rest of the horizon.
    first_episode: bool = False


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


def _rollout(
    adapter: EnvironmentAdapter,
    policy: Policy,
    job: _Job,
    T: int,  # noqa: N803
    policy_seed: int,
) -> dict[str, np.ndarray]:
    """Roll out one job's streams in lock step, the policy batched across them.

    Per step, the policy's actions, the states and the episode indices are stored as one
    column each; each stream then steps its own environment (through its fault's hooks where
    labelled), and the column of next states it fills is the next observation, but for the
    streams whose episode ended (reset).
    """
    seeds, faults, labels = job.seeds, job.faults, job.labels
    n = len(seeds)
    running = [True] * n  # False once a stream's first episode ended, with `first_episode`
    envs = [adapter.make() for _ in range(n)]
    steps = [env.step for env in envs]
    handles = [adapter.handle(env) for env in envs]
    rngs = [noise_rng(policy_seed, s) for s in seeds]
    out = _step_arrays(adapter, n, T)
    states, next_states = out["states"], out["next_states"]
    actions, executed = out["actions"], out["executed_actions"]
    episodes = [0] * n
    obs = np.empty((n, adapter.state_dim), np.float32)
    for i, (env, seed) in enumerate(zip(envs, seeds, strict=True)):
        obs[i] = env.reset(seed=seed)[0]
    live = labels.any(axis=0)  # the steps where some stream's fault acts
    rewards: list = [0.0] * n
    dones: list = [False] * n
    for t in range(T):
        if not any(running):
            break
        commanded = _commanded(adapter, policy, obs, rngs)
        states[:, t] = obs
        actions[:, t] = commanded
        out["episode_index"][:, t] = episodes
        active = labels[:, t].tolist() if live[t] else None
        observed = next_states[:, t]
        faulted, reset = [], []
        for i in range(n):
            if not running[i]:
                dones[i], rewards[i] = False, 0.0
                continue
            fault = faults[i] if active is not None and active[i] else None
            if fault is None:
                nxt, rewards[i], terminated, truncated, _ = steps[i](commanded[i])
            else:
                action = fault.before_step(t, commanded[i], handles[i])
                nxt, rewards[i], terminated, truncated, _ = steps[i](action)
                nxt = fault.after_step(t, nxt, commanded[i], handles[i])
                faulted.append((i, action))
            observed[i] = nxt
            done = dones[i] = terminated or truncated
            if done and job.first_episode:
                running[i] = False
            elif done:
                episodes[i] += 1
                nxt = envs[i].reset(seed=episode_seed(seeds[i], episodes[i]))[0]
                if fault is not None:
                    nxt = fault.after_reset(t, nxt, handles[i])
                reset.append((i, nxt))
        # Recorded after every stream stepped, as the actions the environments were given.
        executed[:, t] = commanded
        for i, action in faulted:
            executed[i, t] = action
        out["rewards"][:, t] = rewards
        out["dones"][:, t] = dones
        obs[...] = observed
        for i, nxt in reset:
            obs[i] = nxt
    for env in envs:
        env.close()
    if job.first_episode:  # a stopped stream's steps after its first episode stay zero
        after = np.cumsum(out["dones"], axis=1) - out["dones"] > 0
        for key in ("states", "actions", "executed_actions", "next_states", "rewards"):
            out[key][after] = 0
    return out


@dataclass(frozen=True)
class Request:
    """One trajectory set to collect: a stream per seed; `faults[i]` acts on stream i where
    `labels` (labels None = a clean set)."""

    seeds: tuple[int, ...]
    labels: np.ndarray | None = None
    faults: tuple[Fault, ...] | None = None
    attrs: dict | None = None


def collect_many(
    adapter: EnvironmentAdapter,
    policy: Policy,
    requests: Sequence[Request],
    T: int,  # noqa: N803
    *,
    policy_seed: int = 0,
    workers: int = 1,
    progress: Callable[[int], None] | None = None,
    first_episode: bool = False,
) -> list[TrajectorySet]:
    """Collect several sets at once: their streams share the jobs and one pool of workers.

    `progress(n)` is called as each job of n streams is done (len of every request's seeds in
    all). `first_episode`: each stream stops when its first episode ends, its later steps left
    zero (`_Job.first_episode`)."""
    adapter.check_policy(policy)
    streams = []  # (request index, row in its set, seed, fault, labels)
    for index, request in enumerate(requests):
        if request.faults is not None and (
            request.labels is None or len(request.faults) != len(request.seeds)
        ):
            raise ValueError("faults need labels and one fault per seed.")
        labels = np.zeros(T, bool) if request.labels is None else np.asarray(request.labels, bool)
        faults = request.faults if request.faults is not None else (None,) * len(request.seeds)
        for row, (seed, fault) in enumerate(zip(request.seeds, faults, strict=True)):
            streams.append((index, row, int(seed), fault, labels))
    plan = _plan(len(streams), workers)
    jobs = [
        _Job(
            tuple(streams[k][2] for k in members),
            tuple(streams[k][3] for k in members),
            np.stack([streams[k][4] for k in members]),
            first_episode,
        )
        for members in plan
    ]

    def done(args: tuple) -> None:
        if progress:
            progress(len(args[2].seeds))

    parts = ordered_map(
        _rollout, [(adapter, policy, job, T, policy_seed) for job in jobs], workers, on_done=done
    )
    arrays = [_step_arrays(adapter, len(request.seeds), T) for request in requests]
    for members, part in zip(plan, parts, strict=True):
        for stream, k in enumerate(members):
            index, row = streams[k][:2]
            for key, values in part.items():
                arrays[index][key][row] = values[stream]
    sets = []
    for request, merged in zip(requests, arrays, strict=True):
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


def _plan(n_streams: int, workers: int) -> list[list[int]]:
    """The streams of each job: as few jobs as BLOCK_SIZE allows, a multiple of the workers
    (no core idles while another finishes a job), streams dealt in turn so that each job
    holds a share of every set (sets differ in cost: faults, episode resets)."""
    workers = max(1, min(workers, n_streams))
    n_jobs = math.ceil(max(1, math.ceil(n_streams / BLOCK_SIZE)) / workers) * workers
    n_jobs = min(n_jobs, n_streams)
    return [list(range(j, n_streams, n_jobs)) for j in range(n_jobs)]


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
    first_episode: bool = False,
) -> TrajectorySet:
    """Roll out one deployment stream per seed; `faults[i]` acts on stream i where `labels`;
    `first_episode`: each stream stops when its first episode ends (`collect_many`)."""
    request = Request(
        tuple(int(s) for s in seeds),
        labels,
        None if faults is None else tuple(faults),
        attrs,
    )
    return collect_many(
        adapter, policy, [request], T, policy_seed=policy_seed, workers=workers,
        progress=progress, first_episode=first_episode,
    )[0]  # fmt: skip
