"""drivelab from Python: train, load a trained policy, act, evaluate. ``import drivelab`` gives
``drivelab.train``, ``drivelab.load``, ``drivelab.evaluate`` and ``drivelab.make_env``::

    import drivelab
    result = drivelab.train("ppo", "CartPole-v1", steps=50_000, seed=0, ppo={"lr": 3e-4})
    policy = drivelab.load(result.run_dir)              # a run, a checkpoint, or RUN/best
    action = policy.act(obs)                            # one observation or a batch
    drivelab.evaluate(policy, "CartPole-v1", episodes=10)   # the dict of `drivelab eval --json`

The CLI calls these same functions. This module sits on top: it hands the algorithm registry
(:data:`drivelab.algos.ALGORITHMS`) down to the config parser and the run, so that nothing below
the algorithms imports them.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import signal
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from drivelab.algos import ALGORITHMS, AlgoSpec
from drivelab.tools.baselines import baseline
from drivelab.training.checkpoint import Checkpoint, checkpoint_step, list_checkpoints, load_checkpoint, restore
from drivelab.config import EnvConfig, TrainConfig, parse_config, read_yaml, resolve_config_file, set_dotted
from drivelab.envs import env_spaces, make_vector_env
from drivelab.errors import DrivelabError
from drivelab.training.evaluation import EvalResult, play, run_episodes
from drivelab.tools.export import DeployedPolicy, export_policy, metadata
from drivelab.training.run import Run
from drivelab.training.video import Recorder


def build_config(data: dict, where: str = "config", algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> TrainConfig:
    """Validate a nested dict (a YAML file's content plus overrides) into a :class:`TrainConfig`."""
    return parse_config(data, {name: spec.params for name, spec in algorithms.items()}, where)


def default_run_dir(cfg: TrainConfig) -> str:
    safe_env = cfg.env.id.replace("/", "_")
    return str(Path("runs") / f"{cfg.algo}-{safe_env}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}")


def raise_interrupt(signum, frame) -> None:
    """SIGTERM (what a cluster scheduler sends) stops a run like Ctrl-C: checkpoint, then stop."""
    raise KeyboardInterrupt


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """While a run trains: SIGTERM raises ``KeyboardInterrupt`` like Ctrl-C, so the run stops
    with a checkpoint of that moment instead of dying with up to ``checkpoint_every`` steps
    lost; and a SIGINT that the shell ignores (background jobs, ``nohup ... &``) is heard again.
    The previous handlers come back afterwards. A SIGTERM handler that the caller installed
    (a cluster launcher's requeue, say) is left alone, and so is everything outside the main
    thread, where Python allows no handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    if previous[signal.SIGTERM] == signal.SIG_DFL:
        signal.signal(signal.SIGTERM, raise_interrupt)
    if previous[signal.SIGINT] == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class TrainResult(NamedTuple):
    run_dir: Path
    metrics: dict[str, float]     # the last logged value of each metric (episode/*, loss/*, eval/*, perf/*)


def train(algo: str | TrainConfig, env: str | Mapping[str, Any] | None = None, *, steps: int | None = None,
          seed: int | None = None, num_envs: int | None = None, run_dir: str | Path | None = None,
          config: str | Path | None = None, resume: bool = False, progress: bool = True,
          algorithms: Mapping[str, AlgoSpec] = ALGORITHMS, **overrides: Any) -> TrainResult:
    """Train an agent and return its run directory and final metrics.

    Either a :class:`TrainConfig`, or an algorithm name with an env (an id, or the ``env``
    section as a dict: ``{"id": "MetaDrive-10env-v0", "action_grid": "3x3"}``) and any config
    field as a keyword: sections as dicts (``ppo={"lr": 1e-3}``, ``eval={"every": 10_000}``) or
    top-level fields (``checkpoint_every=5000``). ``config`` is a YAML file (or the name of a
    shipped config) that these override. ``resume`` continues ``run_dir``.
    """
    if isinstance(algo, TrainConfig):
        cfg = algo
    else:
        if env is not None:
            overrides["env"] = {"id": env} if isinstance(env, str) else env
        cfg = _config_from_arguments(algo, steps, seed, num_envs, run_dir, config, overrides, algorithms)
    spec = algorithms[cfg.algo]
    if cfg.run_dir is None:
        cfg.run_dir = default_run_dir(cfg)
    checkpoint = None
    if resume and not list_checkpoints(cfg.run_dir):
        resume = False  # killed before its first checkpoint: nothing was trained, start it afresh
    if resume:
        checkpoint = load_checkpoint(cfg.run_dir)
        if not isinstance(checkpoint.state.get("numpy_rng"), dict):
            raise DrivelabError(f"checkpoint {checkpoint.path} cannot be resumed: its state.json lacks the RNG state")
        if checkpoint.step >= cfg.steps:
            raise DrivelabError(
                f"run {cfg.run_dir} is already at step {checkpoint.step} >= steps {cfg.steps}; pass a larger --steps to continue"
            )
    elif list_checkpoints(cfg.run_dir):
        raise DrivelabError(f"run directory {cfg.run_dir} already holds a run; use --resume {cfg.run_dir} or another --run-dir")
    # Fail on a bad env id, env kwargs or an unsupported action space before a run directory exists.
    obs_space, act_space = env_spaces(cfg.env)
    try:
        spec.build_policy(cfg, obs_space, act_space)
    except RuntimeError as exc:  # e.g. an image cropped smaller than the CNN's kernels
        raise DrivelabError(f"the {cfg.algo} network does not fit the observation space {obs_space}: "
                            f"{str(exc).strip().splitlines()[0]}") from None
    if "ray" in (cfg.env.backend, cfg.eval.backend):
        from drivelab.envs.ray_backend import connect

        connect(cfg.ray_address)
    run = Run(cfg, resume_from=checkpoint, progress=progress)
    interrupted = False
    try:
        with stop_signals():
            spec.train(cfg, run)
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM from a scheduler (stop_signals turns it into this)
        interrupted = True
        run.checkpoint_now()
        raise
    finally:
        run.close(interrupted)
    return TrainResult(run.dir, last_metrics(run.dir))


def _config_from_arguments(algo: str, steps: int | None, seed: int | None, num_envs: int | None, run_dir,
                           config, overrides: dict[str, Any], algorithms: Mapping[str, AlgoSpec]) -> TrainConfig:
    data = read_yaml(resolve_config_file(config)) if config else {}
    data["algo"] = algo
    for key, value in {"steps": steps, "seed": seed, "run_dir": None if run_dir is None else str(run_dir)}.items():
        if value is not None:
            set_dotted(data, key, value)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(data.get(key), Mapping):
            data[key] = {**data[key], **value}
        else:
            data[key] = dict(value) if isinstance(value, Mapping) else value
    if num_envs is not None:
        set_dotted(data, "env.num_envs", num_envs)
    return build_config(data, where="drivelab.train", algorithms=algorithms)


def last_metrics(run_dir: str | Path) -> dict[str, float]:
    """The last logged value of each metric in ``RUN/metrics.csv``."""
    with open(Path(run_dir) / "metrics.csv", newline="") as f:
        return {row["name"]: float(row["value"]) for row in csv.DictReader(f)}


def checkpoint_config(ckpt: Checkpoint, algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> TrainConfig:
    """The resolved config a checkpoint was trained with."""
    if not isinstance(ckpt.state.get("config"), dict):
        raise DrivelabError(f"checkpoint file {ckpt.path / 'state.json'} holds no training config")
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
                        deterministic: bool = True, recorder: Recorder | None = None) -> tuple[EvalResult, EnvConfig, Path]:
    """Load a checkpoint (or a run's latest) and evaluate its policy.

    ``env_id`` evaluates on another env (e.g. train on ``MetaDrive-100envs-v0``, evaluate on
    ``MetaDrive-validation-v0``); the training env's kwargs are then dropped, as they may
    redefine that env's scenario range, and ``env_kwargs`` are used instead. A ``recorder``
    (:class:`drivelab.training.video.Recorder`) films the episodes, on one env.
    """
    if episodes < 1:
        raise DrivelabError(f"--episodes must be >= 1, got {episodes}")
    ckpt = load_checkpoint(path)
    cfg = checkpoint_config(ckpt)
    env_cfg = cfg.env
    if env_id is not None and env_id != env_cfg.id:
        env_cfg.id, env_cfg.kwargs = env_id, {}
    env_cfg.kwargs.update(env_kwargs or {})
    env_cfg.num_envs = 1 if recorder is not None else max(1, min(num_envs or env_cfg.num_envs, episodes))
    result = play(env_cfg, policy_from_checkpoint(ckpt, cfg, env_cfg), episodes, seed, deterministic, recorder=recorder)
    return result, env_cfg, ckpt.path


def evaluate_baseline(name: str, env_cfg: EnvConfig, episodes: int = 10, seed: int = 0,
                      recorder: Recorder | None = None, deterministic: bool = True) -> EvalResult:
    """Evaluate a reference policy (``random``, ``lane-keeping``, ``metadrive-expert``; see
    :mod:`drivelab.tools.baselines`) with the protocol of :func:`evaluate_checkpoint`: same env config,
    episode k reset with seed ``seed + k``, same metrics; ``deterministic=False`` samples the
    expert's actions, as it samples a checkpoint's."""
    if episodes < 1:
        raise DrivelabError(f"--episodes must be >= 1, got {episodes}")
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
        self.env_config = dataclasses.replace(cfg.env, action_grid=None, fixed_throttle=None)
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

    def to_env(self, action: np.ndarray) -> np.ndarray:
        """Identity: ``act`` already returns the simulator's action (the evaluation loop's protocol)."""
        return action

    def export(self, out: str | Path, fmt: str = "onnx") -> Path:
        """Write the deterministic policy as ONNX or TorchScript, with ``policy.json``, into ``out``."""
        meta = metadata(self.config, checkpoint_step(self.checkpoint), self.observation_space, self.action_space)
        return export_policy(self.deployed, meta, self.observation_space, fmt, Path(out))


def load(path: str | Path) -> TrainedPolicy:
    """The trained policy of a run (its latest checkpoint), a checkpoint directory, or ``RUN/best``."""
    ckpt = load_checkpoint(path)
    cfg = checkpoint_config(ckpt)
    return TrainedPolicy(DeployedPolicy(policy_from_checkpoint(ckpt, cfg, cfg.env), cfg.env), cfg, ckpt.path)


def make_env(env: str | EnvConfig, **kwargs: Any) -> gym.Env:
    """One env as drivelab builds it: an id with keyword overrides (``make_env("MetaDrive-10env-v0",
    traffic_density=0.2)``), or an :class:`EnvConfig` (action grid, filters, reward, ...)."""
    from drivelab.envs import make_env as build

    env_cfg = env if isinstance(env, EnvConfig) else EnvConfig(id=env, kwargs=kwargs)
    env_cfg.validate()
    return build(env_cfg)


def evaluate(policy: TrainedPolicy, env: str | EnvConfig | gym.Env | None = None, episodes: int = 10,
             seed: int = 0, num_envs: int = 1, deterministic: bool = True) -> dict[str, float]:
    """Deterministic episodes of ``policy`` (episode k with seed ``seed + k``); returns the dict
    that ``drivelab eval --json`` prints. ``env``: None (the policy's own env), an env id (its
    kwargs are dropped if it differs from the training env's, as in ``drivelab eval --env``), an
    :class:`EnvConfig`, or an env instance."""
    if isinstance(env, gym.Env):
        envs = SyncVectorEnv([lambda: env], autoreset_mode=AutoresetMode.DISABLED)
        return run_episodes(envs, policy, episodes, seed=seed, deterministic=deterministic).summary()
    if isinstance(env, EnvConfig):
        env_cfg = env
    elif env is None or env == policy.env_config.id:
        env_cfg = policy.env_config
    else:
        env_cfg = dataclasses.replace(policy.env_config, id=env, kwargs={})
    env_cfg = dataclasses.replace(env_cfg, num_envs=max(1, min(num_envs, episodes)))
    return play(env_cfg, policy, episodes, seed, deterministic).summary()
