"""Configs and trained policies outside training: build a config with the algorithm registry,
load a checkpoint's policy, evaluate a checkpoint or a reference policy (baseline).

The tools (report, reward comparison, sweep) and the faces (:mod:`drivelab.api`, which
re-exports these functions, and the CLI) share them, so a checkpoint is loaded and evaluated
the same way wherever it is.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from safetensors.torch import load_file, save_file

from drivelab.algos import ALGORITHMS, AlgoSpec
from drivelab.config import EnvConfig, TrainConfig, config_to_dict, experiment_differences, parse_config, read_yaml
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


def with_defaults(saved: dict) -> dict:
    """A saved config as data with today's defaults for the fields added since it was written
    (as is if it no longer parses: the comparison then names what differs)."""
    try:
        return config_to_dict(build_config(saved))
    except DrivelabError:
        return saved


def config_differences(ckpt: Checkpoint, run_config: Mapping) -> list[str]:
    """The dotted fields where the config saved in ``ckpt`` differs from ``run_config`` (a run's
    config as plain data, with today's defaults), outside the fields a resumed run may change
    (:data:`~drivelab.config.RESUMABLE_FIELDS`) and ``run_dir``: empty when the checkpoint belongs
    to that run's experiment. Resume, evaluation and export all ask this question. Top-level
    fields come first (``algo`` says more than the hyperparameters that differ with it)."""
    saved = ckpt.state.get("config")
    differences = experiment_differences(run_config, with_defaults(saved)) if isinstance(saved, dict) else []
    return sorted(differences, key=lambda name: name.count("."))


def check_checkpoint_in_its_run(ckpt: Checkpoint) -> None:
    """A checkpoint inside a run directory (``RUN/checkpoints/step_<N>`` or ``best``) must have
    been trained with that run's ``config.yaml``: one copied in from another run (another
    algorithm, another env) would otherwise be evaluated or exported as if it were this run's."""
    if ckpt.path.parent.name != "checkpoints":
        return  # a checkpoint on its own: nothing to compare it with
    saved = ckpt.path.parent.parent / "config.yaml"
    try:
        run_config = with_defaults(read_yaml(saved))
    except DrivelabError:
        return  # no config.yaml, or a damaged one: the checkpoint's own config is what loads
    differences = config_differences(ckpt, run_config)
    if differences:
        raise DrivelabError(f"checkpoint {ckpt.path} does not match its run's {saved} (fields {', '.join(differences[:5])}): "
                            "it was copied from another run, or the config was edited; move the checkpoint out of "
                            "the run to use it on its own")


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
    check_checkpoint_in_its_run(ckpt)
    cfg = checkpoint_config(ckpt)
    return policy_from_checkpoint(ckpt, cfg, cfg.env), cfg, ckpt


def evaluate_checkpoint(path: str | Path, episodes: int = 10, env_id: str | None = None,
                        env_kwargs: dict | None = None, num_envs: int | None = None, seed: int = 0,
                        deterministic: bool = True, recorder: Recorder | None = None,
                        progress: bool = False) -> tuple[EvalResult, EnvConfig, Path]:
    """Load a checkpoint (or a run's latest) and evaluate its policy.

    ``env_id`` evaluates on another env (e.g. train on ``MetaDrive-100envs-v0``, evaluate on
    ``MetaDrive-validation-v0``); the training env's kwargs are then dropped, as they may
    redefine that env's scenario range, and ``env_kwargs`` are used instead (all but those
    that shape the observation, :meth:`~drivelab.envs.config.EnvConfig.on`). A ``recorder``
    (:class:`drivelab.training.outputs.video.Recorder`) films the episodes, on one env. ``path`` may
    also name a shipped driver (``drivelab-driver``). ``progress`` shows a bar of the episodes
    done (stderr), labelled with ``path``.
    """
    ckpt = load_checkpoint(resolve_policy_path(path))
    check_checkpoint_in_its_run(ckpt)
    cfg = checkpoint_config(ckpt)
    env_cfg = cfg.env.played()
    if env_id is not None and env_id != env_cfg.id:
        env_cfg = env_cfg.on(env_id)
    env_cfg.kwargs.update(env_kwargs or {})
    env_cfg.num_envs = 1 if recorder is not None else max(1, min(num_envs or env_cfg.num_envs, episodes))
    result = play(env_cfg, policy_from_checkpoint(ckpt, cfg, env_cfg), episodes, seed, deterministic, recorder=recorder,
                  progress=str(path) if progress else None)
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
                      recorder: Recorder | None = None, deterministic: bool = True, progress: bool = False) -> EvalResult:
    """Evaluate a reference policy (``random``, ``lane-keeping``, ``metadrive-expert``; see
    :mod:`drivelab.tools.baselines`) with the protocol of :func:`evaluate_checkpoint`: same env config,
    episode k reset with seed ``seed + k``, same metrics; ``deterministic=False`` samples the
    expert's actions, as it samples a checkpoint's. ``progress`` shows a bar of the episodes done
    (stderr), labelled with ``name``."""
    env_cfg = dataclasses.replace(env_cfg, num_envs=1 if recorder else max(1, min(env_cfg.num_envs, episodes)))
    wrapper, policy = baseline(name, env_spaces(env_cfg)[1], seed, deterministic)
    return play(env_cfg, policy, episodes, seed, wrapper=wrapper, recorder=recorder, progress=name if progress else None)


def evaluation_row(result: EvalResult, env_id: str, checkpoint: Path) -> dict[str, Any]:
    """What ``drivelab eval CHECKPOINT --json`` prints and ``drivelab.evaluate`` returns, in one place
    so that both say the same: the evaluation's summary, the env played, the checkpoint and its step."""
    return {**result.summary(), "env": env_id, "checkpoint": str(checkpoint), "step": checkpoint_step(checkpoint)}


def as_observations(obs: Any, space: gym.Space) -> tuple[torch.Tensor, bool]:
    """``obs`` (one observation of ``space``, or a batch of them, as numpy, torch or nested lists)
    as a batch tensor of the space's dtype, and whether it was a single observation (then batched
    here as ``(1, *shape)``). Bad input is one line naming ``obs``: text or objects, a shape other
    than the space's or ``(N, *shape)``, NaN or inf. ``act`` calls this every step, so the checks
    are cheap numpy ones and nothing is copied where ``obs`` already has the space's dtype."""
    shape = space.shape
    try:  # a view of the same memory for a CPU tensor or an array, no copy
        array = obs.detach().cpu().numpy() if isinstance(obs, torch.Tensor) else np.asarray(obs)
    except (TypeError, ValueError, RuntimeError):  # ragged lists, tensors of a dtype numpy lacks
        array = None
    if array is None or array.dtype.kind not in "biuf":  # bool, int, unsigned, float: numbers only
        shown = repr(obs) if len(repr(obs)) <= 40 else repr(obs)[:37] + "..."
        raise DrivelabError(f"obs: expected numbers of shape {_shapes(shape)}, got {type(obs).__name__} {shown}")
    single = array.shape == shape
    if not single and (array.ndim != len(shape) + 1 or array.shape[1:] != shape):
        raise DrivelabError(f"obs: expected shape {_shapes(shape)}, got shape {array.shape}")
    if array.dtype.kind == "f" and not np.isfinite(array).all():  # checked before a cast could hide it
        raise DrivelabError("obs: holds NaN or inf; the policy acts on finite observations "
                            "(check the env and its observation filters)")
    array = array.astype(space.dtype, copy=False)
    return torch.from_numpy(array[None] if single else array), single


def _shapes(shape: tuple[int, ...]) -> str:
    """The shapes ``act`` takes, for its error lines: one observation or a batch of them."""
    return f"{shape} (one observation) or (N, {', '.join(map(str, shape))}) (a batch)"


def check_fits_env(policy: TrainedPolicy, spaces: tuple[gym.Space, gym.Space], env_name: str) -> None:
    """Refuse an env whose observations or actions are not laid out as the policy's (kind and shape),
    in one line naming both, before an episode is played rather than as a matrix-shape error from
    inside torch. Bounds may differ: the same layout on another scenario set is fine."""
    for what, verb, theirs, ours in (("observations", "takes", spaces[0], policy.observation_space),
                                     ("actions", "gives", spaces[1], policy.action_space)):
        if _layout(theirs) != _layout(ours):
            raise DrivelabError(f"env: {env_name} has {what} {_layout(theirs)}, but the policy of {policy.checkpoint} "
                                f"(trained on {policy.config.env.id}) {verb} {_layout(ours)}; evaluate it on an env "
                                "with the spaces it was trained on")


def _layout(space: gym.Space) -> str:
    """What a policy needs to match in a space, as the error lines show it: its kind and shape
    (``Box(4,)``), or its number of actions (``Discrete(2)``); not its bounds."""
    if isinstance(space, gym.spaces.Discrete):
        return f"Discrete({int(space.n)})"
    return f"{type(space).__name__}{tuple(space.shape or ())}"


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
        """The simulator's action for one observation of :attr:`observation_space`, or actions for a
        batch ``(N, *shape)``; a wrongly shaped, non-numeric or non-finite ``obs`` is one line."""
        x, single = as_observations(obs, self.observation_space)
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
    if not isinstance(path, (str, os.PathLike)):
        raise DrivelabError(f"path: expected a run or checkpoint directory or a driver's name (str or os.PathLike), "
                            f"got {type(path).__name__} {path!r}")
    policy, cfg, ckpt = load_policy(path)
    return TrainedPolicy(DeployedPolicy(policy, cfg.env), cfg, ckpt.path)
