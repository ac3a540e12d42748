"""Train a continuous-control policy with Stable-Baselines3 SAC and export its actor (SPEC §11).

SB3 does the learning; oodrl keeps only the deterministic actor ``tanh(mu(latent(s)))`` rescaled
to the action bounds, saved in oodrl's own checkpoint format (kind ``tanh_actor``), so collecting
data and ``evaluate-policy`` need torch alone, never the trainer. A callback evaluates the actor
every ``eval_every`` steps on *tuning* seeds, keeps the best weights and stops once they reach
``early_stop_return``; the kept actor is then evaluated on *held-out* seeds for the report.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from oodrl.policies.settings import SacConfig

TUNING_SEED_OFFSET = 100_000


def actor_state_dict(model: Any) -> dict[str, torch.Tensor]:
    """The SB3 SAC actor's deterministic path as a ``tanh_actor`` state_dict (``net.{i}.*``)."""
    actor = model.policy.actor
    linears = [m for m in actor.latent_pi if isinstance(m, torch.nn.Linear)] + [actor.mu]
    state: dict[str, torch.Tensor] = {}
    for i, layer in enumerate(linears):
        state[f"net.{2 * i}.weight"] = layer.weight.detach().clone().contiguous()
        state[f"net.{2 * i}.bias"] = layer.bias.detach().clone().contiguous()
    return state


def train_sac(
    config: SacConfig, policy_path: Path, report_path: Path, progress: bool = False
) -> dict[str, Any]:
    """Train; save the best evaluated actor and its report (also returned)."""
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback

    from oodrl.policies.act import policy_from_checkpoint
    from oodrl.policies.checkpoint import save_policy
    from oodrl.policies.evaluate import evaluate_policy

    torch.set_num_threads(1)
    started = time.perf_counter()
    env = gym.make(config.env_id)
    architecture = {
        "kind": "tanh_actor",
        "state_dim": int(np.prod(env.observation_space.shape)),
        "action_dim": int(np.prod(env.action_space.shape)),
        "hidden_sizes": list(config.hidden_sizes),
        "action_low": [float(x) for x in env.action_space.low],
        "action_high": [float(x) for x in env.action_space.high],
    }
    model = SAC(
        "MlpPolicy",
        env,
        learning_rate=config.lr,
        buffer_size=config.buffer_size,
        learning_starts=config.learning_starts,
        batch_size=config.batch_size,
        tau=config.tau,
        gamma=config.gamma,
        train_freq=config.train_freq,
        gradient_steps=config.gradient_steps,
        policy_kwargs={"net_arch": list(config.hidden_sizes)},
        seed=config.seed,
        device="cpu",
        verbose=0,
    )

    def returns(state: dict[str, torch.Tensor], episodes: int, seed: int) -> np.ndarray:
        policy = policy_from_checkpoint(architecture, state)
        return evaluate_policy(policy, episodes, seed, env_id=config.env_id)

    class KeepBest(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.best_return, self.best_step = -np.inf, 0
            self.best_state = actor_state_dict(model)
            self.curve: list[list[float]] = []

        def _on_step(self) -> bool:
            step = self.num_timesteps
            if step <= config.learning_starts or step % config.eval_every:
                return True
            state = actor_state_dict(model)
            tuning_seed = config.seed + TUNING_SEED_OFFSET
            mean = float(returns(state, config.eval_episodes, tuning_seed).mean())
            self.curve.append([step, mean])
            if mean > self.best_return:
                self.best_return, self.best_step, self.best_state = mean, step, state
            if progress:
                print(
                    f"step {step:>8d}  eval {mean:9.1f}  best {self.best_return:9.1f}"
                    f"@{self.best_step}  {time.perf_counter() - started:6.0f}s",
                    flush=True,
                )
            return mean < config.early_stop_return

    keep = KeepBest()
    model.learn(total_timesteps=config.total_steps, callback=keep)
    env.close()

    final = returns(keep.best_state, config.final_eval_episodes, config.final_eval_seed)
    return save_policy(
        policy_path,
        report_path,
        architecture=architecture,
        state_dict=keep.best_state,
        train_config=config.as_dict(),
        final_returns=final,
        final_eval_seed=config.final_eval_seed,
        tuning={
            "episodes": config.eval_episodes,
            "seeds_start": config.seed + TUNING_SEED_OFFSET,
            "best_mean": float(keep.best_return),
            "best_step": keep.best_step,
        },
        steps_run=int(model.num_timesteps),
        learning_curve=keep.curve,
        wall_time_s=time.perf_counter() - started,
        env_id=config.env_id,
        trainer={"stable_baselines3": _sb3_version(), "algorithm": "SAC"},
    )


def _sb3_version() -> str:
    import stable_baselines3

    return str(stable_baselines3.__version__)
