"""Deterministic evaluation of a policy or a checkpoint, with driving metrics.

Episode ``k`` (0-based) is reset with seed ``seed + k``, so an evaluation is reproducible and,
on MetaDrive, ``MetaDrive-validation-v0`` with ``seed=0`` visits scenarios 0, 1, ..., N-1.
Loading a checkpoint to evaluate it is :func:`drivelab.api.evaluate_checkpoint`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from drivelab.envs import EnvConfig, make_vector_env
from drivelab.errors import DrivelabError
from drivelab.training.episodes import EpisodeTracker


@dataclass
class EvalResult:
    returns: np.ndarray                      # (episodes,)
    lengths: np.ndarray                      # (episodes,)
    metrics: dict[str, np.ndarray] = field(default_factory=dict)  # driving metric -> (episodes,)

    def summary(self) -> dict[str, float]:
        out = {
            "episodes": int(len(self.returns)),
            "return_mean": float(np.mean(self.returns)),
            "return_std": float(np.std(self.returns)),
            "length_mean": float(np.mean(self.lengths)),
        }
        out.update({name: float(np.mean(values)) for name, values in self.metrics.items()})
        return out


@torch.no_grad()
def run_episodes(envs: VectorEnv, policy, episodes: int, seed: int = 0, deterministic: bool = True,
                 device: torch.device | str = "cpu", recorder=None) -> EvalResult:
    """Play exactly ``episodes`` episodes (episode k with seed ``seed + k``) on ``envs``, which must
    use ``AutoresetMode.DISABLED``. ``policy`` has ``act(obs, deterministic)`` and ``to_env(action)``.
    ``recorder`` (:class:`drivelab.training.video.Recorder`) films env 0's episodes: it is handed the
    envs after every reset and step."""
    if episodes < 1:
        raise DrivelabError(f"the number of evaluation episodes must be >= 1, got {episodes}")
    n = envs.num_envs
    episode_of = np.arange(n)                  # which episode env i is playing (>= episodes: idle)
    next_episode = n
    tracker = EpisodeTracker(n)
    returns = np.zeros(episodes)
    lengths = np.zeros(episodes, np.int64)
    metrics: dict[str, np.ndarray] = {}        # metric -> (episodes,), for those the env reports
    finished = 0
    obs, info = envs.reset(seed=[seed + i for i in range(n)])
    if recorder is not None:
        recorder.start(envs, info, episode_of[0])
    while finished < episodes:
        action = policy.act(torch.as_tensor(obs, device=device), deterministic=deterministic)
        env_action = policy.to_env(action)
        obs, reward, terminated, truncated, info = envs.step(env_action)
        done = terminated | truncated
        if recorder is not None:
            recorder.step(envs, env_action[0], reward[0], info, bool(done[0]))
        ended = tracker.step(reward, done, info)
        if not ended:
            continue
        reset_seeds: list[int | None] = [None] * n
        for episode in ended:
            k = episode_of[episode.env]
            if k < episodes:
                returns[k], lengths[k] = episode.ret, episode.length
                for name, value in episode.metrics.items():
                    metrics.setdefault(name, np.zeros(episodes))[k] = value
                finished += 1
            episode_of[episode.env] = next_episode
            reset_seeds[episode.env] = seed + next_episode
            next_episode += 1
        if finished < episodes:
            obs, info = envs.reset(seed=reset_seeds, options={"reset_mask": done})
            if recorder is not None and done[0]:
                recorder.start(envs, info, episode_of[0])
    if recorder is not None:
        recorder.close()
    return EvalResult(returns, lengths, metrics)


def play(env_cfg: EnvConfig, policy, episodes: int, seed: int = 0, deterministic: bool = True,
         wrapper=None, recorder=None) -> EvalResult:
    """``episodes`` episodes of ``policy`` on a vector env built from ``env_cfg`` (then closed);
    with a ``recorder``, the envs render ``rgb_array`` frames for it. Sampled actions
    (``deterministic=False``) come from torch's generator seeded with ``seed``, forked so that the
    caller's generator is left as it was: the same seed gives the same episodes."""
    envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED, wrapper=wrapper,
                           render_mode="rgb_array" if recorder is not None else None)
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            return run_episodes(envs, policy, episodes, seed=seed, deterministic=deterministic, recorder=recorder)
    finally:
        envs.close()
