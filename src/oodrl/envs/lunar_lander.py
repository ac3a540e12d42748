"""LunarLander-v3 and LunarLanderContinuous-v3: one lander, two action spaces.

The observation is a fixed affine map of the lander body's position, velocity, angle and
angular velocity (gymnasium's `LunarLander.step`), so the state vector is those six observation
coordinates, and a desired state is written back by inverting the map; the legs move rigidly
with the lander. Leg contacts are outputs of the contact solver, not state: they are not written.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from oodrl.core.adapter import EnvironmentAdapter, SimulatorHandle

if TYPE_CHECKING:
    import gymnasium as gym

# Constants of gymnasium.envs.box2d.lunar_lander, which the observation map uses.
_FPS = 50.0
_SCALE = 30.0
_HALF_W = 600 / _SCALE / 2
_HALF_H = 400 / _SCALE / 2
_LEG_DOWN = 18 / _SCALE


class LunarLanderAdapter(EnvironmentAdapter):
    """Gymnasium's `LunarLander-v3`: 4 discrete actions (no-op, left, main, right engine)."""

    env_id = "LunarLander-v3"

    def handle(self, env: gym.Env) -> LunarLanderHandle:
        return LunarLanderHandle(env.unwrapped)


class LunarLanderContinuousAdapter(LunarLanderAdapter):
    """`LunarLanderContinuous-v3`: (main, lateral) engine throttles in [-1, 1]."""

    env_id = "LunarLanderContinuous-v3"


class LunarLanderHandle(SimulatorHandle):
    """The lander's body coordinates in observation units.

    Box2D stores positions and velocities in float32, and the observation rounds them to
    float32, so a written state reads back to within float32 rounding, not bit for bit.
    """

    state_names = ("x", "y", "vx", "vy", "angle", "angular_velocity")

    def __init__(self, lander_env: gym.Env) -> None:
        self._env = lander_env

    def read_state(self) -> np.ndarray:
        # Rounded to float32 first, exactly as the observation is, so a fault that scales state
        # increments computes with the very numbers the policy saw.
        return self._observation()[:6].astype(np.float64)

    def _observation(self) -> np.ndarray:
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

    def write_state(self, state: np.ndarray) -> np.ndarray:
        """Move the lander (and its legs rigidly with it) to the given body coordinates.

        The simulator's reward-shaping baseline is kept: the next step's reward charges the
        write's potential change with the step's own, so an episode's shaping telescopes to its
        true total under a dynamics fault (resetting the baseline to the written state charged
        no step with it: +490 recorded against −53 true at σ = 1 of dynamics_scaling).
        """
        env = self._env
        s = np.asarray(state, dtype=np.float64)
        lander = env.lander
        old_pos = np.array([lander.position.x, lander.position.y])
        old_vel = np.array([lander.linearVelocity.x, lander.linearVelocity.y])
        old_angle, old_omega = lander.angle, lander.angularVelocity

        new_pos = np.array([s[0] * _HALF_W + _HALF_W, s[1] * _HALF_H + env.helipad_y + _LEG_DOWN])
        new_vel = np.array([s[2] * _FPS / _HALF_W, s[3] * _FPS / _HALF_H])
        new_angle, new_omega = float(s[4]), float(s[5]) * _FPS / 20.0

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

        return self._observation()


def _shaping(s: np.ndarray) -> float:
    """LunarLander's potential-based reward shaping term of an observation."""
    return float(
        -100 * np.sqrt(s[0] * s[0] + s[1] * s[1])
        - 100 * np.sqrt(s[2] * s[2] + s[3] * s[3])
        - 100 * abs(s[4])
        + 10 * s[6]
        + 10 * s[7]
    )
