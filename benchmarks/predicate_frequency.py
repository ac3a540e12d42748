"""How often action_conditioned_dynamics' predicate holds on clean steps, per environment.

    python benchmarks/predicate_frequency.py

SPEC §11 asks for a predicate that holds on roughly a third to a half of clean steps. For each
environment with a committed policy, this collects its clean evaluation streams (the protocol's
seeds, T and policy mode from its params) and prints the fraction of steps on which the
predicate of its params holds: the commanded action is `target_action` (discrete), or its
coordinate `target_dim` is above `target_threshold` (continuous).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oodrl.config import load_params
from oodrl.envs import ENVIRONMENTS
from oodrl.envs.collect import collect
from oodrl.policies.load import load_policy
from oodrl.protocol.streams import eval_seeds
from oodrl.suite.environments import PIPELINE_DIRS, policy_path

ROOT = Path(__file__).resolve().parents[1]


def frequency(env_id: str) -> tuple[str, float] | None:
    policy_file = policy_path(env_id, ROOT)
    if not policy_file.is_file():
        return None
    params = load_params(ROOT / PIPELINE_DIRS[env_id] / "params.yaml")
    block = params.anomaly.injectors["action_conditioned_dynamics"]
    policy = load_policy(policy_file, mode=params.policy.mode)
    streams = collect(
        ENVIRONMENTS.get(env_id)(), policy, eval_seeds(params), params.env.T,
        policy_seed=params.seed,
    )  # fmt: skip
    actions = streams.actions
    if block.get("target_action") is not None:
        return f"action == {block['target_action']}", float(
            np.mean(actions == block["target_action"])
        )
    dim, threshold = block["target_dim"], block["target_threshold"]
    return f"a[{dim}] > {threshold}", float(np.mean(actions[..., dim] > threshold))


def main() -> None:
    print("| environment | predicate | clean steps where it holds |")
    print("|---|---|---:|")
    for env_id in PIPELINE_DIRS:
        found = frequency(env_id)
        if found is None:
            print(f"| {env_id} | — | no committed policy |")
            continue
        predicate, share = found
        print(f"| {env_id} | `{predicate}` | {share:.1%} |")


if __name__ == "__main__":
    main()
