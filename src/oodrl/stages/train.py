"""The train_policy stage: NoisyNet double DQN, or SAC for continuous control (SPEC §2, §11).

The trained policy is committed (models/policy.pt and its report), and training takes 13
minutes, so the stage trains only on purpose: with OODRL_RETRAIN_POLICY=1 in its environment.
Otherwise DVC re-running it (a code edit in its import closure, a replaced policy file) keeps
the policy that is there (`oodrl.policies.trainers`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from oodrl.config import Params
from oodrl.policies.trainers import RETRAIN_COMMAND, kept_policy, retrain_requested, trainer
from oodrl.progress import progress_enabled

__all__ = ["RETRAIN_COMMAND", "retrain_requested", "train_policy"]


def train_policy(params: Params, out: Path, report: Path, retrain: bool) -> dict[str, Any]:
    """Train when `retrain`; otherwise check that the committed policy is there and current."""
    config = params.policy_train_config()
    if not retrain:
        return kept_policy(config.as_dict(), out, report)
    return trainer(config)(config, out, report, progress=progress_enabled(params.executor.progress))
