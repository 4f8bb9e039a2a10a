"""A tiny constrained env with a known answer, for the constrained algorithms' learning tests:
``constrained_env:ThreeLanes-v0``.

A road of 4 stretches; at each the car picks a lane with its one action a in [-1, 1]:

    lane          action           reward/step  cost/step  return over 4  cost over 4
    shoulder      a < -1/3            1.25         0            5            0
    middle        -1/3 <= a <= 1/3    2.0          0.25         8            1
    fast          a > 1/3             2.5          1.0         10            4

Unconstrained, the fast lane is best (return 10, cost 4). With ``cost_limit`` 1 the constrained
optimum is the middle lane at every step (return 8, cost 1), and it is unique: any fast stretch
with a middle one exceeds the limit, and one fast stretch with three on the shoulder returns 6.25.
Per step the Lagrangian r - lambda c is 2.5 - lambda (fast), 2 - 0.25 lambda (middle) and 1.25
(shoulder): the middle lane wins for any lambda in (2/3, 3), a wide basin, so a Lagrangian method
settles on it without oscillating; a fixed cost penalty w in that window does too.

The observation is the one-hot stretch index; ``info["cost"]`` is the step's cost. No randomness.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

STRETCHES = 4
LANES = ((1.25, 0.0), (2.0, 0.25), (2.5, 1.0))   # (reward, cost) per step: shoulder, middle, fast


def lane_of(action: float) -> int:
    return 0 if action < -1 / 3 else (1 if action <= 1 / 3 else 2)


class ThreeLanes(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self):
        self.observation_space = gym.spaces.Box(0.0, 1.0, (STRETCHES,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.t = 0

    def _obs(self) -> np.ndarray:
        obs = np.zeros(STRETCHES, np.float32)
        obs[min(self.t, STRETCHES - 1)] = 1.0
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {"cost": 0.0}

    def step(self, action):
        reward, cost = LANES[lane_of(float(np.asarray(action).reshape(-1)[0]))]
        self.t += 1
        terminated = self.t >= STRETCHES
        info = {"cost": cost, "route_completion": self.t / STRETCHES, "success": terminated}
        return self._obs(), reward, terminated, False, info


gym.register("ThreeLanes-v0", entry_point=ThreeLanes)
