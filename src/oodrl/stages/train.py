"""The train_policy stage: NoisyNet double DQN on the flat state (SPEC §2)."""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params
from oodrl.stages.common import progress_enabled


def train_policy(params: Params, out: Path, report: Path) -> dict:
    from oodrl.policies.train import train

    config = params.policy_train_config()
    return train(config, out, report, progress=progress_enabled(params.executor.progress))
