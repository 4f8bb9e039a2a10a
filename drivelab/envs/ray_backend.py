"""Envs in Ray actors (``env.backend: ray``): the same Gymnasium ``VectorEnv``, its envs spread over
the processes of one machine or the nodes of a Ray cluster.

Layout. ``num_envs`` envs go into ``ceil(num_envs / envs_per_actor)`` actors. Each actor holds a
Gymnasium ``SyncVectorEnv`` of its envs, built with the autoreset mode the trainer chose, so
autoreset, ``final_obs`` and info semantics are exactly those of the local backends: the trainer
sees one vector env and cannot tell the difference (same seeds -> same episodes).

A step is one remote call per actor with its slice of the actions; the replies are concatenated.
Ray sends small numpy arrays inline with the reply and large ones (images) through its
shared-memory object store, read without a copy on the same node; stepping several envs per actor
batches them into one message. Cost per call: see ``benchmarks/ray_backend.py``.

Fault tolerance, the contract of :mod:`drivelab.envs.supervised`: an actor whose call raises, whose
process dies, or that answers no call within ``step_timeout`` is killed and replaced by a fresh one.
Its envs' episodes end as *truncated* with their last observation (the other actors' envs go on);
``on_restart`` hears of it (``env/restarts``); more than ``max_restarts`` failures within
``restart_window`` vector steps stop the run with the env's own error in one line.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.vector.utils import batch_space

from drivelab.envs.supervised import RestartingVectorEnv, error_line, final_obs_info
from drivelab.errors import DrivelabError


def import_ray():
    try:
        import ray
    except ImportError:
        raise DrivelabError("the Ray backend needs Ray: pip install 'drivelab[ray]'") from None
    return ray


def connect(address: str | None = None) -> None:
    """Join the Ray cluster at ``address`` ("auto", "ray://host:10001", "host:6379"), or start a
    local Ray instance when None and $RAY_ADDRESS is unset. Once per process; later calls keep it."""
    ray = import_ray()
    if ray.is_initialized():
        return
    # Ray's token-authentication notice on every local start: drivelab's output stays its own
    logging.getLogger("ray._private.authentication").setLevel(logging.ERROR)
    in_main_thread = threading.current_thread() is threading.main_thread()
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)} if in_main_thread else {}
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False,
                 ignore_reinit_error=True)
    except (ConnectionError, ValueError, RuntimeError) as exc:
        raise DrivelabError(f"could not join the Ray cluster at {address or 'a new local instance'}: "
                            f"{error_line(exc)}") from None
    finally:
        # Ray installs its own handlers; drivelab's turn SIGINT/SIGTERM into a checkpoint and a clean stop.
        for sig, handler in handlers.items():
            if handler is not None:
                signal.signal(sig, handler)


class EnvGroup:
    """The body of one env actor: a few envs stepped together (``SyncVectorEnv``)."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], autoreset_mode: AutoresetMode):
        self.envs = SyncVectorEnv(list(env_fns), autoreset_mode=autoreset_mode)

    def spaces(self) -> tuple[gym.Space, gym.Space, dict]:
        return self.envs.single_observation_space, self.envs.single_action_space, dict(self.envs.metadata)

    def reset(self, seed: list[int | None], options: dict | None):
        return self.envs.reset(seed=seed, options=options)

    def step(self, actions: np.ndarray):
        return self.envs.step(actions)

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        return self.envs.call(name, *args, **kwargs)

    def pid(self) -> int:
        return os.getpid()

    def close(self) -> None:
        self.envs.close()


class RayVectorEnv(RestartingVectorEnv):
    """``num_envs`` envs in Ray actors behind the VectorEnv interface (see the module docstring)."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], envs_per_actor: int = 1,
                 autoreset_mode: AutoresetMode = AutoresetMode.NEXT_STEP, actor_cpus: float = 1.0,
                 step_timeout: float | None = 300.0, max_restarts: int = 3, restart_window: int = 10_000,
                 on_restart: Callable[[int], None] | None = None):
        ray = import_ray()
        connect()
        self._ray = ray
        self.env_fns, self.autoreset_mode = list(env_fns), AutoresetMode(autoreset_mode)
        self.num_envs = len(self.env_fns)
        self._supervise(step_timeout, max_restarts, restart_window, on_restart)
        self.slices = [slice(i, min(i + envs_per_actor, self.num_envs)) for i in range(0, self.num_envs, envs_per_actor)]
        # max_restarts=0: a dead actor stays dead, and this class decides what its episodes become.
        self._actor_class = ray.remote(num_cpus=actor_cpus, max_restarts=0)(EnvGroup)
        self.actors = [self._spawn(s) for s in self.slices]
        try:
            obs_space, act_space, metadata = ray.get(self.actors[0].spaces.remote(), timeout=step_timeout)
        except Exception as exc:  # noqa: BLE001 - the env could not be built in the actor
            self.close()
            raise DrivelabError(f"the env could not be built in a Ray actor: {error_line(exc)}") from None
        if not isinstance(obs_space, (gym.spaces.Box, gym.spaces.Discrete)):
            self.close()
            raise DrivelabError(f"the Ray backend supports Box and Discrete observations, not {obs_space}")
        self.single_observation_space, self.single_action_space = obs_space, act_space
        self.observation_space = batch_space(obs_space, self.num_envs)
        self.action_space = batch_space(act_space, self.num_envs)
        self.metadata = {**metadata, "autoreset_mode": self.autoreset_mode}
        self.render_mode = None
        self._fresh = [False] * len(self.actors)    # restarted, not reset yet (NEXT_STEP: reset on the next step)
        self._pending: list | None = None

    def _spawn(self, envs: slice):
        return self._actor_class.remote(self.env_fns[envs], self.autoreset_mode)

    # ---- reset and step -------------------------------------------------------------------

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        seeds = _per_env_seeds(seed, self.num_envs)
        mask = None if options is None else options.get("reset_mask")
        calls = {}
        for a, (actor, envs) in enumerate(zip(self.actors, self.slices)):
            if mask is not None and not np.any(mask[envs]):
                continue  # nothing of this actor's to reset: it keeps its observations
            sub_options = None
            if options is not None:  # this actor's part of the mask; a fresh actor resets all its envs
                sub_options = {k: v for k, v in options.items() if k != "reset_mask"}
                if mask is not None and not self._fresh[a]:
                    sub_options["reset_mask"] = mask[envs]
            calls[a] = actor.reset.remote(list(seeds[envs]), sub_options)
        replies = gather(self._ray, calls, self.step_timeout)
        obs = self._last_obs.copy() if self._last_obs is not None else np.zeros(self.observation_space.shape,
                                                                                 self.observation_space.dtype)
        parts = []
        for a, reply in replies.items():
            if isinstance(reply, BaseException):  # failed: the fresh actor starts all its envs anew
                self._restart(a, "reset", reply)
                reply = self._ray.get(self.actors[a].reset.remote(list(seeds[self.slices[a]]), None), timeout=self.step_timeout)
            self._fresh[a] = False
            obs[self.slices[a]] = reply[0]
            parts.append((self.slices[a], reply[1]))
        self._last_obs = obs
        return obs, merge_infos(parts, self.num_envs)

    def step_async(self, actions) -> None:
        actions = np.asarray(actions)
        self._pending = {}
        for a, (actor, envs) in enumerate(zip(self.actors, self.slices)):
            if self._fresh[a]:  # NEXT_STEP after a restart: this step only resets (the action is ignored)
                self._pending[a] = ("reset", actor.reset.remote([None] * (envs.stop - envs.start), None))
            else:
                self._pending[a] = ("step", actor.step.remote(actions[envs]))

    def step_wait(self):
        self._steps += 1
        pending, self._pending = self._pending, None
        replies = gather(self._ray, {a: ref for a, (_, ref) in pending.items()}, self.step_timeout)
        n = self.num_envs
        obs = np.empty(self.observation_space.shape, self.observation_space.dtype)
        reward, terminated, truncated = np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
        parts = []
        for a, envs in enumerate(self.slices):
            reply = replies[a]
            if isinstance(reply, BaseException):
                obs[envs], info = self._cut_episodes(a, reply)
                truncated[envs] = True
            elif pending[a][0] == "reset":
                self._fresh[a] = False
                obs[envs], info = reply
            else:
                obs[envs], reward[envs], terminated[envs], truncated[envs], info = reply
            parts.append((envs, info))
        self._last_obs = obs
        return obs, reward, terminated, truncated, merge_infos(parts, n)

    # ---- failures -------------------------------------------------------------------------

    def _cut_episodes(self, a: int, exc: BaseException) -> tuple[np.ndarray, dict]:
        """Replace actor ``a``; its episodes end as truncated at their last observation."""
        envs = self.slices[a]
        last = self._last_obs[envs]
        self._restart(a, "step", exc)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:  # the caller expects the next episodes' starts
            obs, info = self._ray.get(self.actors[a].reset.remote([None] * len(last), None), timeout=self.step_timeout)
            return obs, final_obs_info(last, info)
        # NEXT_STEP: the next step resets it; DISABLED: the caller resets the ended envs itself.
        self._fresh[a] = True
        return last, {}

    def _restart(self, a: int, during: str, exc: BaseException) -> None:
        self._restart_after(exc, f"Ray env actor {a} failed during {during} ({{error}}); restarting it, its "
                            "episodes end as truncated", replace=lambda: self._replace_actor(a))

    def _replace_actor(self, a: int) -> None:
        self._ray.kill(self.actors[a], no_restart=True)
        self.actors[a] = self._spawn(self.slices[a])

    def _stop_workers(self) -> None:
        """Kill every actor (over the restart budget)."""
        self.close()

    # ---- the rest of the VectorEnv interface ----------------------------------------------

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        replies = self._ray.get([actor.call.remote(name, *args, **kwargs) for actor in self.actors],
                                timeout=self.step_timeout)
        return tuple(value for reply in replies for value in reply)

    def render(self):
        return self.call("render")

    def actor_pids(self) -> list[int]:
        """The process id of each env actor (for tests and for finding them with ``ps``)."""
        return self._ray.get([actor.pid.remote() for actor in self.actors], timeout=self.step_timeout)

    def close(self, **kwargs: Any) -> None:
        for actor in getattr(self, "actors", []):
            try:
                self._ray.kill(actor, no_restart=True)
            except Exception:  # noqa: BLE001 - dead already, or Ray shut down
                pass
        self.actors = []
        self.closed = True


def gather(ray, calls: dict[int, Any], timeout: float | None) -> dict[int, Any]:
    """The replies to remote ``calls`` (actor -> object ref): each actor's reply, or the exception
    where the actor raised, died or did not answer within ``timeout``."""
    ready, _ = ray.wait(list(calls.values()), num_returns=len(calls), timeout=timeout)
    ready = set(ready)
    replies: dict[int, Any] = {}
    for a, ref in calls.items():
        if ref not in ready:
            replies[a] = TimeoutError(f"no answer within env.step_timeout {timeout} s")
            continue
        try:
            replies[a] = ray.get(ref)
        except Exception as exc:  # noqa: BLE001 - the env raised, or the actor's process died
            replies[a] = exc
    return replies


def _per_env_seeds(seed: int | Sequence[int | None] | None, n: int) -> np.ndarray:
    """Gymnasium's convention: an int seeds env i with seed + i; a list gives each env its own."""
    if seed is None:
        seeds: list = [None] * n
    elif isinstance(seed, (int, np.integer)):
        seeds = [int(seed) + i for i in range(n)]
    else:
        seeds = list(seed)
        if len(seeds) != n:
            raise ValueError(f"expected {n} seeds, got {len(seeds)}")
    out = np.empty(n, dtype=object)
    out[:] = seeds
    return out


def merge_infos(parts: list[tuple[slice, dict]], n: int) -> dict:
    """One vector-env info dict from the infos of sub-vector envs covering ``slice`` of ``n`` envs.

    Gymnasium's layout: ``info[key]`` is an array over the envs and ``info["_" + key]`` says which
    envs set it; nested dicts (``final_info``) follow the same layout."""
    merged: dict[str, Any] = {}
    keys = dict.fromkeys(k for _, info in parts for k in info if not k.startswith("_"))
    for key in keys:
        present = [(envs, info[key], info.get("_" + key)) for envs, info in parts if key in info]
        if isinstance(present[0][1], dict):
            merged[key] = merge_infos([(envs, value) for envs, value, _ in present], n)
            mask = np.zeros(n, bool)
            for envs, value, sub_mask in present:
                mask[envs] = True if sub_mask is None else sub_mask
            merged["_" + key] = mask
            continue
        first = np.asarray(present[0][1])
        # (n, ...): an env's value may be an array itself (a multi-agent scene's per-slot arrays)
        values = np.zeros((n, *first.shape[1:]), first.dtype) if first.dtype != object else np.empty(n, object)
        mask = np.zeros(n, bool)
        for envs, value, sub_mask in present:
            values[envs] = value
            mask[envs] = True if sub_mask is None else sub_mask
        merged[key], merged["_" + key] = values, mask
    return merged
