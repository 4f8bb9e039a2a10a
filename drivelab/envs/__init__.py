"""Environments: one factory for single and vectorised envs from an id and keyword overrides.

Any registered Gymnasium id works (``CartPole-v1``, ``LunarLander-v3``, ...), plus drivelab's
MetaDrive ids (see :mod:`drivelab.envs.registration`), plus Gymnasium's ``"module:EnvId"`` form
for envs registered by importing ``module`` (e.g. ``flaky_env:Flaky-v0`` in the tests), and
``"module:EnvClass"`` for an env class that nobody registered (``my_env:Corridor``).
"""

from __future__ import annotations

import copy
import difflib
import functools
import multiprocessing
import os
import signal
import sys
import warnings
from collections.abc import Callable

import gymnasium as gym
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv, VectorEnv

from drivelab.envs.config import EnvConfig
from drivelab.envs.costs import CostSignal, CostTermination
from drivelab.envs.filters import apply_filters
from drivelab.envs.metadrive import held_in_simulator
from drivelab.envs.multiagent import agent_spaces
from drivelab.envs.registration import is_multiagent, metadrive_ids, needs_own_process, register_envs, registered_id
from drivelab.envs.rewards import RewardShaping
from drivelab.envs.supervised import SupervisedVectorEnv
from drivelab.envs.wrappers import (
    ActionRepeat,
    DifferentialDrive,
    DiscreteActionGrid,
    FixedThrottle,
    ScenarioReplay,
    parse_grid,
)
from drivelab.errors import DrivelabError, kill_point

__all__ = ["EnvConfig", "make_env", "make_vector_env", "env_spaces", "DiscreteActionGrid", "FixedThrottle", "DifferentialDrive",
           "metadrive_ids", "needs_own_process", "worker_start_method"]


def _check_id(env_id: str) -> str:
    """The registered id of ``env_id`` ("module:EnvId" and "module:EnvClass" resolved), or a one-line error."""
    register_envs()
    name = registered_id(env_id)  # "module:EnvId": imports the module, which registers EnvId
    if name not in gym.registry:
        close = difflib.get_close_matches(name, list(gym.registry), n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise DrivelabError(f"unknown env id '{env_id}'{hint}")
    return name


def make_env(cfg: EnvConfig, *, render_mode: str | None = None,
             wrapper: Callable[[gym.Env], gym.Env] | None = None) -> gym.Env:
    """Build one environment from a validated :class:`~drivelab.config.EnvConfig`, then drivelab's
    wrappers in this order: the cost signal (``cfg.cost``, and ``info["episode_cost"]`` for any env
    that reports a cost: :mod:`drivelab.envs.costs`), the end of an episode whose cost exceeds
    ``cfg.cost_termination`` (training only), the replay of failed scenarios
    (``cfg.scenario_replay``), reward shaping (``cfg.reward``, whose ``cost`` term sees the cost
    after ``cfg.cost``'s terms), action adapter (``cfg.action_grid`` or ``cfg.fixed_throttle``), action repeat
    (``cfg.action_repeat``, over the shaped reward; with ``cfg.simulator_repeat``, MetaDrive holds
    the action itself: :func:`~drivelab.envs.metadrive.held_in_simulator`),
    observation filters (``cfg.obs_filters``: they see the observations the agent decides on).

    ``cfg.kwargs`` go to ``gym.make`` (for MetaDrive: any MetaDrive config key, e.g.
    ``{"num_scenarios": 10, "traffic_density": 0.2}``). A task that shapes its reward itself
    (lane following, Duckietown) has its terms replaced by ``cfg.reward``: one route per knob.
    A task's own shaping sees the env's own cost. ``render_mode="rgb_array"`` is for videos; ``wrapper`` goes on last (e.g. a baseline's, see
    :mod:`drivelab.tools.baselines`; a module-level class, so vector envs can pickle it).
    """
    env_id = _check_id(cfg.id)
    in_worker = multiprocessing.parent_process() is not None
    kill_tested = in_worker and os.environ.get("DRIVELAB_KILL_AT", "").startswith("env-worker")
    if in_worker:
        # In an env worker, Ctrl-C is the trainer's to handle: it checkpoints and closes the
        # workers. (SIGTERM stays fatal: the supervisor terminates hung workers with it.)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    kwargs = cfg.kwargs or {}
    if cfg.simulator_repeat and cfg.action_repeat > 1:
        kwargs = held_in_simulator(kwargs, cfg.action_repeat)
    if render_mode is not None:  # pygame-drawn frames (CartPole, MetaDrive's top-down) need no display
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    env = _make_base_env(cfg.id, env_id, kwargs, render_mode)
    if is_multiagent(env_id):  # agent slots: MetaDrive's own settings only (EnvConfig refuses the wrappers)
        env = KillPointInWorker(env) if kill_tested else env
        return wrapper(env) if wrapper is not None else env
    env = CostSignal(env, cfg.cost)  # silent on an env that reports no cost and has no env.cost terms
    if cfg.cost_termination is not None:
        env = CostTermination(env, cfg.cost_termination)
    if cfg.scenario_replay:
        env = ScenarioReplay(env, cfg.scenario_replay)
    if cfg.reward:
        task_shaping = _find_wrapper(env, RewardShaping)
        if task_shaping is not None:
            task_shaping.replace_terms(cfg.reward)
        else:
            env = RewardShaping(env, cfg.reward)
    if kill_tested:
        env = KillPointInWorker(env)
    if cfg.action_grid:
        steering_bins, throttle_bins = parse_grid(cfg.action_grid)
        env = DiscreteActionGrid(env, steering_bins, throttle_bins, max_steering=cfg.max_steering)
    elif cfg.fixed_throttle is not None:
        env = FixedThrottle(env, cfg.fixed_throttle)
    if cfg.action_repeat > 1 and not cfg.simulator_repeat:
        env = ActionRepeat(env, cfg.action_repeat)
    if cfg.obs_filters:
        env = apply_filters(env, list(cfg.obs_filters))
    return wrapper(env) if wrapper is not None else env


def _make_base_env(name: str, env_id: str, kwargs: dict, render_mode: str | None) -> gym.Env:
    """``gym.make`` with ``render_mode`` only when one is asked for (videos): an env class whose
    ``__init__`` takes no ``render_mode`` works as with ``gym.make(id)``; one that cannot render
    in that mode is one line."""
    mode = {"render_mode": render_mode} if render_mode is not None else {}
    try:
        with warnings.catch_warnings():  # a mode missing from the env's metadata: said below, in one line
            warnings.filterwarnings("ignore", message=".*render_mode.*")
            env = gym.make(env_id, **mode, **kwargs)
    except DrivelabError:
        raise
    except (TypeError, ValueError, KeyError, AssertionError, gym.error.Error) as exc:
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if render_mode is not None and "render_mode" in message:
            raise DrivelabError(f"env '{name}' cannot render (a video needs render_mode='{render_mode}'): "
                                f"{message}") from None
        raise DrivelabError(f"env '{name}' could not be created with kwargs {kwargs}: {message}") from None
    if render_mode is not None and getattr(env.unwrapped, "render_mode", None) != render_mode:
        env.close()
        raise DrivelabError(f"env '{name}' cannot render: it ignored render_mode='{render_mode}' "
                            f"(its metadata lists {env.metadata.get('render_modes', [])}); videos need it")
    return env


def _find_wrapper(env: gym.Env, kind: type[gym.Wrapper]) -> gym.Wrapper | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, kind):
            return env
        env = env.env
    return None


def env_spaces(cfg: EnvConfig, wrapper: Callable[[gym.Env], gym.Env] | None = None) -> tuple[gym.Space, gym.Space]:
    """(observation_space, action_space) of one env, after drivelab's wrappers: the spaces a
    policy acts in (for a multi-agent scene, those of one agent: every car shares the policy).

    Builds the env in this process without resetting it; for MetaDrive this starts no engine.
    """
    env = make_env(cfg, wrapper=wrapper)
    try:
        if is_multiagent(cfg.id):
            return agent_spaces(env.observation_space), agent_spaces(env.action_space)
        return env.observation_space, env.action_space
    finally:
        env.close()


def make_vector_env(cfg: EnvConfig, num_envs: int | None = None, *,
                    autoreset_mode: AutoresetMode = AutoresetMode.NEXT_STEP,
                    render_mode: str | None = None, wrapper: Callable[[gym.Env], gym.Env] | None = None,
                    on_restart: Callable[[int], None] | None = None) -> VectorEnv:
    """Build ``num_envs`` (default ``cfg.num_envs``) copies of the env as a Gymnasium vector env.
    ``num_envs`` is at least 1: :meth:`EnvConfig.validate` checks ``cfg.num_envs``, and each override
    is 1 or more by construction (an env group's share, one env for a video, an evaluation's count).

    ``cfg.backend`` picks where they run: ``"sync"`` steps the envs in this process (best for
    cheap envs such as CartPole), ``"async"`` runs one subprocess per env, ``"ray"`` puts them in
    Ray actors (:mod:`drivelab.envs.ray_backend`, same contract). ``"auto"`` chooses async for
    simulators that allow only one instance per process (MetaDrive) and sync otherwise.
    Subprocesses start from a fresh interpreter, never as forks of this process, so no simulator
    or torch state leaks into them (:func:`worker_start_method`).

    ``autoreset_mode`` is passed through; each trainer chooses it deliberately (Gymnasium 1.x
    defaults to NEXT_STEP: the step after an episode ends only resets and ignores its action).
    Subprocess and Ray envs are supervised (:mod:`drivelab.envs.supervised`): a worker that
    raises, dies or hangs longer than ``cfg.step_timeout`` is restarted; ``on_restart(total)``
    hears of it.
    """
    num_envs = cfg.num_envs if num_envs is None else num_envs
    _check_id(cfg.id)
    mode = cfg.resolved_backend()
    cfg.check_one_per_process()
    fns = [functools.partial(make_env, copy.deepcopy(cfg), render_mode=render_mode, wrapper=wrapper)
           for _ in range(num_envs)]
    if mode == "sync":
        return SyncVectorEnv(fns, autoreset_mode=autoreset_mode)
    if mode == "async":
        # A fork server's workers inherit the server's os.environ, from when it started: each gets
        # this process's, as a spawned worker would (proxies, DRIVELAB_KILL_AT, a user's settings).
        environ = dict(os.environ)
        fns = [functools.partial(_with_environment, environ, fn) for fn in fns]
        make = functools.partial(AsyncVectorEnv, fns, context=worker_start_method(cfg.id),
                                 autoreset_mode=autoreset_mode)
        return SupervisedVectorEnv(make, cfg.step_timeout, cfg.max_restarts, cfg.restart_window, on_restart)
    if mode == "ray":
        from drivelab.envs.ray_backend import RayVectorEnv

        return RayVectorEnv(fns, cfg.envs_per_actor, autoreset_mode, cfg.actor_cpus, cfg.step_timeout,
                            cfg.max_restarts, cfg.restart_window, on_restart)
    raise DrivelabError(f"config field 'env.backend' must be auto, sync, async or ray, got {mode!r}")


def worker_start_method(env_id: str) -> str:
    """How env worker subprocesses start: ``"forkserver"`` on Linux, ``"spawn"`` elsewhere.

    Both start each worker from a fresh interpreter, not as a fork of the trainer. The fork server
    is one such interpreter per trainer that imports the env's modules once and forks every worker
    from itself, so a worker does not import them again (MetaDrive's imports are most of a
    spawned worker's start; ``benchmarks/worker_start.py`` times both methods). That start recurs
    for every evaluation, video and restarted worker. macOS keeps ``spawn``: its system libraries
    are not safe to use after fork.
    """
    if not sys.platform.startswith("linux"):
        return "spawn"
    # Read when the server starts, so the first subprocess vector env of a process chooses; a
    # module that fails to import is skipped there and imported by each worker as with spawn.
    modules = ["drivelab.envs", "metadrive"] if needs_own_process(env_id) else ["drivelab.envs"]
    multiprocessing.get_context("forkserver").set_forkserver_preload(modules)
    return "forkserver"


def _with_environment(environ: dict[str, str], make: Callable[[], gym.Env]) -> gym.Env:
    """In an env worker: set ``os.environ`` to the trainer's (``environ``), then build the env."""
    os.environ.clear()
    os.environ.update(environ)
    return make()


class KillPointInWorker(gym.Wrapper):
    """The kill tests' ``env-worker`` phase (:func:`drivelab.errors.kill_point`): every step of an
    env worker passes it, so ``DRIVELAB_KILL_AT=env-worker:N`` kills a worker at its N-th step."""

    def step(self, action):
        kill_point("env-worker")
        return self.env.step(action)
