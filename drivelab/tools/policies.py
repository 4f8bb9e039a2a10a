"""Configs and trained policies outside training: build a config with the algorithm registry,
load a checkpoint's policy, evaluate a checkpoint or a reference policy (baseline).

The tools (report, reward comparison, sweep) and the faces (:mod:`drivelab.api`, which
re-exports these functions, and the CLI) share them, so a checkpoint is loaded and evaluated
the same way wherever it is.
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from drivelab.algos import ALGORITHMS, AlgoSpec
from drivelab.config import EnvConfig, TrainConfig, parse_config
from drivelab.envs import env_spaces
from drivelab.errors import DrivelabError
from drivelab.tools.baselines import baseline
from drivelab.tools.drivers import check_observation_layout, resolve_policy_path
from drivelab.tools.export import DeployedPolicy, export_policy, metadata
from drivelab.training.collection.evaluation import EvalResult, play
from drivelab.training.outputs.checkpoint import Checkpoint, checkpoint_step, load_checkpoint, restore
from drivelab.training.outputs.video import Recorder

# The env the baselines play when neither a checkpoint nor an env id says which.
DEFAULT_BASELINE_ENV = "MetaDrive-validation-v0"


def build_config(data: dict, where: str = "config", algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> TrainConfig:
    """Validate a nested dict (a YAML file's content plus overrides) into a :class:`TrainConfig`,
    with the hyperparameter dataclasses of the registered algorithms."""
    return parse_config(data, {name: spec.params for name, spec in algorithms.items()}, where)


def checkpoint_config(ckpt: Checkpoint, algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> TrainConfig:
    """The resolved config a checkpoint was trained with."""
    if not isinstance(ckpt.state.get("config"), dict):
        raise DrivelabError(f"checkpoint file {ckpt.path / 'state.json'} holds no training config")
    return build_config(ckpt.state["config"], where=f"config in {ckpt.path}", algorithms=algorithms)


def policy_from_checkpoint(ckpt: Checkpoint, cfg: TrainConfig, env_cfg: EnvConfig,
                           algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> torch.nn.Module:
    """The trained policy, in eval mode, built for the spaces of ``env_cfg`` (a driver with a
    model card refuses an env whose observations it was not trained on)."""
    spaces = env_spaces(env_cfg)
    check_observation_layout(ckpt.path, spaces[0])
    policy = algorithms[cfg.algo].build_policy(cfg, *spaces)
    restore(ckpt, {"policy": policy}, rng=False)
    return policy.eval()


def load_policy(path: str | Path) -> tuple[torch.nn.Module, TrainConfig, Checkpoint]:
    """The trained policy of a checkpoint (or a run's latest checkpoint, or a shipped driver's
    name, see :mod:`drivelab.tools.drivers`), with its config."""
    ckpt = load_checkpoint(resolve_policy_path(path))
    cfg = checkpoint_config(ckpt)
    return policy_from_checkpoint(ckpt, cfg, cfg.env), cfg, ckpt


def evaluate_checkpoint(path: str | Path, episodes: int = 10, env_id: str | None = None,
                        env_kwargs: dict | None = None, num_envs: int | None = None, seed: int = 0,
                        deterministic: bool = True, recorder: Recorder | None = None) -> tuple[EvalResult, EnvConfig, Path]:
    """Load a checkpoint (or a run's latest) and evaluate its policy.

    ``env_id`` evaluates on another env (e.g. train on ``MetaDrive-100envs-v0``, evaluate on
    ``MetaDrive-validation-v0``); the training env's kwargs are then dropped, as they may
    redefine that env's scenario range, and ``env_kwargs`` are used instead (all but those
    that shape the observation, :meth:`~drivelab.envs.config.EnvConfig.on`). A ``recorder``
    (:class:`drivelab.training.outputs.video.Recorder`) films the episodes, on one env. ``path`` may
    also name a shipped driver (``drivelab-driver``).
    """
    ckpt = load_checkpoint(resolve_policy_path(path))
    cfg = checkpoint_config(ckpt)
    env_cfg = cfg.env.played()
    if env_id is not None and env_id != env_cfg.id:
        env_cfg = env_cfg.on(env_id)
    env_cfg.kwargs.update(env_kwargs or {})
    env_cfg.num_envs = 1 if recorder is not None else max(1, min(num_envs or env_cfg.num_envs, episodes))
    result = play(env_cfg, policy_from_checkpoint(ckpt, cfg, env_cfg), episodes, seed, deterministic, recorder=recorder)
    return result, env_cfg, ckpt.path


def baseline_env(played: EnvConfig | None = None, env_id: str | None = None, kwargs: dict | None = None,
                 num_envs: int = 2) -> EnvConfig:
    """The env the reference policies play: the env a checkpoint was evaluated on (``played``: its
    id and kwargs, without the checkpoint's action or observation adapters, which a baseline has
    its own of), else ``env_id`` (default ``MetaDrive-validation-v0``) with ``kwargs``."""
    if played is not None:
        env_cfg = EnvConfig(id=played.id, kwargs=dict(played.kwargs), num_envs=num_envs)
    else:
        env_cfg = EnvConfig(id=env_id or DEFAULT_BASELINE_ENV, kwargs=dict(kwargs or {}), num_envs=num_envs)
    env_cfg.validate()
    return env_cfg


def evaluate_baseline(name: str, env_cfg: EnvConfig, episodes: int = 10, seed: int = 0,
                      recorder: Recorder | None = None, deterministic: bool = True) -> EvalResult:
    """Evaluate a reference policy (``random``, ``lane-keeping``, ``metadrive-expert``; see
    :mod:`drivelab.tools.baselines`) with the protocol of :func:`evaluate_checkpoint`: same env config,
    episode k reset with seed ``seed + k``, same metrics; ``deterministic=False`` samples the
    expert's actions, as it samples a checkpoint's."""
    env_cfg = dataclasses.replace(env_cfg, num_envs=1 if recorder else max(1, min(env_cfg.num_envs, episodes)))
    wrapper, policy = baseline(name, env_spaces(env_cfg)[1], seed, deterministic)
    return play(env_cfg, policy, episodes, seed, wrapper=wrapper, recorder=recorder)


class TrainedPolicy:
    """A trained policy outside training (``drivelab.load``): observations of the run's env (after
    its observation filters) -> the simulator's action, with the run's observation normalisation
    and action adapters applied (:class:`drivelab.tools.export.DeployedPolicy`).

    ``act`` takes one observation or a batch (numpy or torch) and returns numpy actions of the
    same batch shape; ``env_config`` builds the env it acts in (``drivelab.make_env``): the run's
    env with its filters and reward, without the action adapters the policy already applies.
    """

    def __init__(self, deployed: DeployedPolicy, cfg: TrainConfig, checkpoint: Path):
        self.deployed, self.config, self.checkpoint = deployed.eval().requires_grad_(False), cfg, checkpoint
        self.env_config = dataclasses.replace(cfg.env.played(), action_grid=None, fixed_throttle=None)
        self.observation_space, self.action_space = env_spaces(cfg.env)[0], env_spaces(self.env_config)[1]

    @torch.no_grad()
    def act(self, obs, deterministic: bool = True) -> np.ndarray:
        x = torch.as_tensor(np.asarray(obs, dtype=self.observation_space.dtype))
        single = tuple(x.shape) == tuple(self.observation_space.shape)
        x = x[None] if single else x
        if deterministic:
            action = self.deployed(x)
        else:
            network = self.deployed.network
            action = self.deployed.adapt(torch.as_tensor(network.to_env(network.act(x, deterministic=False))))
        action = action.cpu().numpy()
        return action[0] if single else action

    def predict(self, obs, state=None, episode_start=None, deterministic: bool = True) -> tuple[np.ndarray, None]:
        """Stable-Baselines3's signature: ``(action, None)`` (drivelab's policies keep no
        recurrent state; ``state`` and ``episode_start`` are accepted and ignored)."""
        return self.act(obs, deterministic=deterministic), None

    def to_env(self, action: np.ndarray) -> np.ndarray:
        """Identity: ``act`` already returns the simulator's action (the evaluation loop's protocol)."""
        return action

    def save(self, path: str | Path) -> Path:
        """Write the policy alone (its weights and observation statistics, without optimiser
        state or replay buffer) with its checkpoint's ``state.json`` (config, step) into the
        directory ``path``, which ``drivelab.load`` reads back."""
        out = Path(path)
        out.mkdir(parents=True, exist_ok=True)
        tensors = load_file(str(self.checkpoint / "tensors.safetensors"))
        save_file({k: v for k, v in tensors.items() if k.startswith("module/policy/")}, str(out / "tensors.safetensors"))
        shutil.copyfile(self.checkpoint / "state.json", out / "state.json")
        return out

    def export(self, out: str | Path, fmt: str = "onnx") -> Path:
        """Write the deterministic policy as ONNX or TorchScript, with ``policy.json``, into ``out``."""
        meta = metadata(self.config, checkpoint_step(self.checkpoint), self.observation_space, self.action_space)
        return export_policy(self.deployed, meta, self.observation_space, fmt, Path(out))


def load(path: str | Path) -> TrainedPolicy:
    """The trained policy of a run (its latest checkpoint), a checkpoint directory, ``RUN/best``,
    or a shipped driver by name (``drivelab.load("drivelab-driver")``)."""
    policy, cfg, ckpt = load_policy(path)
    return TrainedPolicy(DeployedPolicy(policy, cfg.env), cfg, ckpt.path)
