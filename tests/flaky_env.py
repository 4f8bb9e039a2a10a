"""An env that fails on purpose, for testing drivelab's supervision of env workers
(:mod:`drivelab.envs.supervised`): ``flaky_env:Flaky-v0``.

Gymnasium's "module:EnvId" form imports this module first, which registers ``Flaky-v0``; every
process that builds the env (a CLI subprocess, a spawned env worker, a Ray actor) therefore needs
this directory on its path (``PYTHONPATH``, or the parent's ``sys.path`` for spawned workers).

CartPole whose ``step`` raises, kills its process, or hangs once, at step ``at_step`` of the
worker's life, the first time it runs with a given ``marker`` file (the file records that the
failure happened, so the restarted worker behaves); or, with ``fail="nan"``, whose rewards are
NaN from ``at_step`` on.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import gymnasium as gym


def importable_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """Environment variables (``os.environ`` by default) for a child process that must import this
    module, such as a CLI run or a Ray worker: this directory goes first on PYTHONPATH."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(Path(__file__).parent), env.get("PYTHONPATH")]))
    return env


class FlakyEnv(gym.Wrapper):
    def __init__(self, fail: str = "raise", at_step: int = 50, marker: str = "", render_mode: str | None = None):
        super().__init__(gym.make("CartPole-v1", render_mode=render_mode))
        self.fail, self.at_step, self.marker = fail, at_step, Path(marker) if marker else None
        self._steps = 0

    def step(self, action):
        self._steps += 1
        if self.fail == "nan" and self._steps >= self.at_step:
            obs, _, terminated, truncated, info = self.env.step(action)
            return obs, float("nan"), terminated, truncated, info
        if self._steps == self.at_step and self.marker is not None and not self.marker.exists():
            self.marker.write_text(self.fail)
            if self.fail == "raise":
                raise RuntimeError("the simulator crashed (on purpose)")
            if self.fail == "die":
                os._exit(1)
            time.sleep(3600)  # hang
        return self.env.step(action)


if "Flaky-v0" not in gym.registry:
    gym.register(id="Flaky-v0", entry_point=FlakyEnv)
