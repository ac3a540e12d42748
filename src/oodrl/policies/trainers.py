"""Which trainer a `policy.train` block runs, and the checks that keep a committed policy.

A committed policy is kept unless retraining is asked for on purpose: it is missing, or its
recorded training settings differ from params, and either stops with the command that restores
it or retrains it (training takes 13 minutes and overwrites the committed file).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from oodrl.errors import ConfigError, PolicyError

RETRAIN_VARIABLE = "OODRL_RETRAIN_POLICY"
#: The command that retrains on purpose (-s: nothing else is re-run with it).
RETRAIN_COMMAND = f"{RETRAIN_VARIABLE}=1 dvc repro -s -f train_policy"


def retrain_requested() -> bool:
    return os.environ.get(RETRAIN_VARIABLE) == "1"


def trainer(config):
    """The training function of a `policy.train` settings type: the NoisyNet DQN (discrete
    actions) or SAC (continuous control; imports Stable-Baselines3 only when it trains)."""
    from oodrl.policies.settings import ImportedConfig, SacConfig, TrainConfig

    if isinstance(config, TrainConfig):
        from oodrl.policies.train import train

        return train
    if isinstance(config, SacConfig):
        from oodrl.policies.sac import train_sac

        return train_sac
    if isinstance(config, ImportedConfig):
        raise PolicyError(
            f"policy.train: this pipeline's policy was imported ({config.source} "
            f"{config.file}), not trained here; to change it, make a new pipeline with "
            "`oodrl new NAME --env ID --policy PATH`."
        )
    raise ConfigError(f"policy.train: no trainer for {type(config).__name__}.")


def kept_policy(settings: dict[str, Any], out: Path, report: Path) -> dict[str, Any]:
    """The report of the policy at `out`, refused when missing or trained with other settings."""
    missing = [str(path) for path in (out, report) if not path.is_file()]
    if missing:
        raise PolicyError(
            f"{' and '.join(missing)} missing; restore the committed policy with "
            f"`git checkout -- {out} {report}`, or retrain on purpose (13 min) with "
            f"`{RETRAIN_COMMAND}`."
        )
    recorded = json.loads(report.read_text()).get("train_config", {})
    keys = settings.keys() | recorded.keys()
    changed = sorted(k for k in keys if settings.get(k) != recorded.get(k))
    if changed:
        key = changed[0]
        raise ConfigError(
            f"policy.train.{key}: {settings.get(key)!r}, but {out} was trained with "
            f"{recorded.get(key)!r}; restore policy.train, or retrain on purpose (13 min) with "
            f"`{RETRAIN_COMMAND}`."
        )
    print(f"train_policy: keeping {out} (trained with these policy.train settings); "
          f"to retrain: `{RETRAIN_COMMAND}`.")  # fmt: skip
    return json.loads(report.read_text())
