"""Train the benchmark's policy: double DQN with NoisyNet exploration on the flat state.

One readable file in the style of CleanRL's ``dqn.py``. Exploration comes only from the noisy layers
(no ε-greedy). The online network picks the next action and the target network values it (double
Q-learning); each side draws its own noise sample per update. A periodic greedy evaluation on
*tuning* seeds keeps the best weights and stops training early once they are good enough; the
kept weights are then evaluated on *held-out* seeds (disjoint from training and tuning seeds) for
the report.

Seeds: training episodes are the environment's RNG stream after ``reset(seed=seed)``; tuning
evaluations use seeds ``seed + 100_000 + i``; the final evaluation uses ``final_eval_seed + i``.
On one machine with one torch thread, a given config gives byte-identical checkpoint files.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from oodrl.policies.act import policy_from_checkpoint
from oodrl.policies.checkpoint import save_policy
from oodrl.policies.evaluate import evaluate_policy
from oodrl.policies.networks import NoisyQNetwork
from oodrl.policies.settings import TrainConfig

TUNING_SEED_OFFSET = 100_000


class ReplayBuffer:
    """Fixed-size ring buffer of transitions in preallocated numpy arrays."""

    def __init__(self, size: int, state_dim: int) -> None:
        self.obs = np.zeros((size, state_dim), dtype=np.float32)
        self.next_obs = np.zeros((size, state_dim), dtype=np.float32)
        self.actions = np.zeros(size, dtype=np.int64)
        self.rewards = np.zeros(size, dtype=np.float32)
        self.terminated = np.zeros(size, dtype=np.float32)
        self.size = size
        self.count = 0

    def add(self, obs, action: int, reward: float, next_obs, terminated: bool) -> None:
        i = self.count % self.size
        self.obs[i], self.actions[i], self.rewards[i] = obs, action, reward
        self.next_obs[i], self.terminated[i] = next_obs, terminated
        self.count += 1

    def sample(self, batch_size: int, rng: np.random.Generator) -> tuple[torch.Tensor, ...]:
        idx = rng.integers(0, min(self.count, self.size), size=batch_size)
        return tuple(
            torch.from_numpy(a[idx])
            for a in (self.obs, self.actions, self.rewards, self.next_obs, self.terminated)
        )


def greedy_returns(
    network: NoisyQNetwork, config: TrainConfig, episodes: int, seed: int
) -> np.ndarray:
    """Returns of the noise-free network on episodes seeded seed..seed+episodes-1."""
    policy = policy_from_checkpoint({"kind": "noisy_dqn"}, network.state_dict())
    return evaluate_policy(policy, episodes, seed, env_id=config.env_id)


def train(
    config: TrainConfig, policy_path: Path, report_path: Path, progress: bool = False
) -> dict[str, Any]:
    """Train; save the best evaluated weights and their report (also returned)."""
    torch.set_num_threads(1)
    torch.manual_seed(config.seed)
    np_rng = np.random.default_rng(config.seed)
    noise_gen = torch.Generator().manual_seed(config.seed + 1)
    started = time.perf_counter()

    env = gym.make(config.env_id)
    state_dim = int(np.prod(env.observation_space.shape))
    n_actions = int(env.action_space.n)
    q_net = NoisyQNetwork(state_dim, n_actions, config.hidden_sizes, config.sigma0)
    target_net = copy.deepcopy(q_net)
    optimizer = torch.optim.Adam(q_net.parameters(), lr=config.lr, eps=config.adam_eps)
    buffer = ReplayBuffer(config.buffer_size, state_dim)

    best_state = copy.deepcopy(q_net.state_dict())
    best_return, best_step = -np.inf, 0
    curve: list[tuple[int, float]] = []
    episode_return, episode_returns = 0.0, []
    obs, _ = env.reset(seed=config.seed)
    step = 0
    for step in range(1, config.total_steps + 1):
        with torch.no_grad():
            q = q_net(torch.from_numpy(obs).unsqueeze(0), q_net.sample_noise(noise_gen))
        action = int(q.argmax())
        next_obs, reward, terminated, truncated, _ = env.step(action)
        buffer.add(obs, action, float(reward), next_obs, terminated)
        episode_return += float(reward)
        obs = next_obs
        if terminated or truncated:
            episode_returns.append(episode_return)
            episode_return = 0.0
            obs, _ = env.reset()

        if step > config.learning_starts and step % config.train_freq == 0:
            frac = min(1.0, step / config.total_steps)
            for group in optimizer.param_groups:
                group["lr"] = config.lr + frac * (config.lr_final - config.lr)
            b_obs, b_act, b_rew, b_next, b_term = buffer.sample(config.batch_size, np_rng)
            online_noise = q_net.sample_noise(noise_gen)
            with torch.no_grad():
                next_action = q_net(b_next, online_noise).argmax(dim=1, keepdim=True)
                next_q = target_net(b_next, target_net.sample_noise(noise_gen)).gather(
                    1, next_action
                )
                target = b_rew + config.gamma * (1.0 - b_term) * next_q.squeeze(1)
            q_taken = q_net(b_obs, online_noise).gather(1, b_act.unsqueeze(1)).squeeze(1)
            loss = nn.functional.smooth_l1_loss(q_taken, target)
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(q_net.parameters(), config.max_grad_norm)
            optimizer.step()

        if step % config.target_sync == 0:
            target_net.load_state_dict(q_net.state_dict())

        if step > config.learning_starts and step % config.eval_every == 0:
            tuning_seed = config.seed + TUNING_SEED_OFFSET
            mean = float(greedy_returns(q_net, config, config.eval_episodes, tuning_seed).mean())
            curve.append((step, mean))
            if mean > best_return:
                best_return, best_step = mean, step
                best_state = copy.deepcopy(q_net.state_dict())
            if progress:
                recent = np.mean(episode_returns[-20:]) if episode_returns else float("nan")
                print(
                    f"step {step:>8d}  eval {mean:8.1f}  best {best_return:8.1f}@{best_step}  "
                    f"train(20) {recent:8.1f}  {time.perf_counter() - started:6.0f}s",
                    flush=True,
                )
            if mean >= config.early_stop_return:
                break
    env.close()

    q_net.load_state_dict(best_state)
    final = greedy_returns(q_net, config, config.final_eval_episodes, config.final_eval_seed)
    return save_policy(
        policy_path,
        report_path,
        architecture={
            "kind": "noisy_dqn",
            "state_dim": state_dim,
            "n_actions": n_actions,
            "hidden_sizes": list(config.hidden_sizes),
            "sigma0": config.sigma0,
        },
        state_dict=best_state,
        env_id=config.env_id,
        train_config=config.as_dict(),
        final_returns=final,
        final_eval_seed=config.final_eval_seed,
        tuning={
            "episodes": config.eval_episodes,
            "seeds_start": config.seed + TUNING_SEED_OFFSET,
            "best_mean": float(best_return),
            "best_step": best_step,
        },
        steps_run=step,
        learning_curve=curve,
        wall_time_s=time.perf_counter() - started,
        trainer={"algorithm": "NoisyNet double DQN (oodrl)"},
    )
