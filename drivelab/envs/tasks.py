"""Driving tasks registered as Gymnasium ids (see :mod:`drivelab.envs.registration`)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from drivelab.envs.metadrive import MetaDriveGym
from drivelab.envs.rewards import RewardShaping
from drivelab.envs.wrappers import CruiseControl

# The cross-track-error reward (drivelab.envs.rewards.cte_reward), scaled for MetaDrive's 3.5 m lanes: the factor 1 - (|cte|/1.5)^2 is
# 0 where the car's edge touches the lane line; -10 and the end of the episode on a collision, off
# the road, or further than 1.5 m from the centre. Paid per unit of route progress (300 for the
# whole route driven on the centre line, about MetaDrive's native scale), since with a learnable
# throttle a per-step CTE reward makes "park on the centre line" optimal.
LANE_FOLLOW_REWARD = {"cte": {"weight": 1.0, "scale": 300.0, "max_cte": 1.5, "crash": -10.0, "per": "progress"}}


def lane_follow(render_mode: str | None = None, target_speed: float | None = None, **metadrive: Any) -> gym.Env:
    """MetaDrive lane following: empty roads (no traffic), state observations, the CTE reward
    :data:`LANE_FOLLOW_REWARD` (``env.reward`` replaces its terms; ``env.fixed_throttle`` gives
    steering-only control at a constant throttle).

    Args:
        target_speed: steering-only 1-D actions, the throttle held by a speed controller at this
            speed in m/s (:class:`CruiseControl`). On MetaDrive a fixed throttle is a constant
            engine force: the car keeps speeding up.
        **metadrive: MetaDrive config overrides (num_scenarios, map, horizon, ...).
    """
    config = {"start_seed": 1000, "num_scenarios": 100, "traffic_density": 0.0, **metadrive}
    env: gym.Env = RewardShaping(MetaDriveGym(render_mode=render_mode, **config), LANE_FOLLOW_REWARD)
    return CruiseControl(env, target_speed) if target_speed is not None else env
