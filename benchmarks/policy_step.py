"""The policy's share of a simulated step, old exact step vs new step, in one run (SPEC §14).

    python benchmarks/policy_step.py [--envs LunarLander-v3 CartPole-v1 ...] [--streams 32]
        [--steps 300] [--repeats 3]

For each environment of the suite, its committed policy collects ``--streams`` streams of
``--steps`` steps twice per repeat, alternating between two steps:

- ``old``: every layer by ``numerics.linear`` (weights converted and bounded on every call),
  then the argmax or the squashing: the step before `numerics.Affine` and `ReluArgmax`;
- ``new``: the policy's ``act``: layers by `numerics.Affine` (prepared once); a greedy ReLU
  argmax head decides by `numerics.ReluArgmax`, the exact outputs only for undecided rows.

The collector is the real one; the policy call and every ``env.step`` are timed where they
run. Prints, per environment and step, the best repeat's policy and env.step milliseconds per
stream-step (CPU time of the thread, so that other processes' load on a shared machine counts
less), the policy/env.step ratio, new/old policy time, and whether both steps collected the
same bytes.

Run it with ``OPENBLAS_NUM_THREADS=1`` as the stages do (`oodrl.parallel`).
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np

from oodrl import numerics
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import collect
from oodrl.policies.load import load_policy
from oodrl.suite.environments import PIPELINE_DIRS, policy_path

ROOT = Path(__file__).resolve().parents[1]


class _Clock:
    """Seconds spent in the policy's calls and in env.step, and the stream-steps acted on."""

    def __init__(self) -> None:
        self.policy = self.env = 0.0
        self.rows = 0


class _TimedPolicy:
    """The policy, acting through ``step`` (its ``act`` or ``exact_act``), its calls timed."""

    def __init__(self, policy, step, clock: _Clock) -> None:
        self._policy, self._step, self._clock = policy, step, clock

    def __getattr__(self, name: str):
        return getattr(self._policy, name)

    def act(self, observations, rngs=None):
        start = time.thread_time()
        actions = self._step(observations, rngs)
        self._clock.policy += time.thread_time() - start
        self._clock.rows += len(observations)
        return actions


def _timed_adapter(env_id: str, clock: _Clock):
    """The environment's adapter, each env.step it makes timed."""
    adapter = ENVIRONMENTS.get(env_id)()
    make = adapter.make

    def timed_make():
        env = make()
        step = env.step

        def timed_step(action):
            start = time.thread_time()
            result = step(action)
            clock.env += time.thread_time() - start
            return result

        env.step = timed_step
        return env

    adapter.make = timed_make
    return adapter


def old_step(policy):
    """The policy acting as before prepared layers: `numerics.linear` per layer and call."""
    old = copy.copy(policy)  # without its prepared layers (`LayeredPolicy.__getstate__`)
    old._affine = [
        lambda x, w=lay.weight, b=lay.bias: numerics.linear(x, w, b) for lay in old.layers
    ]
    old._certified_argmax = None
    return old.act


def _run(env_id: str, policy, step, streams: int, steps: int) -> tuple[_Clock, bytes]:
    clock = _Clock()
    tset = collect(
        _timed_adapter(env_id, clock), _TimedPolicy(policy, step, clock), range(streams), steps
    )
    fields = (tset.states, tset.actions, tset.executed_actions, tset.rewards, tset.next_states)
    return clock, b"".join(np.ascontiguousarray(f).tobytes() for f in fields)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=list(PIPELINE_DIRS))
    parser.add_argument("--streams", type=int, default=32)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    print(
        f"{args.streams} streams x {args.steps} steps, best of {args.repeats}; ms per stream-step"
    )
    print(
        f"{'environment':26s} {'step':5s} {'policy':>8s} {'env.step':>8s} {'pol/env':>8s} "
        f"{'new/old':>8s}  same bytes"
    )
    for env_id in args.envs:
        policy = load_policy(policy_path(env_id, ROOT))
        steps = {"old": old_step(policy), "new": policy.act}
        best: dict[str, _Clock] = {}
        digests = {}
        for _ in range(args.repeats):
            for name, step in steps.items():  # alternating: machine load hits both alike
                clock, digests[name] = _run(env_id, policy, step, args.streams, args.steps)
                if name not in best or clock.policy < best[name].policy:
                    best[name] = clock
        same = len(set(digests.values())) == 1
        for name, clock in best.items():
            policy_ms, env_ms = 1e3 * clock.policy / clock.rows, 1e3 * clock.env / clock.rows
            speedup = clock.policy / best["old"].policy
            print(
                f"{env_id:26s} {name:5s} {policy_ms:8.4f} {env_ms:8.4f} "
                f"{policy_ms / env_ms:8.2f} {speedup:8.2f}  {same if name == 'new' else ''}"
            )


if __name__ == "__main__":
    main()
