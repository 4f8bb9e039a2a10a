"""Deterministic evaluation of a policy or a checkpoint, with driving metrics.

Episode ``k`` (0-based) is reset with seed ``seed + k``, so an evaluation is reproducible and,
on MetaDrive, ``MetaDrive-validation-v0`` with ``seed=0`` visits scenarios 0, 1, ..., N-1.
Loading a checkpoint to evaluate it is :func:`drivelab.api.evaluate_checkpoint`. Evaluation during
training (:mod:`drivelab.training.run.periodic_evaluation`) plays :func:`evaluation_round`, in the trainer's
process or in an :class:`EvalActor` (``eval.backend: ray``): the same code either way.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from drivelab.config import EvalConfig
from drivelab.envs import EnvConfig, make_vector_env
from drivelab.errors import DrivelabError, kill_point
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.outputs.video import Recorder


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
    ``recorder`` (:class:`drivelab.training.outputs.video.Recorder`) films env 0's episodes: it is handed the
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
                kill_point("mid-video" if recorder is not None else "mid-evaluation")
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


def evaluate_policy(envs: VectorEnv, policy: torch.nn.Module, episodes: int, seed: int,
                    device: torch.device | str = "cpu") -> dict[str, float]:
    """The summary of ``episodes`` deterministic episodes of ``policy`` in eval mode on ``envs``
    (``AutoresetMode.DISABLED``); the policy goes back to the mode it was in."""
    was_training = policy.training
    policy.eval()
    try:
        return run_episodes(envs, policy, episodes, seed=seed, device=device).summary()
    finally:
        policy.train(was_training)


def new_best(summary: dict[str, float], metric: str, best: list[float] | None) -> list[float] | None:
    """The score ``[metric, return_mean]`` of ``summary`` when it beats ``best`` (ties, frequent
    for rates over few episodes, go to the higher return), else None; None too when the env does
    not report ``metric``."""
    if metric not in summary:
        return None
    score = [summary[metric], summary["return_mean"]]
    if best is not None and score <= best:
        return None
    return score


def film_episode(env_cfg: EnvConfig, policy: torch.nn.Module, seed: int, path: Path,
                 device: torch.device | str = "cpu") -> tuple[Path, np.ndarray | None]:
    """Film one deterministic episode (seed ``seed``) of ``policy`` into ``path`` on a fresh
    rendering env; returns the file and a strip of its frames (for TensorBoard)."""
    recorder = Recorder(path, max_episodes=1, thumbnails=8)
    envs = make_vector_env(env_cfg, num_envs=1, autoreset_mode=AutoresetMode.DISABLED, render_mode="rgb_array")
    was_training = policy.training
    policy.eval()
    try:
        run_episodes(envs, policy, 1, seed=seed, device=device, recorder=recorder)
    finally:
        envs.close()
        policy.train(was_training)
    return recorder.paths[0], recorder.strip()


def evaluation_round(envs: VectorEnv, env_cfg: EnvConfig, policy: torch.nn.Module, spec: EvalConfig,
                     best: list[float] | None, video_path: Path, device: torch.device | str = "cpu"
                     ) -> tuple[dict[str, float], tuple[Path, np.ndarray | None] | None]:
    """One periodic evaluation: the summary of ``spec.episodes`` episodes on ``envs`` and, when it
    beats ``best`` and ``spec.video`` is on, (file, frame strip) of one episode filmed into
    ``video_path`` (else None)."""
    summary = evaluate_policy(envs, policy, spec.episodes, spec.seed, device)
    if not spec.video or new_best(summary, spec.best_metric, best) is None:
        return summary, None
    return summary, film_episode(env_cfg, policy, spec.seed, video_path, device)


class EvalActor:
    """The body of the evaluation actor (``eval.backend: ray``): plays :func:`evaluation_round` with
    a copy of the policy on its own envs while the trainer goes on training."""

    def __init__(self, env_cfg: EnvConfig, num_envs: int):
        self.env_cfg = env_cfg
        self.envs = make_vector_env(env_cfg, num_envs=num_envs, autoreset_mode=AutoresetMode.DISABLED)

    def evaluate(self, policy: torch.nn.Module, spec: EvalConfig, best: list[float] | None
                 ) -> tuple[dict[str, float], bytes | None, np.ndarray | None]:
        """(summary, the filmed episode's MP4 bytes or None, its frame strip or None): the actor
        may run on another machine, so the video travels as bytes."""
        with tempfile.TemporaryDirectory() as tmp:
            summary, film = evaluation_round(self.envs, self.env_cfg, policy, spec, best, Path(tmp) / "best.mp4")
            if film is None:
                return summary, None, None
            return summary, film[0].read_bytes(), film[1]

    def close(self) -> None:
        self.envs.close()
