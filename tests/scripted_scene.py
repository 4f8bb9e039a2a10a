"""A tiny multi-agent scene with a script of arrivals and departures, for the batch interface's tests.

Each agent's observation is ``[number, t, t_born]`` (its number, the scene step, the step it
appeared), its reward at scene step t is ``number * 10 + t``, so a test can tell from any row
whose data it holds. The script (scene step: what happens after the agents act):

* reset: a0 and a1 appear;
* step 1: a0 is terminated (crashed); a2 appears (it takes a0's slot);
* step 2: a1 is truncated (its step limit);
* step 3: nothing ends; a3 appears (a1's old slot);
* step 4: a2 arrives (terminated, success);
* step 5: a3 is terminated; no agent is left: the scene episode ends.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv

# step -> (terminated, truncated, appearing)
SCRIPT = {1: (["a0"], [], ["a2"]), 2: ([], ["a1"], []), 3: ([], [], ["a3"]), 4: (["a2"], [], []),
          5: (["a3"], [], [])}


class ScriptedScene(ParallelEnv):
    metadata = {"name": "scripted_scene_v0"}
    possible_agents = ["a0", "a1", "a2", "a3"]

    def __init__(self):
        self._obs_space = gym.spaces.Box(-100.0, 100.0, (3,), np.float32)
        self._act_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.actions_seen: list[dict] = []

    def observation_space(self, agent):
        return self._obs_space

    def action_space(self, agent):
        return self._act_space

    def _obs(self, agent: str) -> np.ndarray:
        return np.array([int(agent[1:]), self.t, self.born[agent]], np.float32)

    def reset(self, seed=None, options=None):
        self.t, self.agents = 0, ["a0", "a1"]
        self.born = {"a0": 0, "a1": 0}
        return {a: self._obs(a) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        assert set(actions) == set(self.agents), (actions, self.agents)
        self.actions_seen.append(actions)
        self.t += 1
        terminated, truncated, appearing = SCRIPT[self.t]
        acted = list(self.agents)
        for agent in appearing:
            self.born[agent] = self.t
        every = acted + appearing
        obs = {a: self._obs(a) for a in every}
        rewards = {a: float(int(a[1:]) * 10 + self.t) if a in acted else 0.0 for a in every}
        terms = {a: a in terminated for a in every}
        truncs = {a: a in truncated for a in every}
        infos = {a: {"arrive_dest": a == "a2" and a in terminated, "crash": a in ("a0", "a3") and a in terminated,
                     "max_step": a in truncated, "route_completion": 0.5, "cost": 1.0 if a == "a0" else 0.0}
                 for a in every}
        self.agents = [a for a in every if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    def positions(self, agents):
        """Agent number n stands at (5 n, 0): a0 and a1 are 5 m apart, a0 and a2 10 m."""
        return np.array([[5.0 * int(a[1:]), 0.0] for a in agents])
