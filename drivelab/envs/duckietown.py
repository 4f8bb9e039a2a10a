"""Duckietown camera lane following behind the Gymnasium API (an optional extra).

``duckietown-gym-daffy`` pins ``pyglet<2`` and ``numpy<1.24`` and speaks the old gym API, so it
lives in its own environment: ``make duckietown`` creates ``.venv-duckietown`` with drivelab and
the simulator, and its OpenGL renderer needs a display (``xvfb-run`` on a headless machine).

The adapter turns the simulator's ``reset() -> obs`` / ``step() -> (obs, r, done, info)`` into
Gymnasium's five-tuple (its step limit is a truncation), drives it with [steering, throttle]
through :class:`drivelab.envs.wrappers.DifferentialDrive`, and reports the same lane geometry as
MetaDrive (``cte``, ``heading_error``, ``speed``, ``speed_along_lane``, ``collided``,
``out_of_road``), so drivelab's reward terms and metrics apply unchanged, and a ``cost`` of 1 per
step in a collision (:mod:`drivelab.envs.costs`).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import gymnasium as gym
import numpy as np

from drivelab.envs.rewards import RewardShaping
from drivelab.envs.wrappers import DifferentialDrive
from drivelab.errors import DrivelabError

INSTALL_HINT = ("Duckietown is an optional extra with its own environment: run `make duckietown`, then use "
                "`xvfb-run .venv-duckietown/bin/drivelab ...` (see README, 'Duckietown')")

# gym-duckietown's own lane reward, in drivelab's reward terms (drivelab.envs.rewards.lane_reward).
DUCKIETOWN_REWARD = {"lane": {"weight": 1.0, "w_speed": 1.0, "w_dist": 10.0, "w_col": 40.0}}


def duckietown_available() -> bool:
    """Whether the Duckietown extra (``gym_duckietown``) can be imported here."""
    import importlib.util

    return importlib.util.find_spec("gym_duckietown") is not None


class DuckietownGym(gym.Env):
    """The Duckietown simulator with Gymnasium's API and drivelab's lane-geometry info."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, map_name: str = "loop_empty", camera_width: int = 80, camera_height: int = 60,
                 max_steps: int = 500, domain_rand: bool = False, render_mode: str | None = None, **simulator: Any):
        try:
            from gym_duckietown.simulator import Simulator
        except ImportError:
            raise DrivelabError(f"gym_duckietown is not installed. {INSTALL_HINT}") from None
        logging.getLogger("gym-duckietown").setLevel(logging.WARNING)  # it logs every reset at DEBUG
        self._sim = Simulator(map_name=map_name, camera_width=camera_width, camera_height=camera_height,
                              max_steps=max_steps, domain_rand=domain_rand, **simulator)
        self.observation_space = gym.spaces.Box(0, 255, (camera_height, camera_width, 3), np.uint8)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)   # left, right wheel velocities
        self.render_mode = render_mode
        self.max_steps = max_steps

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._sim.seed(seed)
        obs = self._sim.reset()
        self._abs_cte_sum, self._steps = 0.0, 0
        return np.asarray(obs, np.uint8), self._info()

    def step(self, action):
        obs, reward, done, _ = self._sim.step(np.asarray(action, np.float32))
        self._steps += 1
        info = self._info()
        truncated = bool(done) and self._sim.step_count >= self.max_steps
        terminated = bool(done) and not truncated
        return np.asarray(obs, np.uint8), float(reward), terminated, truncated, {**info, "native_reward": float(reward)}

    def _info(self) -> dict:
        from gym_duckietown.simulator import NotInLane

        sim = self._sim
        speed = float(sim.speed)
        collided = sim.proximity_penalty2(sim.cur_pos, sim.cur_angle) < 0
        try:
            lane = sim.get_lane_pos2(sim.cur_pos, sim.cur_angle)
            # gym-duckietown measures both to the right of the lane; drivelab's are + to the left.
            cte, heading = -float(lane.dist), -float(lane.angle_rad)
            out_of_road = False
        except NotInLane:
            cte, heading, out_of_road = 0.0, 0.0, True
        if self._steps:
            self._abs_cte_sum += abs(cte)
        # No route here (the loop has no destination), so no success or route completion.
        return {"cte": cte, "heading_error": heading, "speed": speed, "speed_along_lane": speed * math.cos(heading),
                "collided": bool(collided), "crash": bool(collided), "out_of_road": out_of_road,
                "cost": float(collided),  # constrained RL's cost: 1 per step in a collision (drivelab.envs.costs)
                "mean_abs_cte": self._abs_cte_sum / max(self._steps, 1)}

    def render(self):
        return self._sim.render_obs() if self.render_mode == "rgb_array" else None

    def close(self):
        self._sim.close()


def DuckietownLaneFollow(render_mode: str | None = None, **simulator: Any) -> gym.Env:
    """``drivelab/DuckietownLaneFollow-v0``: small (60x80) camera images, [steering, throttle]
    actions, gym-duckietown's lane reward (``env.reward`` replaces its terms)."""
    env: gym.Env = DuckietownGym(render_mode=render_mode, **simulator)
    env = RewardShaping(env, DUCKIETOWN_REWARD)
    return DifferentialDrive(env)
