"""Train a continuous-control policy with Stable-Baselines3 SAC and export its actor (SPEC §11).

SB3 does the learning; oodrl keeps only the deterministic actor ``tanh(mu(latent(s)))`` rescaled
to the action bounds, saved in oodrl's own checkpoint format (kind ``tanh_actor``), so collecting
data and ``evaluate-policy`` need torch alone, never the trainer. A callback evaluates the actor
every ``eval_every`` steps on *tuning* seeds, keeps the best weights and stops once they reach
``early_stop_return``; the kept actor is then evaluated on *held-out* seeds for the report.

A MuJoCo or LunarLanderContinuous training takes one to several hours of a core, longer than a
working session on a shared machine, so at every evaluation the trainer also saves what it needs
to go on (`<policy>.training/`: SB3's model with its optimisers, the replay buffer, the kept
actor and the curve so far). Started again with the same `policy.train` settings, it resumes
from there, and the report lists the steps it resumed at; a checkpoint of other settings is
set aside. A resumed run is not bit-identical to one run straight through (the environment
restarts its episode and the samplers their streams), as no two trainings are promised to be.
The checkpoint is removed once the policy is saved.
"""

from __future__ import annotations

import io
import json
import shutil
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
    from oodrl.policies.load import quiet_sb3_logger

    torch.set_num_threads(1)
    started = time.perf_counter()
    checkpoint = TrainingCheckpoint(policy_path, config.as_dict())
    env = gym.make(config.env_id)
    architecture = {
        "kind": "tanh_actor",
        "state_dim": int(np.prod(env.observation_space.shape)),
        "action_dim": int(np.prod(env.action_space.shape)),
        "hidden_sizes": list(config.hidden_sizes),
        "action_low": [float(x) for x in env.action_space.low],
        "action_high": [float(x) for x in env.action_space.high],
    }
    progress_so_far = checkpoint.progress()
    if progress_so_far is not None:
        model = checkpoint.load_model(SAC, env, progress_so_far)
        # Seeded by the step resumed at: resuming one checkpoint twice trains the same policy.
        model.set_random_seed(config.seed + model.num_timesteps)
        print(f"train_policy: resuming at step {model.num_timesteps} from {checkpoint.directory}")
    else:
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
            self.resumed_at: list[int] = []
            self.earlier_wall_s = 0.0
            if progress_so_far is not None:
                self.best_return = progress_so_far["best_return"]
                self.best_step = progress_so_far["best_step"]
                self.best_state = progress_so_far["best_state"]
                self.curve = progress_so_far["curve"]
                self.resumed_at = [*progress_so_far["resumed_at"], progress_so_far["step"]]
                self.earlier_wall_s = progress_so_far["wall_s"]

        def wall_s(self) -> float:
            return self.earlier_wall_s + time.perf_counter() - started

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
                    f"@{self.best_step}  {self.wall_s():6.0f}s",
                    flush=True,
                )
            go_on = mean < config.early_stop_return
            if go_on:
                checkpoint.save(model, {
                    "step": step, "best_return": self.best_return, "best_step": self.best_step,
                    "best_state": self.best_state, "curve": self.curve,
                    "resumed_at": self.resumed_at, "wall_s": self.wall_s(),
                })  # fmt: skip
            return go_on

    keep = KeepBest()
    remaining = config.total_steps - model.num_timesteps
    model.set_logger(quiet_sb3_logger())
    model.learn(total_timesteps=remaining, callback=keep, reset_num_timesteps=False)
    env.close()

    final = returns(keep.best_state, config.final_eval_episodes, config.final_eval_seed)
    report = save_policy(
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
        wall_time_s=keep.wall_s(),
        env_id=config.env_id,
        trainer={
            "stable_baselines3": _sb3_version(), "algorithm": "SAC",
            **({"resumed_at_steps": keep.resumed_at} if keep.resumed_at else {}),
        },
    )  # fmt: skip
    checkpoint.remove()
    return report


class TrainingCheckpoint:
    """What a SAC training needs to go on, beside the policy it will write (module docstring).

    `progress.pt` (the kept actor, the curve, the step) is written last and names the step of
    the model and buffer files, so an interrupted save leaves the previous checkpoint whole.
    """

    def __init__(self, policy_path: Path, settings: dict[str, Any]) -> None:
        self.directory = policy_path.with_name(policy_path.name + ".training")
        self.settings = settings

    def progress(self) -> dict[str, Any] | None:
        """The saved progress of a training with these settings, or None."""
        path = self.directory / "progress.pt"
        if not path.is_file():
            return None
        saved = torch.load(path, weights_only=True)
        if json.loads(saved["settings"]) != self.settings:
            print(f"train_policy: {self.directory} holds a training of other settings: not resumed")
            return None
        return saved

    def load_model(self, sac: type, env: Any, progress: dict[str, Any]) -> Any:
        step = progress["step"]
        model = sac.load(self.directory / f"model-{step}.zip", env=env, device="cpu")
        model.load_replay_buffer(self.directory / f"buffer-{step}.pkl")
        return model

    def save(self, model: Any, progress: dict[str, Any]) -> None:
        from oodrl.io.fileio import atomic_write_bytes

        step = progress["step"]
        self.directory.mkdir(parents=True, exist_ok=True)
        model.save(self.directory / f"model-{step}.zip")
        model.save_replay_buffer(self.directory / f"buffer-{step}.pkl")
        buffer = io.BytesIO()
        torch.save({**progress, "settings": json.dumps(self.settings)}, buffer)
        atomic_write_bytes(self.directory / "progress.pt", buffer.getvalue())
        for old in self.directory.glob("*-*.*"):
            if old.stem.rsplit("-", 1)[-1] != str(step):
                old.unlink()

    def remove(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)


def _sb3_version() -> str:
    import stable_baselines3

    return str(stable_baselines3.__version__)
