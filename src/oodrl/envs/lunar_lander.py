"""LunarLander-v3 adapter: clean rollouts plus the simulator hooks online faults need.

The observation is a fixed affine map of the lander body's position, velocity, angle and
angular velocity (gymnasium's `LunarLander.step`), so a desired observation can be written
back exactly by inverting that map; the legs move rigidly with the lander.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# Constants of gymnasium.envs.box2d.lunar_lander, which the observation map uses.
_FPS = 50.0
_SCALE = 30.0
_HALF_W = 600 / _SCALE / 2
_HALF_H = 400 / _SCALE / 2
_LEG_DOWN = 18 / _SCALE


class LunarLanderAdapter:
    """Creates environments and exposes one live environment's state to online faults."""

    env_id = "LunarLander-v3"
    state_dim = 8
    n_actions = 4

    def __init__(self, **env_kwargs: Any) -> None:
        self.env_kwargs = env_kwargs

    def make(self):
        import gymnasium as gym

        # Never a render mode: rendering keeps flame particles alive and slows every step.
        return gym.make(self.env_id, disable_env_checker=True, **self.env_kwargs)

    @staticmethod
    def version() -> str:
        import gymnasium

        return gymnasium.__version__

    def handle(self, env) -> LunarLanderHandle:
        return LunarLanderHandle(env.unwrapped)


class LunarLanderHandle:
    """Read and write the observation-level state of one live LunarLander."""

    def __init__(self, lander_env) -> None:
        self._env = lander_env

    def observation(self) -> np.ndarray:
        env = self._env
        pos, vel = env.lander.position, env.lander.linearVelocity
        return np.array(
            [
                (pos.x - _HALF_W) / _HALF_W,
                (pos.y - (env.helipad_y + _LEG_DOWN)) / _HALF_H,
                vel.x * _HALF_W / _FPS,
                vel.y * _HALF_H / _FPS,
                env.lander.angle,
                20.0 * env.lander.angularVelocity / _FPS,
                1.0 if env.legs[0].ground_contact else 0.0,
                1.0 if env.legs[1].ground_contact else 0.0,
            ],
            dtype=np.float32,
        )

    def write_observation(self, observation: np.ndarray) -> np.ndarray:
        """Move the lander (and its legs rigidly with it) so the observation reads back as given.

        Leg contacts are outputs of the contact solver and cannot be written; they are kept.
        The reward shaping baseline is recomputed so the next reward describes the written state.
        """
        env = self._env
        obs = np.asarray(observation, dtype=np.float64)
        lander = env.lander
        old_pos = np.array([lander.position.x, lander.position.y])
        old_vel = np.array([lander.linearVelocity.x, lander.linearVelocity.y])
        old_angle, old_omega = lander.angle, lander.angularVelocity

        new_pos = np.array(
            [obs[0] * _HALF_W + _HALF_W, obs[1] * _HALF_H + env.helipad_y + _LEG_DOWN]
        )
        new_vel = np.array([obs[2] * _FPS / _HALF_W, obs[3] * _FPS / _HALF_H])
        new_angle, new_omega = float(obs[4]), float(obs[5]) * _FPS / 20.0

        turn = new_angle - old_angle
        rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
        for leg in env.legs:
            offset = np.array([leg.position.x, leg.position.y]) - old_pos
            leg_pos = new_pos + rotation @ offset
            leg.transform = ((float(leg_pos[0]), float(leg_pos[1])), leg.angle + turn)
            leg_vel = np.array([leg.linearVelocity.x, leg.linearVelocity.y]) + new_vel - old_vel
            leg.linearVelocity = (float(leg_vel[0]), float(leg_vel[1]))
            leg.angularVelocity = leg.angularVelocity + new_omega - old_omega
        lander.transform = ((float(new_pos[0]), float(new_pos[1])), new_angle)
        lander.linearVelocity = (float(new_vel[0]), float(new_vel[1]))
        lander.angularVelocity = new_omega
        lander.awake = True

        realised = self.observation()
        if env.prev_shaping is not None:
            env.prev_shaping = _shaping(realised)
        return realised


def _shaping(s: np.ndarray) -> float:
    """LunarLander's potential-based reward shaping term of an observation."""
    return float(
        -100 * np.sqrt(s[0] * s[0] + s[1] * s[1])
        - 100 * np.sqrt(s[2] * s[2] + s[3] * s[3])
        - 100 * abs(s[4])
        + 10 * s[6]
        + 10 * s[7]
    )


class HeuristicPolicy:
    """gymnasium's hand-written LunarLander controller: a torch-free policy for tests."""

    state_dim = 8
    n_actions = 4
    sha256 = "heuristic"

    def act(self, observations: np.ndarray, rngs=None) -> np.ndarray:
        from gymnasium.envs.box2d.lunar_lander import heuristic

        return np.array([heuristic(_DISCRETE_ENV, o) for o in observations], dtype=np.int64)


class _DiscreteEnv:
    """Stands in for the env in gymnasium's heuristic(), which only asks `continuous`."""

    continuous = False

    @property
    def unwrapped(self):
        return self


_DISCRETE_ENV = _DiscreteEnv()
