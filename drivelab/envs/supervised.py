"""Subprocess envs that survive their simulator: a worker that raises, dies or stops answering is
restarted instead of ending the run.

Simulators crash (MetaDrive's physics, a lost display for Duckietown), and a training run of an
hour should not die with them. :class:`SupervisedVectorEnv` wraps Gymnasium's
``AsyncVectorEnv``: when a reset or step fails or takes longer than ``step_timeout``, every
worker is replaced (gymnasium cannot restart one), and the episodes in flight end as
*truncated* (a time-limit-like cut: the state had a future, nothing terminal happened), with the
last observation as their final one. More than ``max_restarts`` restarts within
``restart_window`` vector steps stop the run with the env's own error in one line.
"""

from __future__ import annotations

import multiprocessing
import queue
import sys
import warnings
from collections import deque
from collections.abc import Callable

import numpy as np
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, VectorEnv

from drivelab.errors import DrivelabError


class RestartBudget:
    """Counts env failures; more than ``max_restarts`` within ``restart_window`` vector steps
    raise a one-line :class:`DrivelabError` with the env's own error."""

    def __init__(self, max_restarts: int, restart_window: int):
        self.max_restarts, self.restart_window = max_restarts, restart_window
        self._recent: deque[int] = deque()   # vector step of each recent failure

    def spend(self, step: int, exc: BaseException, restarting: str, stop: Callable[[], None]) -> None:
        """Count a failure at vector step ``step`` and warn that ``restarting`` (a sentence) follows;
        over the budget, ``stop()`` the workers and raise instead."""
        self._recent.append(step)
        while self._recent and self._recent[0] < step - self.restart_window:
            self._recent.popleft()
        if len(self._recent) > self.max_restarts:
            stop()
            raise DrivelabError(f"the env failed {len(self._recent)} times within {self.restart_window} steps "
                                f"(env.max_restarts {self.max_restarts}); last error: {error_line(exc)}")
        print(f"drivelab: warning: {restarting.format(error=error_line(exc))}", file=sys.stderr)


def error_line(exc: BaseException) -> str:
    """``Type: first line of the message`` of the root cause (Ray wraps an actor's exception)."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException) and cause is not exc:
        exc = cause
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def final_obs_info(last_obs, info: dict) -> dict:
    """SAME_STEP autoreset's info for envs whose episodes were cut: ``final_obs`` is the last
    observation each had, ``final_info`` empty."""
    n = len(last_obs)
    final = np.empty(n, dtype=object)
    final[:] = list(last_obs)
    mask = np.ones(n, bool)
    return {**info, "final_obs": final, "_final_obs": mask, "final_info": {}, "_final_info": mask}


class RestartingVectorEnv(VectorEnv):
    """The restart bookkeeping both supervised backends share (:class:`SupervisedVectorEnv` here,
    ``RayVectorEnv`` in :mod:`drivelab.envs.ray_backend`): a count of vector steps (the clock of the
    restart window), a :class:`RestartBudget` spent on each failure, the replacement of the failed
    workers and ``on_restart(total)``. A subclass says how to stop all its workers."""

    def _supervise(self, step_timeout: float | None, max_restarts: int, restart_window: int,
                   on_restart: Callable[[int], None] | None) -> None:
        """Set up the bookkeeping; the subclass's ``__init__`` calls it."""
        self.step_timeout = step_timeout
        self.budget, self.on_restart = RestartBudget(max_restarts, restart_window), on_restart
        self.restarts = 0
        self._steps = 0
        self._last_obs = None    # each env's latest observation: the final one of an episode cut short

    def step(self, actions):
        self.step_async(actions)
        return self.step_wait()

    def _restart_after(self, exc: BaseException, restarting: str, replace: Callable[[], None]) -> None:
        """Spend the restart budget on ``exc`` (over it: stop every worker and raise), then
        ``replace()`` the failed workers and tell ``on_restart``. ``restarting`` as in
        :meth:`RestartBudget.spend`. A :class:`DrivelabError` from a worker (what the env handed
        it is unusable, e.g. a non-finite observation) is not a crash that a restart cures: the
        workers stop and its one line ends the run."""
        cause = getattr(exc, "cause", None)   # Ray wraps an actor's exception
        if isinstance(exc, DrivelabError) or isinstance(cause, DrivelabError):
            self._stop_workers()
            raise DrivelabError(error_line(exc).removeprefix("DrivelabError: ")) from None
        self.budget.spend(self._steps, exc, restarting, stop=self._stop_workers)
        self.restarts += 1
        replace()
        if self.on_restart is not None:
            self.on_restart(self.restarts)

    def _stop_workers(self) -> None:
        raise NotImplementedError


class WorkerCallQueue:
    """The call protocol of :class:`SupervisedVectorEnv`'s workers: ``call(name, *args)`` sent to
    every gymnasium worker over its pipe, without waiting for the calls sent before it (a worker
    answers its calls in order). A failed call restarts the workers like a failed step.

    A mixin: it uses its host's ``envs`` (an ``AsyncVectorEnv``), ``_steps``, ``_pending_error``,
    ``_queued_calls``, ``_mid_exchange`` and ``_restart``."""

    def call_or_restart(self, name: str, *args, steps: int = 1, timeout: float | None = None) -> tuple | None:
        """``call(name, *args)`` in every worker, a call that plays ``steps`` env steps in each
        (they count towards the restart window): the results, or None when a worker raised, died
        or took longer than ``timeout``; the workers are then restarted (as for a failed step,
        within the restart budget) and every env needs a reset."""
        self.call_queue(name, *args, steps=steps)
        return self.call_next(timeout)

    def call_queue(self, name: str, *args, steps: int = 1, each: list[tuple] | None = None) -> None:
        """Queue ``call(name, *args)`` in every worker without waiting for the calls queued
        before it: a worker takes its calls in order, so it starts the next one as soon as it has
        answered one (the off-policy workers play chunk after chunk while the learner updates).
        :meth:`call_next` returns the results, oldest call first. ``steps`` as in
        :meth:`call_or_restart`; ``each`` (one tuple per worker) adds each worker's own arguments
        after ``args`` (the evaluation episodes a worker plays)."""
        self._steps += steps
        self._mid_exchange = True
        try:
            for index, pipe in enumerate(self.envs.parent_pipes):
                own = each[index] if each is not None else ()
                pipe.send(("_call", (name, (*args, *own), {})))
            self._queued_calls += 1
        except Exception as exc:  # noqa: BLE001 - a dead worker
            self._pending_error = self._reported_error() or exc

    def _reported_error(self) -> BaseException | None:
        """The exception a worker reported (gymnasium's error queue) before it ended and its pipe
        broke, so that the run names the worker's own error rather than the broken pipe."""
        try:
            _, exctype, value, _ = self.envs.error_queue.get(timeout=1.0)
        except queue.Empty:
            return None
        return value if isinstance(value, BaseException) else exctype(value)

    def call_next(self, timeout: float | None = None) -> tuple | None:
        """The results of the oldest queued call, or None when a worker raised, died or took
        longer than ``timeout``: the workers are then restarted and every queued call is dropped
        (every env needs a reset)."""
        try:
            if self._pending_error is not None:
                raise self._pending_error
            results, successes = [], []
            for index, pipe in enumerate(self.envs.parent_pipes):
                if not pipe.poll(timeout):
                    raise multiprocessing.TimeoutError(f"env worker {index} did not answer within {timeout} s")
                result, success = pipe.recv()
                results.append(result)
                successes.append(success)
            with warnings.catch_warnings():  # gymnasium re-prints the worker's traceback; we say it in one line
                warnings.simplefilter("ignore")
                self.envs._raise_if_errors(successes)  # gymnasium's: raises the worker's own exception
            self._queued_calls -= 1
        except Exception as exc:  # noqa: BLE001 - whatever the simulator raised, or a dead/hung worker
            self._restart(exc)
            results, self._queued_calls = None, 0
        self._pending_error = None
        self._mid_exchange = self._queued_calls > 0
        return results


class SupervisedVectorEnv(WorkerCallQueue, RestartingVectorEnv):
    """Gymnasium's ``AsyncVectorEnv`` (built by ``make``) whose workers are all replaced when one
    fails (see the module docstring)."""

    def __init__(self, make: Callable[[], AsyncVectorEnv], step_timeout: float | None, max_restarts: int,
                 restart_window: int, on_restart: Callable[[int], None] | None = None):
        self.make = make
        self._supervise(step_timeout, max_restarts, restart_window, on_restart)
        self.envs = make()
        for name in ("num_envs", "single_observation_space", "single_action_space", "observation_space",
                     "action_space", "metadata", "render_mode", "spec"):
            setattr(self, name, getattr(self.envs, name, None))
        self.autoreset_mode = self.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        self._pending_error: Exception | None = None
        self._queued_calls = 0           # call_queue calls whose results call_next has not read yet
        # True while actions or results are half sent or half read. A Ctrl-C (or SIGTERM, which
        # drivelab turns into one) there leaves gymnasium's pipes out of step: a worker may owe a
        # step result that close() would take for its goodbye, or owe nothing while close()
        # waits for it. close() then stops the workers instead of talking to them.
        self._mid_exchange = False

    def reset(self, *, seed=None, options=None):
        self._mid_exchange = True
        try:
            self.envs.reset_async(seed=seed, options=options)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                obs, info = self.envs.reset_wait(timeout=self.step_timeout)
        except Exception as exc:  # noqa: BLE001 - whatever the simulator raised, or a dead/hung worker
            self._restart(exc)
            obs, info = self.envs.reset(seed=seed)  # fresh workers: every env starts anew
        self._mid_exchange = False
        self._last_obs = obs
        return obs, info

    def step_async(self, actions) -> None:
        self._pending_error = None
        self._mid_exchange = True
        try:
            self.envs.step_async(actions)
        except Exception as exc:  # noqa: BLE001
            self._pending_error = exc
        self._mid_exchange = False

    def step_wait(self):
        self._steps += 1
        self._mid_exchange = True
        try:
            if self._pending_error is not None:
                raise self._pending_error
            with warnings.catch_warnings():  # gymnasium re-prints the worker's traceback; we say it in one line
                warnings.simplefilter("ignore")
                result = self.envs.step_wait(timeout=self.step_timeout)
        except Exception as exc:  # noqa: BLE001
            result = self._cut_episodes(exc)
        self._mid_exchange = False
        self._last_obs = result[0]
        return result

    def result_pipes(self) -> list:
        """The workers' pipes, readable once a step's result is there (for ``connection.wait``;
        a dead worker's pipe is readable too, and its ``step_wait`` restarts it)."""
        return [] if self._pending_error is not None else self.envs.parent_pipes

    def _cut_episodes(self, exc: BaseException):
        """Restart every worker; the step ends all episodes in flight as truncated."""
        self._restart(exc)
        n = self.num_envs
        reward, terminated, truncated = np.zeros(n), np.zeros(n, bool), np.ones(n, bool)
        last = self._last_obs
        if self.autoreset_mode == AutoresetMode.SAME_STEP:  # the caller expects the next episodes' starts
            obs, info = self.envs.reset()
            self._last_obs = obs
            return obs, reward, terminated, truncated, final_obs_info(last, info)
        self.envs.reset()  # the caller resets the ended envs itself (DISABLED) on fresh workers
        return last, reward, terminated, truncated, {}

    def _restart(self, exc: BaseException) -> None:
        self._restart_after(exc, "env worker failed ({error}); restarting the envs, their episodes end as "
                            "truncated", replace=self._replace_workers)

    def _replace_workers(self) -> None:
        self._stop_workers()  # a failed or hung exchange: the pipes are out of step, no goodbye
        self.envs = self.make()

    def call(self, name: str, *args, **kwargs):
        return self.envs.call(name, *args, **kwargs)

    def close(self, **kwargs) -> None:
        if self._mid_exchange:
            self._stop_workers()
            return
        try:
            with warnings.catch_warnings():  # closing between a step's send and its wait: gymnasium waits, and warns
                warnings.simplefilter("ignore")
                self.envs.close(**kwargs)
        except Exception:  # noqa: BLE001 - closing after a failure
            self._stop_workers()

    def _stop_workers(self) -> None:
        """End the workers without a word (SIGTERM; a spawned worker has no handler for it, so it
        exits at once and prints nothing; a dead one is simply reaped) and close our ends of
        their pipes. For an interrupted or failed exchange, where a close handshake cannot work."""
        envs = self.envs
        if not isinstance(envs, AsyncVectorEnv):  # a stand-in without worker processes
            envs.close(terminate=True)
            return
        if envs.closed:
            return
        for process in envs.processes:
            process.terminate()
        for process in envs.processes:
            process.join()
        for pipe in envs.parent_pipes:
            if pipe is not None:  # gymnasium drops the pipe of a worker that raised
                pipe.close()
        envs.closed = True  # its __del__ must not try to close it again
