"""drivelab from Python: build a config, train, load a trained policy, evaluate it.

    from drivelab.api import build_config, train, load_policy, evaluate_checkpoint
    run_dir = train(build_config({"algo": "ppo", "env": {"id": "CartPole-v1"}, "steps": 50_000}))
    result, env_cfg, checkpoint = evaluate_checkpoint(run_dir, episodes=10)

The CLI calls these same functions. This module sits on top: it hands the algorithm registry
(:data:`drivelab.algos.ALGORITHMS`) down to the config parser and the run, so that nothing below
the algorithms imports them.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from pathlib import Path

import torch
from gymnasium.vector import AutoresetMode

from drivelab.algos import ALGORITHMS, AlgoSpec
from drivelab.baselines import baseline
from drivelab.checkpoint import Checkpoint, load_checkpoint, restore
from drivelab.config import EnvConfig, TrainConfig, parse_config
from drivelab.envs import env_spaces, make_vector_env
from drivelab.errors import DrivelabError
from drivelab.evaluate import EvalResult, run_episodes
from drivelab.run import Run


def build_config(data: dict, where: str = "config", algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> TrainConfig:
    """Validate a nested dict (a YAML file's content plus overrides) into a :class:`TrainConfig`."""
    return parse_config(data, {name: spec.params for name, spec in algorithms.items()}, where)


def default_run_dir(cfg: TrainConfig) -> str:
    safe_env = cfg.env.id.replace("/", "_")
    return str(Path("runs") / f"{cfg.algo}-{safe_env}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}")


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True,
          algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> Path:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.steps`` env steps (continuing the latest
    checkpoint in ``cfg.run_dir`` when ``resume``). Returns the run directory."""
    spec = algorithms[cfg.algo]
    if cfg.run_dir is None:
        cfg.run_dir = default_run_dir(cfg)
    checkpoint = None
    if resume:
        checkpoint = load_checkpoint(cfg.run_dir)
        if checkpoint.step >= cfg.steps:
            raise DrivelabError(
                f"run {cfg.run_dir} is already at step {checkpoint.step} >= steps {cfg.steps}; pass a larger --steps to continue"
            )
    elif (Path(cfg.run_dir) / "checkpoints").exists():
        raise DrivelabError(f"run directory {cfg.run_dir} already holds a run; use --resume {cfg.run_dir} or another --run-dir")
    # Fail on a bad env id, env kwargs or an unsupported action space before a run directory exists.
    spec.build_policy(cfg, *env_spaces(cfg.env))
    run = Run(cfg, resume_from=checkpoint, progress=progress)
    try:
        spec.train(cfg, run)
    finally:
        run.close()
    return run.dir


def checkpoint_config(ckpt: Checkpoint, algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> TrainConfig:
    """The resolved config a checkpoint was trained with."""
    return build_config(ckpt.state["config"], where=f"config in {ckpt.path}", algorithms=algorithms)


def policy_from_checkpoint(ckpt: Checkpoint, cfg: TrainConfig, env_cfg: EnvConfig,
                           algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> torch.nn.Module:
    """The trained policy, in eval mode, built for the spaces of ``env_cfg``."""
    policy = algorithms[cfg.algo].build_policy(cfg, *env_spaces(env_cfg))
    restore(ckpt, {"policy": policy}, rng=False)
    return policy.eval()


def load_policy(path: str | Path) -> tuple[torch.nn.Module, TrainConfig, Checkpoint]:
    """The trained policy of a checkpoint (or a run's latest checkpoint), with its config."""
    ckpt = load_checkpoint(path)
    cfg = checkpoint_config(ckpt)
    return policy_from_checkpoint(ckpt, cfg, cfg.env), cfg, ckpt


def evaluate_checkpoint(path: str | Path, episodes: int = 10, env_id: str | None = None,
                        env_kwargs: dict | None = None, num_envs: int | None = None, seed: int = 0,
                        deterministic: bool = True) -> tuple[EvalResult, EnvConfig, Path]:
    """Load a checkpoint (or a run's latest) and evaluate its policy.

    ``env_id`` evaluates on another env (e.g. train on ``MetaDrive-100envs-v0``, evaluate on
    ``MetaDrive-validation-v0``); the training env's kwargs are then dropped, as they may
    redefine that env's scenario range, and ``env_kwargs`` are used instead.
    """
    if episodes < 1:
        raise DrivelabError(f"--episodes must be >= 1, got {episodes}")
    ckpt = load_checkpoint(path)
    cfg = checkpoint_config(ckpt)
    env_cfg = cfg.env
    if env_id is not None and env_id != env_cfg.id:
        env_cfg.id, env_cfg.kwargs = env_id, {}
    env_cfg.kwargs.update(env_kwargs or {})
    env_cfg.num_envs = max(1, min(num_envs or env_cfg.num_envs, episodes))
    result = play(env_cfg, policy_from_checkpoint(ckpt, cfg, env_cfg), episodes, seed, deterministic)
    return result, env_cfg, ckpt.path


def evaluate_baseline(name: str, env_cfg: EnvConfig, episodes: int = 10, seed: int = 0) -> EvalResult:
    """Evaluate a reference policy (``random``, ``lane-keeping``, ``metadrive-expert``; see
    :mod:`drivelab.baselines`) with the protocol of :func:`evaluate_checkpoint`: same env config,
    episode k reset with seed ``seed + k``, same metrics."""
    if episodes < 1:
        raise DrivelabError(f"--episodes must be >= 1, got {episodes}")
    env_cfg = dataclasses.replace(env_cfg, num_envs=max(1, min(env_cfg.num_envs, episodes)))
    wrapper, policy = baseline(name, env_spaces(env_cfg)[1], seed)
    return play(env_cfg, policy, episodes, seed, wrapper=wrapper)


def play(env_cfg: EnvConfig, policy, episodes: int, seed: int = 0, deterministic: bool = True,
         wrapper=None) -> EvalResult:
    """``episodes`` episodes of ``policy`` on a vector env built from ``env_cfg`` (then closed)."""
    envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED, wrapper=wrapper)
    try:
        return run_episodes(envs, policy, episodes, seed=seed, deterministic=deterministic)
    finally:
        envs.close()
