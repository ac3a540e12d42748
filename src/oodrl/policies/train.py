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
from dataclasses import dataclass, field
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


@dataclass
class Tuning:
    """The periodic greedy evaluations on tuning seeds: the curve and the best weights so far."""

    seeds_start: int
    episodes: int
    best_state: dict[str, torch.Tensor]
    best_return: float = -np.inf
    best_step: int = 0
    curve: list[tuple[int, float]] = field(default_factory=list)

    def evaluate(self, q_net: NoisyQNetwork, config: TrainConfig, step: int) -> float:
        """The greedy mean return now; keeps the weights when it is the best so far."""
        mean = float(greedy_returns(q_net, config, self.episodes, self.seeds_start).mean())
        self.curve.append((step, mean))
        if mean > self.best_return:
            self.best_return, self.best_step = mean, step
            self.best_state = copy.deepcopy(q_net.state_dict())
        return mean

    def report(self) -> dict[str, Any]:
        return {
            "episodes": self.episodes,
            "seeds_start": self.seeds_start,
            "best_mean": float(self.best_return),
            "best_step": self.best_step,
        }


def update(
    q_net: NoisyQNetwork,
    target_net: NoisyQNetwork,
    optimizer: torch.optim.Optimizer,
    batch: tuple[torch.Tensor, ...],
    config: TrainConfig,
    step: int,
    noise_gen: torch.Generator,
) -> None:
    """One double-DQN step on a replay minibatch, at the step's linearly annealed learning rate.

    The online network picks the next action and the target network values it; the online side
    uses one noise sample for both its passes, the target side its own.
    """
    frac = min(1.0, step / config.total_steps)
    for group in optimizer.param_groups:
        group["lr"] = config.lr + frac * (config.lr_final - config.lr)
    b_obs, b_act, b_rew, b_next, b_term = batch
    online_noise = q_net.sample_noise(noise_gen)
    with torch.no_grad():
        next_action = q_net(b_next, online_noise).argmax(dim=1, keepdim=True)
        next_q = target_net(b_next, target_net.sample_noise(noise_gen)).gather(1, next_action)
        target = b_rew + config.gamma * (1.0 - b_term) * next_q.squeeze(1)
    q_taken = q_net(b_obs, online_noise).gather(1, b_act.unsqueeze(1)).squeeze(1)
    loss = nn.functional.smooth_l1_loss(q_taken, target)
    optimizer.zero_grad()
    loss.backward()
    nn.utils.clip_grad_norm_(q_net.parameters(), config.max_grad_norm)
    optimizer.step()


def print_progress(step: int, mean: float, tuning: Tuning, returns: list[float], started: float):
    recent = np.mean(returns[-20:]) if returns else float("nan")
    print(
        f"step {step:>8d}  eval {mean:8.1f}  best {tuning.best_return:8.1f}@{tuning.best_step}  "
        f"train(20) {recent:8.1f}  {time.perf_counter() - started:6.0f}s",
        flush=True,
    )


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
    tuning = Tuning(
        config.seed + TUNING_SEED_OFFSET, config.eval_episodes, copy.deepcopy(q_net.state_dict())
    )

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

        learning = step > config.learning_starts
        if learning and step % config.train_freq == 0:
            batch = buffer.sample(config.batch_size, np_rng)
            update(q_net, target_net, optimizer, batch, config, step, noise_gen)
        if step % config.target_sync == 0:
            target_net.load_state_dict(q_net.state_dict())
        if learning and step % config.eval_every == 0:
            mean = tuning.evaluate(q_net, config, step)
            if progress:
                print_progress(step, mean, tuning, episode_returns, started)
            if mean >= config.early_stop_return:
                break
    env.close()

    q_net.load_state_dict(tuning.best_state)
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
        state_dict=tuning.best_state,
        env_id=config.env_id,
        train_config=config.as_dict(),
        final_returns=final,
        final_eval_seed=config.final_eval_seed,
        tuning=tuning.report(),
        steps_run=step,
        learning_curve=tuning.curve,
        wall_time_s=time.perf_counter() - started,
        trainer={"algorithm": "NoisyNet double DQN (oodrl)"},
    )
