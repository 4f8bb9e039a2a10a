"""What surrounds every trainer's loop: the run directory, seeding, episode statistics, metric
logging, periodic evaluation, checkpoints and resume. The loop itself lives in each
``drivelab/algos/<algo>.py`` and calls :class:`Run`; nothing here calls the algorithm back.

``Run`` is the one object a loop receives; it composes small parts, each in its own module:

* :mod:`drivelab.training.run.directory`: the run directory, its lock, ``config.yaml``, seeding;
* :mod:`drivelab.training.run.metrics` (and :mod:`~drivelab.training.run.timing`): update means,
  the divergence guard, the progress bar, ``perf/*``, the tracker;
* :mod:`drivelab.training.run.periodic_evaluation`: periodic evaluation (local or Ray) and ``checkpoints/best``;
* :mod:`drivelab.training.run.checkpoints`: when to save, saving, and the resume state.

A loop looks like this::

    resumed = run.start(modules, optimizers, policy)     # restore on resume, step-0 checkpoint
    while not run.done:
        ... collect (with run.timing.env: envs.step(...)), compute targets ...
        with run.timing.update:
            run.record(update(...))                      # losses, averaged until the next log
        run.end_iteration(steps)                         # log, evaluate, checkpoint when due

Reproducibility: the torch RNG (action sampling, initialisation) is seeded with ``cfg.seed``; env
resets take explicit seeds drawn from ``Run.rng``, a numpy Generator seeded with ``cfg.seed``.
Both RNG states are saved in every checkpoint, so a resumed run continues the same streams.

Metrics, the same for every algorithm (``metrics.csv``, TensorBoard, MLflow):

* ``episode/return``, ``episode/length`` and, for driving envs, ``episode/success_rate``,
  ``episode/crash_rate``, ``episode/out_of_road_rate``, ``episode/route_completion``,
  ``episode/mean_abs_cte``, ``episode/reward/<term>``: means over the last ``stats_window``
  finished training episodes;
* ``loss/*`` and ``charts/*``: what the algorithm's update returns, averaged since the last log;
* ``eval/*``: periodic deterministic evaluation (``eval.every``), the same keys as ``drivelab eval``;
  with ``eval.backend: ray`` a Ray actor evaluates a copy of the policy while training goes on,
  and its results are logged at the step the copy was taken;
* ``perf/steps_per_s``: env steps per second of wall time since this process started training;
  ``perf/env_fraction``, ``perf/update_fraction`` and ``perf/other_fraction``: the shares of
  wall time since the last log spent stepping envs, in gradient updates, and in everything
  else (policy inference during collection, storage, bookkeeping, evaluation, checkpoints).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from drivelab.config import TrainConfig, fit_steps, resolve_device
from drivelab.errors import kill_point
from drivelab.training.learning.precision import native_bf16
from drivelab.training.outputs.checkpoint import Checkpoint, restore
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.run.checkpoints import ExtraState, RunCheckpoints
from drivelab.training.run.directory import open_run_dir, seed_everything
from drivelab.training.run.metrics import RunMetrics, check_finite
from drivelab.training.run.periodic_evaluation import RunEvaluation
from drivelab.training.run.timing import Timing


class RunEvent(NamedTuple):
    """What a training callback hears (``drivelab.train(..., callback=fn)``): ``fn(event)`` is
    called on each log, evaluation and checkpoint; returning False stops the run cleanly, with a
    checkpoint at the step reached."""
    kind: str                     # "log", "eval" or "checkpoint"
    step: int                     # env steps so far
    metrics: dict[str, float]     # log: the values logged; eval: the evaluation's summary; checkpoint: {}
    path: Path | None = None      # checkpoint: its directory


Callback = Callable[[RunEvent], "bool | None"]


def _warn_emulated_bf16(cfg: TrainConfig, device: torch.device) -> None:
    """``bf16_updates`` where the hardware has no bfloat16 arithmetic makes the updates slower, not
    faster (torch emulates bfloat16 through float32): one line on stderr, the run goes on as configured."""
    if getattr(cfg.algo_params, "bf16_updates", False) is True and native_bf16(device) is False:
        print(f"drivelab: warning: {cfg.algo}.bf16_updates is on, but this machine's {device.type} computes "
              f"bfloat16 only by emulation (x86 CPUs need AVX512-BF16 or AMX, GPUs compute capability 8.0): "
              f"its updates run several times slower than float32 (--{cfg.algo}.bf16_updates auto or false)",
              file=sys.stderr)


class Run:
    """A training run's state and services (see the module docstring for the loop they serve)."""

    def __init__(self, cfg: TrainConfig, resume_from: Checkpoint | None = None, progress: bool = True,
                 callback: Callback | None = None):
        resolve_device(cfg)  # before anything is written: a device this machine lacks is one line
        fit_steps(cfg)       # whole iterations: config.yaml, the bar and the report say where the run ends
        self.cfg = cfg
        self._callback, self.stopped_by_callback = callback, False
        self.dir = Path(cfg.run_dir)
        self._lock = open_run_dir(cfg)
        self.device = torch.device(cfg.device)
        _warn_emulated_bf16(cfg, self.device)
        self.rng = seed_everything(cfg)
        self.step, self.iteration, best = 0, 0, None
        self.episodes = EpisodeTracker(cfg.env.num_envs, cfg.stats_window)
        self.timing = Timing(cfg.update_threads)
        self.env_restarts = 0
        self._checkpoints = RunCheckpoints(cfg, self.dir, self.rng, self.episodes)
        self._resume_from = resume_from
        if resume_from is not None:
            self.step, self.iteration, best = self._checkpoints.resume(resume_from)
        self._metrics = RunMetrics(cfg, self.dir, self.episodes, self.timing, self.step,
                                   resumed=resume_from is not None, progress=progress)
        self.tracker, self.pbar = self._metrics.tracker, self._metrics.pbar
        self._evaluation = RunEvaluation(cfg, self.dir, self.tracker, self.device, best=best,
                                         save=lambda name: self._save(name=name), on_restart=self.note_env_restart,
                                         on_result=lambda step, summary: self._notify(RunEvent("eval", step, summary)))
        self._policy: torch.nn.Module | None = None
        self._extra_state: ExtraState | None = None
        self._next_log = self._after(self.step, cfg.log_every)
        self._next_eval = self._after(self.step, cfg.eval.every) if cfg.eval.every else math.inf
        self._evaluated_at: int | None = None

    @staticmethod
    def _after(step: int, every: int) -> int:
        """The first multiple of ``every`` above ``step`` (schedules survive a resume)."""
        return (step // every + 1) * every

    # ---- set-up ---------------------------------------------------------------------------

    def start(self, modules: dict[str, torch.nn.Module], optimizers: dict[str, torch.optim.Optimizer],
              policy: torch.nn.Module) -> Checkpoint | None:
        """Register what a checkpoint saves (``modules``, ``optimizers``) and what evaluation
        plays (``policy``). When resuming, load their states and the torch RNG and return the
        checkpoint (its ``state["trainer"]`` and ``tensors`` hold what the trainer saved itself,
        e.g. a replay buffer); on a fresh run, save the initial policy as the step-0 checkpoint
        (for before/after comparisons) and return None."""
        self._checkpoints.modules, self._checkpoints.optimizers, self._policy = modules, optimizers, policy
        if self._resume_from is not None:
            restore(self._resume_from, modules, optimizers)
            return self._resume_from
        self._save()
        kill_point("after-first-checkpoint")
        return None

    def note_env_restart(self, total: int) -> None:
        """An env worker was restarted (drivelab.envs.supervised): logged as ``env/restarts``."""
        self.env_restarts += 1
        self.tracker.log(self.step, {"env/restarts": self.env_restarts})

    def reset_seeds(self, mask: np.ndarray) -> list[int | None]:
        """Fresh seeds for the envs where ``mask`` is True (None elsewhere), for ``VectorEnv.reset``."""
        seeds = self.rng.integers(0, 2**31 - 1, size=int(mask.sum()))
        it = iter(seeds.tolist())
        return [next(it) if m else None for m in mask]

    # ---- each iteration -------------------------------------------------------------------

    def record(self, metrics: Mapping[str, torch.Tensor | float]) -> None:
        """Add an update's metrics (0-d tensors or floats); they are logged as means over the
        updates since the last log. Tensors are summed on their device: no host sync per update."""
        self._metrics.record(metrics)

    def end_iteration(self, steps: int, extra_state: ExtraState | None = None) -> None:
        """Count ``steps`` new env steps, then log, evaluate and checkpoint when each is due.

        Call it where no update is half done; ``extra_state`` is called only when a checkpoint
        is written."""
        self._extra_state = extra_state
        self.step += int(steps)
        self.iteration += 1
        self._metrics.advance(self.step)
        self._metrics.stop_if_diverged(self.step, self._checkpoints.last_step)  # before the next rollout
        if self.step >= self._next_log or self.done:
            self._next_log = self._after(self.step, self.cfg.log_every)
            self.log(check_finite(self._metrics.flush(), self.step, self._checkpoints.last_step))
        self._evaluation.poll()
        # eval.final: the policy the run ends with is weighed for checkpoints/best as well
        ends_unevaluated = (self.cfg.eval.final and self.cfg.eval.every and self.done and not self.stopped_by_callback
                            and self._evaluated_at != self.step)
        if self.step >= self._next_eval or ends_unevaluated:
            self._next_eval = self._after(self.step, self.cfg.eval.every)
            self.evaluate()
        if self._checkpoints.due(self.step, self.done):
            self._save(extra_state)

    @property
    def done(self) -> bool:
        """``steps`` reached, ``max_minutes`` of training spent (in this process), or the
        callback asked to stop."""
        if self.step >= self.cfg.steps or self.stopped_by_callback:
            return True
        limit = self.cfg.max_minutes
        return limit is not None and time.perf_counter() - self._metrics.start_time >= 60 * limit

    @property
    def steps_left(self) -> int:
        """Env steps still to play before ``steps`` (episodic algorithms cut their last batch to it)."""
        return max(0, self.cfg.steps - self.step)

    def log(self, metrics: Mapping[str, float]) -> None:
        """Log ``metrics`` with the episode means and the perf/* numbers at the current step."""
        self._notify(RunEvent("log", self.step, self._metrics.log(self.step, metrics)))

    def _notify(self, event: RunEvent) -> None:
        if self._callback is not None and self._callback(event) is False:
            self.stopped_by_callback = True

    # ---- evaluation and checkpoints -------------------------------------------------------

    def evaluate(self) -> dict[str, float]:
        """Deterministic episodes of the registered policy on the evaluation env (``cfg.eval``),
        logged as ``eval/*``; a new best ``eval.best_metric`` is saved as ``checkpoints/best``.
        With ``eval.backend: ray`` this only starts the evaluation and returns {}."""
        self._evaluated_at = self.step
        return self._evaluation.evaluate(self.step, self._policy)

    def _save(self, extra_state: ExtraState | None = None, name: str | None = None) -> Path:
        path = self._checkpoints.save(self.step, self.iteration, self._evaluation.best, extra_state, name)
        if name is None:  # the run's own checkpoints (not best, nor an evaluation's copy)
            self._notify(RunEvent("checkpoint", self.step, {}, path))
        return path

    def checkpoint_now(self) -> Path | None:
        """After an interrupt (Ctrl-C, SIGTERM): save the current state unless it is saved already
        (the networks as after the last update, at the step count of the last full iteration)."""
        if not self._checkpoints.modules or self.step == self._checkpoints.last_step:
            return None
        return self._save(self._extra_state)

    def close(self, interrupted: bool = False) -> None:
        """Release envs, workers, trackers and the lock; the evaluation in flight is waited for
        (so the last one is logged) unless the run was ``interrupted``."""
        self._evaluation.close(interrupted)
        self._metrics.close()
        if self.step > self.cfg.steps:  # REINFORCE and GRPO: the episodes in flight end past `steps`
            print(f"drivelab: {self.step:,} env steps trained, {self.step - self.cfg.steps:,} past steps "
                  f"({self.cfg.steps:,}): {self.cfg.algo} updates on whole episodes", file=sys.stderr)
        self._lock.close()  # releases the lock
