"""The environment suite (SPEC §11): each environment's pipeline directory, in one place.

The root of the project is the paper's default pipeline (LunarLander); every other environment
has its own pipeline under ``pipeline/<directory>/``, whose ``params.yaml`` extends the shared
one and whose ``models/policy.pt`` is its committed policy.
"""

from __future__ import annotations

from pathlib import Path

#: Environment id → its pipeline directory, relative to the project root.
PIPELINE_DIRS: dict[str, Path] = {
    "LunarLander-v3": Path("."),
    "CartPole-v1": Path("pipeline/cartpole"),
    "Acrobot-v1": Path("pipeline/acrobot"),
    "Pendulum-v1": Path("pipeline/pendulum"),
    "LunarLanderContinuous-v3": Path("pipeline/lunar_lander_continuous"),
    "HalfCheetah-v5": Path("pipeline/half_cheetah"),
    "Hopper-v5": Path("pipeline/hopper"),
}

#: Mean return over 30 held-out episodes a committed policy must reach (SPEC §11).
POLICY_BARS: dict[str, float] = {
    "LunarLander-v3": 230.0,
    "CartPole-v1": 475.0,
    "Acrobot-v1": -100.0,
    "Pendulum-v1": -200.0,
    "LunarLanderContinuous-v3": 200.0,
    "HalfCheetah-v5": 3000.0,
    "Hopper-v5": 2000.0,
}


def policy_path(env_id: str, root: Path = Path(".")) -> Path:
    """The committed policy of an environment of the suite."""
    return root / pipeline_dir(env_id) / "models" / "policy.pt"


def pipeline_dir(env_id: str) -> Path:
    from oodrl.config import did_you_mean
    from oodrl.errors import ConfigError

    if env_id not in PIPELINE_DIRS:
        hint = did_you_mean(env_id, list(PIPELINE_DIRS))
        raise ConfigError(
            f"--env: {env_id!r} is not an environment of the suite.{hint} "
            f"Known: {', '.join(PIPELINE_DIRS)}."
        )
    return PIPELINE_DIRS[env_id]
