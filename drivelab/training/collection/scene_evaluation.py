"""Evaluation on multi-agent scenes: every car driven by the shared policy, metrics over the cars.

An evaluation plays ``episodes`` scene episodes (scene episode k reset with seed ``seed + k``, as
single-agent evaluation does) on :class:`~drivelab.envs.multiagent.AgentSlots` envs and counts
every car that drove in them as one agent episode. The measures are those of MetaDrive's
multi-agent benchmark (CoPO, Peng et al. 2021, sec. 5):

* ``success_rate``, ``crash_rate``, ``out_of_road_rate``, ``timeout_rate``, ``route_completion``:
  means over the cars' episodes (a car ends in one of arrival, crash, leaving the road, its step limit);
* ``crashes_per_episode``: cars that crashed per scene episode (CoPO's safety: fewer is safer);
* ``efficiency``: (arrivals - failures) per 1,000 env steps of the scene (CoPO's efficiency: how
  fast the scene lets cars through, failures counting against it);
* ``live_agents``: the mean number of cars on the road per step;
* ``return_mean``, ``return_std``, ``length_mean``, ``cost``: per car episode.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from tqdm.auto import tqdm

from drivelab.envs import EnvConfig, make_vector_env
from drivelab.envs.multiagent import OUTCOMES
from drivelab.errors import DrivelabError
from drivelab.training.collection.agents import slot_arrays


@dataclass
class SceneResult:
    """The cars' episodes of an evaluation, and the scenes' step and car counts."""
    scenes: int                                           # scene episodes played
    scene_steps: int = 0                                  # env steps of those scenes together
    car_steps: int = 0                                    # car decisions (live cars summed over steps)
    returns: list[float] = field(default_factory=list)    # one per car episode
    lengths: list[int] = field(default_factory=list)
    outcomes: dict[str, list[float]] = field(default_factory=dict)  # success, crash, ... -> per car episode

    def add_car(self, ret: float, length: int, outcome: dict[str, float]) -> None:
        self.returns.append(ret)
        self.lengths.append(length)
        for name, value in outcome.items():
            self.outcomes.setdefault(name, []).append(value)

    def summary(self) -> dict[str, float]:
        cars = len(self.returns)
        out: dict[str, float] = {"episodes": self.scenes, "agent_episodes": cars}
        if cars:
            out.update({"return_mean": float(np.mean(self.returns)), "return_std": float(np.std(self.returns)),
                        "length_mean": float(np.mean(self.lengths))})
            out.update({name: float(np.mean(values)) for name, values in self.outcomes.items()})
        else:
            out.update({"return_mean": float("nan"), "return_std": float("nan"), "length_mean": float("nan")})
        arrived = float(np.sum(self.outcomes.get("success_rate", [])))
        failed = float(np.sum(self.outcomes.get("crash_rate", [])) + np.sum(self.outcomes.get("out_of_road_rate", [])))
        out["crashes_per_episode"] = float(np.sum(self.outcomes.get("crash_rate", []))) / max(self.scenes, 1)
        out["efficiency"] = 1000.0 * (arrived - failed) / max(self.scene_steps, 1)
        out["live_agents"] = self.car_steps / max(self.scene_steps, 1)
        return out


@torch.no_grad()
def play_scenes(env_cfg: EnvConfig, policy, episodes: int, seed: int = 0, deterministic: bool = True,
                recorder=None, progress: str | None = None) -> SceneResult:
    """``episodes`` scene episodes of ``policy`` driving every car (see the module docstring);
    ``recorder`` films scene 0's episodes from above, ``progress`` labels a bar of scene episodes."""
    if episodes < 1:
        raise DrivelabError(f"the number of evaluation episodes must be >= 1, got {episodes}")
    n = 1 if recorder is not None else max(1, min(env_cfg.num_envs, episodes))
    envs = make_vector_env(env_cfg, n, autoreset_mode=AutoresetMode.DISABLED,
                           render_mode="rgb_array" if recorder is not None else None)
    bar = tqdm(total=episodes, desc=progress, unit="episode", dynamic_ncols=True, disable=progress is None,
               mininterval=0.5, smoothing=0.1)
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            return _play(envs, policy, episodes, seed, deterministic, recorder, bar)
    finally:
        bar.close()
        envs.close()


def _play(envs, policy, episodes: int, seed: int, deterministic: bool, recorder, bar) -> SceneResult:
    n, k = envs.num_envs, envs.single_observation_space.shape[0]
    result = SceneResult(episodes)
    scene_of = np.arange(n)                   # the scene episode each env plays (>= episodes: idle)
    running = np.zeros((2, n * k))            # each slot's car: return, length
    cost = np.zeros(n * k)
    obs, info = envs.reset(seed=[seed + i for i in range(n)])
    if recorder is not None:
        recorder.start(envs, info, 0)
    finished, next_scene = 0, n
    while finished < episodes:
        action = policy.act(torch.as_tensor(obs.reshape(n * k, -1)), deterministic=deterministic)
        obs, reward, _, _, info = envs.step(policy.to_env(action).reshape(n, k, -1))
        slots = slot_arrays(info, n, k, envs.single_observation_space.shape[1])
        playing = np.repeat(scene_of < episodes, k)
        acted = slots["acted"] & playing
        running += np.stack([np.where(acted, slots["agent_reward"], 0.0), acted])
        cost += np.where(acted, slots["agent_cost"], 0.0)
        result.scene_steps += int((scene_of < episodes).sum())
        result.car_steps += int(acted.sum())
        for slot in np.flatnonzero(acted & (slots["agent_terminated"] | slots["agent_truncated"])):
            outcome = {f"{name}_rate": float(slots[name][slot]) for name in OUTCOMES}
            outcome.update(route_completion=float(slots["route_completion"][slot]), cost=float(cost[slot]))
            result.add_car(float(running[0, slot]), int(running[1, slot]), outcome)
            running[:, slot], cost[slot] = 0.0, 0.0
        ended = np.asarray(info["scene_end"], bool) & (scene_of < episodes)
        if recorder is not None:
            recorder.step(envs, None, float(reward[0]), {}, bool(ended[0]))
        if not ended.any():
            continue
        finished += int(ended.sum())
        bar.update(int(ended.sum()))
        seeds: list[int | None] = [None] * n
        for i in np.flatnonzero(ended):
            scene_of[i], seeds[i] = next_scene, seed + next_scene
            next_scene += 1
        if finished < episodes:  # a scene that ended restarts with its evaluation seed
            obs, info = envs.reset(seed=seeds, options={"reset_mask": ended})
            running[:, np.repeat(ended, k)] = 0.0
            if recorder is not None and ended[0]:
                recorder.start(envs, info, scene_of[0])
    if recorder is not None:
        recorder.close()
    return result
