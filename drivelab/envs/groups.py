"""N envs as G groups that step on their own: one vector env per group, and a wait for whichever
group has its results first.

A lockstep vector env leaves its workers idle twice per step: while the trainer chooses the next
actions, and while the slowest env finishes (a MetaDrive reset builds a new map; the other
workers wait for it). With groups the trainer chooses one group's actions while the others
simulate, and a slow env holds back only its own group. Each group keeps its own row in the
rollout (:class:`drivelab.training.collection.rollout.RolloutCollector`), so the data of every env is the same
whatever order the groups answer in; only wall time changes.

Groups need subprocess envs (``backend: async``); in-process (sync) and Ray envs form one group.
"""

from __future__ import annotations

from collections.abc import Callable
from multiprocessing.connection import wait

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv

from drivelab.envs import make_vector_env
from drivelab.envs.config import EnvConfig


class EnvGroups:
    """``cfg.num_envs`` envs split into ``num_groups`` vector envs of (nearly) equal size.

    ``slices[g]`` are group g's env indices within 0..N-1. The protocol is explicit:
    :meth:`send` actions to a group, :meth:`wait_any` for one of the groups that were sent
    actions, :meth:`receive` its step.
    """

    def __init__(self, cfg: EnvConfig, num_groups: int, *, autoreset_mode: AutoresetMode,
                 on_restart: Callable[[int], None] | None = None, wrapper: Callable[[gym.Env], gym.Env] | None = None):
        bounds = np.linspace(0, cfg.num_envs, num_groups + 1).round().astype(int)
        self.slices = [slice(int(lo), int(hi)) for lo, hi in zip(bounds[:-1], bounds[1:])]
        self.envs: list[VectorEnv] = []
        try:
            for envs in self.slices:
                self.envs.append(make_vector_env(cfg, envs.stop - envs.start, autoreset_mode=autoreset_mode,
                                                 on_restart=on_restart, wrapper=wrapper))
        except BaseException:
            self.close()
            raise
        self.num_envs = cfg.num_envs
        self.timeout = cfg.step_timeout
        first = self.envs[0]
        self.single_observation_space: gym.Space = first.single_observation_space
        self.single_action_space: gym.Space = first.single_action_space
        self._pending: list[np.ndarray | None] = [None] * num_groups   # actions of in-process groups

    def __len__(self) -> int:
        return len(self.envs)

    def reset(self, seeds: list[int | None]) -> np.ndarray:
        """Reset every env with its seed; the (N, ...) first observations."""
        return np.concatenate([envs.reset(seed=seeds[s])[0] for envs, s in zip(self.envs, self.slices)])

    def send(self, group: int, actions: np.ndarray) -> None:
        """Start group ``group``'s step with its (n_g, ...) actions; returns at once for subprocess envs."""
        envs = self.envs[group]
        if hasattr(envs, "step_async"):
            envs.step_async(actions)
        else:
            self._pending[group] = actions

    def wait_any(self, in_flight: list[int]) -> int:
        """One of the groups in ``in_flight`` whose step results are all there (blocks until one is)."""
        if len(in_flight) == 1:
            return in_flight[0]
        while True:
            unanswered = []
            for group in in_flight:
                pipes = [pipe for pipe in self.envs[group].result_pipes() if not pipe.poll()]
                if not pipes:
                    return group
                unanswered += pipes
            if not wait(unanswered, timeout=self.timeout):
                return in_flight[0]  # nobody answered in time: receive() times out and restarts that group

    def receive(self, group: int) -> tuple:
        """Group ``group``'s step: (obs, reward, terminated, truncated, info), each for its n_g envs."""
        envs = self.envs[group]
        if hasattr(envs, "step_async"):
            return envs.step_wait()
        actions, self._pending[group] = self._pending[group], None
        return envs.step(actions)

    def close(self) -> None:
        """Close every group, even when one of them fails to close."""
        for envs in self.envs:
            try:
                envs.close()
            except Exception:  # noqa: BLE001 - keep closing the others
                pass
