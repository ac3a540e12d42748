"""Lock step changes nothing: a stream collected beside others is the stream collected alone.

The collector steps many streams together with one policy call per step (`BLOCK_SIZE` streams
at most); that is a speed-up only if a stream's bytes do not depend on the streams beside it,
nor on how they are grouped into jobs. Checked on every environment of the suite with its
committed policy, clean and with a live fault, and with NoisyNet noise where the policy has it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import Request, collect, collect_many
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import injector_rng
from oodrl.policies.load import load_policy
from oodrl.suite.environments import PIPELINE_DIRS, policy_path

ROOT = Path(__file__).resolve().parents[2]
FIELDS = ("states", "actions", "executed_actions", "rewards", "next_states", "dones")
FIELDS += ("episode_index", "seeds", "labels")
SEEDS, T, ONSET, POLICY_SEED = (7, 8, 9), 40, 10, 3
FAULT = "dynamics_scaling"  # reads and writes the simulator's state on every labelled step


def _faults(adapter, count: int) -> tuple:
    """Stream j's fault, made afresh (faults keep state), from its own generator."""
    injector = INJECTORS.get(FAULT)()
    injector.check_adapter(adapter)
    spec = injector.spec(0.8, ONSET)
    return tuple(injector.fault(spec, injector_rng(0, FAULT, j)) for j in range(count))


def _labels() -> np.ndarray:
    labels = np.zeros(T, bool)
    labels[ONSET:] = True
    return labels


def _assert_same(together, alone, row: int) -> None:
    for field in FIELDS:
        a, b = getattr(together, field), getattr(alone, field)
        if a is None or b is None:
            assert a is None and b is None, field
            continue
        assert a.dtype == b.dtype, field
        assert a[row].tobytes() == b[0].tobytes(), f"{field}, stream {row}"


def _modes(env_id: str) -> list[str]:
    policy = load_policy(policy_path(env_id, ROOT))
    return ["greedy", "noisy"] if policy.kind == "noisy_dqn" else ["greedy"]


@pytest.mark.parametrize(
    ("env_id", "mode"), [(env_id, mode) for env_id in PIPELINE_DIRS for mode in _modes(env_id)]
)
def test_a_stream_in_lock_step_is_the_stream_alone(env_id, mode):
    adapter = ENVIRONMENTS.get(env_id)()
    policy = load_policy(policy_path(env_id, ROOT), mode=mode)
    labels = _labels()
    clean, faulty = collect_many(
        adapter,
        policy,
        [Request(SEEDS), Request(SEEDS, labels, _faults(adapter, len(SEEDS)))],
        T,
        policy_seed=POLICY_SEED,
    )
    assert faulty.labels is not None and not np.array_equal(clean.states, faulty.states)
    faults = _faults(adapter, len(SEEDS))
    for row, seed in enumerate(SEEDS):
        alone = collect(adapter, policy, [seed], T, policy_seed=POLICY_SEED)
        _assert_same(clean, alone, row)
        alone = collect(
            adapter, policy, [seed], T, policy_seed=POLICY_SEED, labels=labels,
            faults=[faults[row]],
        )  # fmt: skip
        _assert_same(faulty, alone, row)


def test_two_workers_collect_what_one_does_with_jobs_of_mixed_sets():
    env_id = "CartPole-v1"
    adapter = ENVIRONMENTS.get(env_id)()
    policy = load_policy(policy_path(env_id, ROOT), mode="noisy")

    def sets(workers: int) -> list:
        requests = [Request(SEEDS), Request(SEEDS, _labels(), _faults(adapter, len(SEEDS)))]
        return collect_many(adapter, policy, requests, T, policy_seed=POLICY_SEED, workers=workers)

    for one, two in zip(sets(1), sets(2), strict=True):
        for field in FIELDS:
            a, b = getattr(one, field), getattr(two, field)
            if a is None:  # the clean set's labels
                assert b is None, field
                continue
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), field
