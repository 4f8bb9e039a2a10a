"""Deterministic evaluation of a policy or a checkpoint, with driving metrics.

Episode ``k`` (0-based) is reset with seed ``seed + k``, so an evaluation is reproducible and,
on MetaDrive, ``MetaDrive-validation-v0`` with ``seed=0`` visits scenarios 0, 1, ..., N-1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from drivelab.checkpoint import load_checkpoint, restore
from drivelab.config import EnvConfig, build_config
from drivelab.envs import env_spaces, make_vector_env
from drivelab.episodes import episode_info
from drivelab.errors import DrivelabError


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
                 device: torch.device | str = "cpu") -> EvalResult:
    """Play exactly ``episodes`` episodes (episode k with seed ``seed + k``) on ``envs``, which must
    use ``AutoresetMode.DISABLED``."""
    n = envs.num_envs
    next_episode = min(n, episodes)
    episode_of = np.arange(n)                  # which episode env i is playing (>= episodes: idle)
    obs, _ = envs.reset(seed=[seed + i for i in range(n)])
    returns = np.zeros(episodes)
    lengths = np.zeros(episodes, np.int64)
    metrics: dict[str, np.ndarray] = {}     # metric -> (episodes,), for those the env reports
    running_return = np.zeros(n)
    running_length = np.zeros(n, np.int64)
    finished = 0
    while finished < episodes:
        action = policy.act(torch.as_tensor(obs, device=device), deterministic=deterministic)
        obs, reward, terminated, truncated, info = envs.step(policy.to_env(action))
        running_return += reward
        running_length += 1
        done = terminated | truncated
        if not done.any():
            continue
        reset_seeds: list[int | None] = [None] * n
        for i in np.flatnonzero(done):
            k = episode_of[i]
            if k < episodes:
                returns[k], lengths[k] = running_return[i], running_length[i]
                for name, value in episode_info(info, i).items():
                    metrics.setdefault(name, np.zeros(episodes))[k] = value
                finished += 1
            episode_of[i] = next_episode
            next_episode += 1
            reset_seeds[i] = seed + int(episode_of[i])
        running_return[done] = 0.0
        running_length[done] = 0
        if finished < episodes:
            obs, _ = envs.reset(seed=reset_seeds, options={"reset_mask": done})
    return EvalResult(returns, lengths, metrics)


def evaluate_checkpoint(path: str | Path, episodes: int = 10, env_id: str | None = None,
                        env_kwargs: dict | None = None, num_envs: int | None = None, seed: int = 0,
                        deterministic: bool = True) -> tuple[EvalResult, EnvConfig, Path]:
    """Load a checkpoint (or a run's latest) and evaluate its policy.

    ``env_id`` evaluates on another env (e.g. train on ``MetaDrive-100envs-v0``, evaluate on
    ``MetaDrive-validation-v0``); the training env's kwargs are then dropped, as they may
    redefine that env's scenario range, and ``env_kwargs`` are used instead.
    """
    from drivelab.algos import get_algo

    if episodes < 1:
        raise DrivelabError(f"--episodes must be >= 1, got {episodes}")
    ckpt = load_checkpoint(path)
    cfg = build_config(ckpt.state["config"], where=f"config in {ckpt.path}")
    env_cfg = cfg.env
    if env_id is not None and env_id != env_cfg.id:
        env_cfg.id, env_cfg.kwargs = env_id, {}
    env_cfg.kwargs.update(env_kwargs or {})
    env_cfg.num_envs = max(1, min(num_envs or env_cfg.num_envs, episodes))
    obs_space, act_space = env_spaces(env_cfg)
    policy = get_algo(cfg.algo).build_policy(cfg, obs_space, act_space)
    restore(ckpt, {"policy": policy}, rng=False)
    policy.eval()
    envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED)
    try:
        result = run_episodes(envs, policy, episodes, seed=seed, deterministic=deterministic)
    finally:
        envs.close()
    return result, env_cfg, ckpt.path
