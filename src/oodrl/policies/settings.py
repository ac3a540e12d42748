"""The policy trainer's settings (`policy.train` in params.yaml), importable without torch.

Every stage validates params.yaml on start; keeping this dataclass free of torch keeps that cheap.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True, kw_only=True)
class PolicyTrainConfig:
    """What every policy trainer reads: the environment, the network, the step budget, the
    periodic and final evaluation, and the seed. Each trainer's settings add their own fields
    and the defaults that differ between trainers."""

    env_id: str
    hidden_sizes: tuple[int, ...] = (256, 256)
    total_steps: int
    batch_size: int
    gamma: float = 0.99
    lr: float
    buffer_size: int
    learning_starts: int = 10_000
    train_freq: int
    eval_every: int = 10_000
    eval_episodes: int
    early_stop_return: float
    """Training ends once the greedy policy's mean return on the tuning seeds reaches it."""
    final_eval_episodes: int = 30
    final_eval_seed: int = 1_000_000
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden_sizes", tuple(int(h) for h in self.hidden_sizes))

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["hidden_sizes"] = list(self.hidden_sizes)
        return d


@dataclass(frozen=True, kw_only=True)
class TrainConfig(PolicyTrainConfig):
    """Hyper-parameters of :func:`oodrl.policies.train.train` (NoisyNet double DQN)."""

    env_id: str = "LunarLander-v3"
    sigma0: float = 0.5
    total_steps: int = 300_000
    batch_size: int = 64
    lr: float = 5e-4
    lr_final: float = 5e-4
    """Learning rate at ``total_steps``, reached by linear decay from ``lr``."""
    adam_eps: float = 1.5e-4
    buffer_size: int = 100_000
    target_sync: int = 1000
    train_freq: int = 4
    max_grad_norm: float = 10.0
    eval_episodes: int = 20
    early_stop_return: float = 260.0


@dataclass(frozen=True, kw_only=True)
class SacConfig(PolicyTrainConfig):
    """Hyper-parameters of :func:`oodrl.policies.sac.train_sac` (continuous control, SPEC §11).

    Defaults follow RL Baselines3 Zoo's SAC settings.
    """

    env_id: str = "Pendulum-v1"
    total_steps: int = 1_000_000
    lr: float = 3e-4
    buffer_size: int = 1_000_000
    batch_size: int = 256
    tau: float = 0.005
    train_freq: int = 1
    gradient_steps: int = 1
    eval_episodes: int = 10
    early_stop_return: float = 0.0


@dataclass(frozen=True, kw_only=True)
class ImportedConfig:
    """A policy `oodrl new` converted or trained (SPEC §18): the pipeline keeps it and never
    trains it. What it came from, recorded so the kept policy's report can be checked."""

    env_id: str
    source: str
    """How it was made: 'Stable-Baselines3 PPO .zip', 'RL Zoo folder', 'oodrl new --train sac'."""
    file: str = ""
    """The source file's name (no directory: no host paths in the pipeline's files)."""
    sha256: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


#: ``policy.train.algorithm`` → the settings of its trainer.
TRAINER_CONFIGS: dict[str, type] = {
    "noisy_dqn": TrainConfig,
    "sac": SacConfig,
    "imported": ImportedConfig,
}
