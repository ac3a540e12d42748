"""The policy trainer's settings (`policy.train` in params.yaml), importable without torch.

Every stage validates params.yaml on start; keeping this dataclass free of torch keeps that cheap.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class TrainConfig:
    """Hyper-parameters of :func:`train` (``policy.train`` in params.yaml)."""

    env_id: str = "LunarLander-v3"
    hidden_sizes: tuple[int, ...] = (256, 256)
    sigma0: float = 0.5
    total_steps: int = 300_000
    batch_size: int = 64
    gamma: float = 0.99
    lr: float = 5e-4
    lr_final: float = 5e-4
    """Learning rate at ``total_steps``, reached by linear decay from ``lr``."""
    adam_eps: float = 1.5e-4
    buffer_size: int = 100_000
    target_sync: int = 1000
    learning_starts: int = 10_000
    train_freq: int = 4
    max_grad_norm: float = 10.0
    eval_every: int = 10_000
    eval_episodes: int = 20
    early_stop_return: float = 260.0
    final_eval_episodes: int = 30
    final_eval_seed: int = 1_000_000
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden_sizes", tuple(int(h) for h in self.hidden_sizes))

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["hidden_sizes"] = list(self.hidden_sizes)
        return d


@dataclass(frozen=True)
class SacConfig:
    """Hyper-parameters of :func:`oodrl.policies.sac.train_sac` (continuous control, SPEC §11).

    Defaults follow RL Baselines3 Zoo's SAC settings; ``early_stop_return`` ends training once
    the deterministic actor's mean return on the tuning seeds reaches it.
    """

    env_id: str = "Pendulum-v1"
    hidden_sizes: tuple[int, ...] = (256, 256)
    total_steps: int = 1_000_000
    learning_starts: int = 10_000
    lr: float = 3e-4
    buffer_size: int = 1_000_000
    batch_size: int = 256
    gamma: float = 0.99
    tau: float = 0.005
    train_freq: int = 1
    gradient_steps: int = 1
    eval_every: int = 10_000
    eval_episodes: int = 10
    early_stop_return: float = 0.0
    final_eval_episodes: int = 30
    final_eval_seed: int = 1_000_000
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden_sizes", tuple(int(h) for h in self.hidden_sizes))

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["hidden_sizes"] = list(self.hidden_sizes)
        return d


#: ``policy.train.algorithm`` → the settings of its trainer.
TRAINER_CONFIGS: dict[str, type] = {"noisy_dqn": TrainConfig, "sac": SacConfig}
