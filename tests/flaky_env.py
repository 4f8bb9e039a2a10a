"""An env that fails on purpose, for testing drivelab's supervision of env workers
(:mod:`drivelab.envs.supervised`): ``flaky_env:Flaky-v0``.

Gymnasium's "module:EnvId" form imports this module first, which registers ``Flaky-v0``; every
process that builds the env (a CLI subprocess, a spawned env worker, a Ray actor) therefore needs
this directory on its path (``PYTHONPATH``, or the parent's ``sys.path`` for spawned workers).

CartPole (or the env ``base``) whose ``step`` raises, kills its process, or hangs once, at step ``at_step`` of the
worker's life, the first time it runs with a given ``marker`` file (the file records that the
failure happened, so the restarted worker behaves); or, with ``fail="nan"`` (``"nan_obs"``), whose
rewards (observations) are NaN from ``at_step`` on.

``flaky_env:Tally-v0`` is a bookkeeping env for the replay collectors: its observation names the
episode and the step within it, so a test can check that every transition was stored once, in
order, with its own action and reward (and it fails like ``Flaky-v0`` when given a ``marker``).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import gymnasium as gym
import numpy as np


def importable_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """Environment variables (``os.environ`` by default) for a child process that must import this
    module, such as a CLI run or a Ray worker: this directory goes first on PYTHONPATH."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(Path(__file__).parent), env.get("PYTHONPATH")]))
    return env


class FlakyEnv(gym.Wrapper):
    def __init__(self, fail: str = "raise", at_step: int = 50, marker: str = "", render_mode: str | None = None,
                 base: str = "CartPole-v1"):
        super().__init__(gym.make(base, render_mode=render_mode))
        self.fail, self.at_step, self.marker = fail, at_step, Path(marker) if marker else None
        self._steps = 0

    def step(self, action):
        self._steps += 1
        if self.fail == "nan" and self._steps >= self.at_step:
            obs, _, terminated, truncated, info = self.env.step(action)
            return obs, float("nan"), terminated, truncated, info
        if self.fail == "nan_obs" and self._steps >= self.at_step:
            obs, reward, terminated, truncated, info = self.env.step(action)
            return np.full_like(obs, np.nan), reward, terminated, truncated, info
        if self._steps == self.at_step and self.marker is not None and not self.marker.exists():
            self.marker.write_text(self.fail)
            if self.fail == "raise":
                raise RuntimeError("the simulator crashed (on purpose)")
            if self.fail == "die":
                os._exit(1)
            time.sleep(3600)  # hang
        return self.env.step(action)


class TallyEnv(gym.Env):
    """obs = (episode id, t, episode length); reward = 10 t + a for action a at step t; an
    episode of 3-11 steps ends terminated (even ids) or truncated (odd ids). Raises once at the worker's
    ``at_step``-th step when ``marker`` names a file that does not exist yet."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, at_step: int = 0, marker: str = "", render_mode: str | None = None):
        self.at_step, self.marker = at_step, Path(marker) if marker else None
        self._steps, self.episode, self.t, self.length = 0, 0, 0, 0

    def _obs(self) -> np.ndarray:
        return np.array([self.episode, self.t, self.length], np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.episode, self.t = int(self.np_random.integers(1, 2**24)), 0
        self.length = int(self.np_random.integers(3, 12))
        return self._obs(), {}

    def step(self, action):
        self._steps += 1
        if self._steps == self.at_step and self.marker is not None and not self.marker.exists():
            self.marker.write_text("raise")
            raise RuntimeError("the simulator crashed (on purpose)")
        reward = 10.0 * self.t + float(action[0])
        self.t += 1
        ended = self.t >= self.length
        return self._obs(), reward, ended and self.episode % 2 == 0, ended and self.episode % 2 == 1, {}


def late_step_bonus(info: dict, prev: dict | None, after: int = 2) -> float:
    """A user's reward term (``flaky_env:late_step_bonus``): 1 for each step past ``after`` in
    the episode, read from the observation drivelab hands the term."""
    return 1.0 if info["observation"][1] > after else 0.0


def make_tally(**kwargs) -> TallyEnv:
    """A factory, as the API accepts one."""
    return TallyEnv(**kwargs)


if "Tally-v0" not in gym.registry:
    gym.register(id="Tally-v0", entry_point=TallyEnv)

if "Flaky-v0" not in gym.registry:
    gym.register(id="Flaky-v0", entry_point=FlakyEnv)
