"""The environment suite (SPEC §11): each environment's pipeline directory, in one place.

The root of the project is the paper's default pipeline (LunarLander, the paper's eight
detectors). Every environment of the suite, LunarLander included, has its own pipeline under
``pipeline/<directory>/``, whose ``params.yaml`` extends the suite's (``pipeline/params.yaml``:
the paper's protocol plus the library detectors, SPEC §17) and whose ``models/policy.pt`` is its
committed policy (LunarLander's is the root's, byte for byte).
"""

from __future__ import annotations

from pathlib import Path

#: Environment id → its pipeline directory, relative to the project root.
PIPELINE_DIRS: dict[str, Path] = {
    "LunarLander-v3": Path("pipeline/lunar_lander"),
    "CartPole-v1": Path("pipeline/cartpole"),
    "Acrobot-v1": Path("pipeline/acrobot"),
    "Pendulum-v1": Path("pipeline/pendulum"),
    "LunarLanderContinuous-v3": Path("pipeline/lunar_lander_continuous"),
    "HalfCheetah-v5": Path("pipeline/half_cheetah"),
    "Hopper-v5": Path("pipeline/hopper"),
}

#: Each environment's further policies (SPEC §16), trained like its first from training seeds
#: 1, 2, … and each built by a pipeline of its own: (environment id, policy) → pipeline
#: directory. An environment's policy "0" is its PIPELINE_DIRS entry.
MORE_POLICIES: dict[tuple[str, str], Path] = {
    ("CartPole-v1", "1"): Path("pipeline/cartpole_policy1"),
    ("CartPole-v1", "2"): Path("pipeline/cartpole_policy2"),
    ("Acrobot-v1", "1"): Path("pipeline/acrobot_policy1"),
    ("Acrobot-v1", "2"): Path("pipeline/acrobot_policy2"),
    ("LunarLander-v3", "1"): Path("pipeline/lunar_lander_policy1"),
    ("LunarLander-v3", "2"): Path("pipeline/lunar_lander_policy2"),
    ("Pendulum-v1", "1"): Path("pipeline/pendulum_policy1"),
    ("Pendulum-v1", "2"): Path("pipeline/pendulum_policy2"),
    ("LunarLanderContinuous-v3", "1"): Path("pipeline/lunar_lander_continuous_policy1"),
    ("LunarLanderContinuous-v3", "2"): Path("pipeline/lunar_lander_continuous_policy2"),
    ("HalfCheetah-v5", "1"): Path("pipeline/half_cheetah_policy1"),
    ("HalfCheetah-v5", "2"): Path("pipeline/half_cheetah_policy2"),
    ("Hopper-v5", "1"): Path("pipeline/hopper_policy1"),
    ("Hopper-v5", "2"): Path("pipeline/hopper_policy2"),
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


def suite_runs() -> dict[tuple[str, str], Path]:
    """(environment id, policy) → its pipeline directory: every run the leaderboard reads."""
    from oodrl.metrics.leaderboard import FIRST_POLICY

    runs = {(env_id, FIRST_POLICY): directory for env_id, directory in PIPELINE_DIRS.items()}
    return {**runs, **MORE_POLICIES}


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
