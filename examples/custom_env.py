"""Bring your own environment: a Gymnasium env class and a reward term of your own, in your own
module, trained, evaluated and exported by drivelab.

    python examples/custom_env.py --steps 20000          # train PPO, then evaluate 10 episodes

The same from the command line, in this folder (drivelab finds ``custom_env`` in the current
directory; ``--env module:Class`` is saved in the run's config, so eval, resume and export find it):

    drivelab train --algo ppo --env custom_env:LaneKeepingToy --steps 20000 --run-dir runs/toy
    drivelab eval runs/toy --episodes 10
    drivelab export runs/toy --format onnx --out runs/toy-onnx

Env workers run in subprocesses, so the class must live in an importable module (this file is
imported as ``custom_env``), not in ``__main__`` or a notebook cell.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np


class LaneKeepingToy(gym.Env):
    """A car at a constant 10 m/s on a straight lane, seen as (lateral offset m, heading error
    rad); the action steers, in [-1, 1] (a yaw rate of up to 0.5 rad/s). Reward 1 per step on
    the lane; the episode ends terminated off the lane (|offset| > 2 m) and truncated after 200
    steps of 0.1 s. It reports ``cte`` and ``speed`` in ``info`` like drivelab's driving envs,
    so the driving reward terms apply to it."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    metadata = {"render_modes": []}
    speed, dt, max_offset, max_steps = 10.0, 0.1, 2.0, 200

    def __init__(self, render_mode: str | None = None):
        self.render_mode = render_mode

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.offset, self.heading = self.np_random.uniform(-1.0, 1.0), self.np_random.uniform(-0.3, 0.3)
        self.t = 0
        return self._obs(), self._info()

    def step(self, action):
        yaw_rate = 0.5 * float(np.clip(action[0], -1.0, 1.0)) + self.np_random.normal(0.0, 0.05)  # a gusty road
        self.heading += yaw_rate * self.dt
        self.offset += self.speed * np.sin(self.heading) * self.dt
        self.t += 1
        off_lane = abs(self.offset) > self.max_offset
        return self._obs(), 1.0, off_lane, self.t >= self.max_steps and not off_lane, self._info()

    def _obs(self) -> np.ndarray:
        return np.array([self.offset, self.heading], np.float32)

    def _info(self) -> dict:
        return {"cte": self.offset, "speed": self.speed}


def centred(info: dict, prev: dict | None, width: float = 0.5) -> float:
    """A reward term of your own (``custom_env:centred`` in a config): 1 within ``width`` m of
    the lane centre, else 0. drivelab hands it the step's info with the observation and action."""
    return 1.0 if abs(info["observation"][0]) < width else 0.0


def main() -> None:
    import drivelab

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--run-dir", default="runs/custom_env")
    args = parser.parse_args()
    # The env's own reward (1 per step on the lane) plus half a point per step near the centre.
    env = {"id": "custom_env:LaneKeepingToy", "reward": {"native": {}, "custom_env:centred": {"weight": 0.5}}}
    # PPO's 4 envs x 250 steps: 1000 env steps an update
    result = drivelab.train("ppo", env, steps=args.steps, seed=0, run_dir=args.run_dir, ppo={"num_steps": 250})
    policy = drivelab.load(result.run_dir)
    summary = drivelab.evaluate(policy, episodes=10)
    print(f"{summary['length_mean']:.0f} of 200 steps on the lane on average, return {summary['return_mean']:.1f} "
          f"(10 episodes); run in {result.run_dir}")


if __name__ == "__main__":
    main()
