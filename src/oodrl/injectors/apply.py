"""Stage-facing helpers: perturb a clean set post hoc, or re-collect it with online faults."""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Callable, Sequence

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter
from oodrl.core.injector import BaseAnomalyInjector, OnlineInjector, PostHocInjector
from oodrl.core.policy import Policy
from oodrl.core.spec import AnomalySpec
from oodrl.core.trajectory import TrajectorySet
from oodrl.envs.collect import Request, collect_many
from oodrl.errors import ContractError


def injector_rng(seed: int, injector: str, episode: int) -> np.random.Generator:
    """SPEC §3: the generator of one injector on one episode, seeded by (seed, name, episode).

    The name enters through its CRC-32, which (unlike `hash()`) is the same in every process.
    """
    return np.random.default_rng([int(seed), zlib.crc32(injector.encode()), int(episode)])


def _check_spec(injector: BaseAnomalyInjector, spec: AnomalySpec) -> None:
    if spec.name != injector.injector_name or spec.mode != injector.mode:
        raise ContractError(
            f"AnomalySpec ({spec.name!r}, mode {spec.mode!r}) does not describe injector "
            f"{injector.injector_name!r} (mode {injector.mode!r}); build it with injector.spec()."
        )


def perturb_posthoc(
    injector: PostHocInjector, clean: TrajectorySet, spec: AnomalySpec, seed: int
) -> TrajectorySet:
    """A perturbed copy of every clean trajectory, with labels and the spec in its attributes.

    Episode j draws from `injector_rng(seed, name, j)`, so the result does not depend on which
    other episodes are perturbed alongside it.
    """
    _check_spec(injector, spec)
    states, next_states, labels = [], [], []
    for j in range(len(clean)):
        rng = injector_rng(seed, injector.injector_name, j)
        perturbed, y = injector.inject(clean.trajectory(j), spec, rng)
        states.append(perturbed.states)
        next_states.append(perturbed.next_states)
        labels.append(y)
    return dataclasses.replace(
        clean,
        states=np.stack(states),
        next_states=np.stack(next_states),
        labels=np.stack(labels),
        attrs={**clean.attrs, "mode": spec.mode, "onset": spec.onset, "spec": spec.to_dict()},
    )


def collect_online(
    injector: OnlineInjector,
    adapter: EnvironmentAdapter,
    policy: Policy,
    seeds: Sequence[int],
    T: int,  # noqa: N803 - T is the protocol's name for the horizon
    spec: AnomalySpec,
    seed: int,
    policy_seed: int,
    workers: int = 1,
) -> TrajectorySet:
    """Re-run the clean streams' seeds with a fresh fault per stream, active where labelled.

    Stream j's fault draws from `injector_rng(seed, name, j)`; with the same `policy_seed` the
    steps before the onset reproduce the matched clean streams exactly.
    """
    return collect_online_sets(
        injector, adapter, policy, seeds, T, [spec], seed, policy_seed, workers
    )[0]


def collect_online_sets(
    injector: OnlineInjector,
    adapter: EnvironmentAdapter,
    policy: Policy,
    seeds: Sequence[int],
    T: int,  # noqa: N803
    specs: Sequence[AnomalySpec],
    seed: int,
    policy_seed: int,
    workers: int = 1,
    progress: Callable[[int], None] | None = None,
    first_episode: bool = False,
) -> list[TrajectorySet]:
    """`collect_online` for several specs (a severity sweep) sharing one pool of workers.

    `progress(n)` is called as each job of n streams is done: len(seeds) · len(specs) in all.
    `first_episode`: each stream stops when its first episode ends (`oodrl.envs.collect`).
    """
    injector.check_adapter(adapter)
    requests = []
    for spec in specs:
        _check_spec(injector, spec)
        faults = tuple(
            injector.fault(spec, injector_rng(seed, injector.injector_name, j))
            for j in range(len(seeds))
        )
        attrs = {
            "T": T,
            "env_id": adapter.env_id,
            "mode": spec.mode,
            "onset": spec.onset,
            "policy_sha256": policy.sha256,
            "spec": spec.to_dict(),
        }
        requests.append(Request(tuple(int(s) for s in seeds), spec.labels(T), faults, attrs))
    return collect_many(
        adapter, policy, requests, T, policy_seed=policy_seed, workers=workers,
        progress=progress, first_episode=first_episode,
    )  # fmt: skip
