"""Driving tasks registered as Gymnasium ids (see :mod:`drivelab.envs.registration`)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from drivelab.envs.metadrive import MetaDriveGym
from drivelab.envs.rewards import RewardShaping
from drivelab.envs.wrappers import FixedThrottle

# Notebook 003's CTE reward, scaled for MetaDrive's 3.5 m lanes: full reward on the centre
# line, 0 at 1.5 m (the car's edge touches the lane line), -10 and the end of the episode on a
# collision, off the road, or further than 1.5 m from the centre. A small progress term keeps
# "park on the centre line" from being optimal.
LANE_FOLLOW_REWARD = {"cte": {"weight": 1.0, "scale": 1.0, "max_cte": 1.5, "crash": -10.0},
                      "progress": {"weight": 1.0, "scale": 100.0}}


def lane_follow(render_mode: str | None = None, reward: dict[str, Any] | None = None,
                fixed_throttle: float | None = None, **metadrive: Any) -> gym.Env:
    """MetaDrive lane following: empty roads (no traffic), state observations, the CTE reward.

    Args:
        reward: reward terms replacing :data:`LANE_FOLLOW_REWARD`.
        fixed_throttle: steering-only 1-D actions at this throttle (notebook 003 used 0.3).
        **metadrive: MetaDrive config overrides (num_scenarios, map, horizon, ...).
    """
    config = {"start_seed": 1000, "num_scenarios": 100, "traffic_density": 0.0, **metadrive}
    env: gym.Env = MetaDriveGym(render_mode=render_mode, **config)
    env = RewardShaping(env, reward or LANE_FOLLOW_REWARD)
    if fixed_throttle is not None:
        env = FixedThrottle(env, fixed_throttle)
    return env
