"""What surrounds every trainer's loop: the run directory, seeding, tracking, progress bar,
checkpoints and resume. The loop itself lives in each ``drivelab/algos/<algo>.py``.

Reproducibility: the torch RNG (action sampling, initialisation) is seeded with ``cfg.seed``; env
resets take explicit seeds drawn from ``Run.rng``, a numpy Generator seeded with ``cfg.seed``.
Both RNG states are saved in every checkpoint, so a resumed run continues the same streams.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from drivelab.checkpoint import Checkpoint, load_checkpoint, restore, save_checkpoint
from drivelab.config import TrainConfig, config_to_dict, save_config
from drivelab.episodes import EpisodeStats
from drivelab.errors import DrivelabError
from drivelab.track import Tracker


class Run:
    """A training run's state and services. Trainers call, in their loop:

    * :meth:`reset_seeds` for the seeds of env resets,
    * :meth:`restore` once, after building their networks (no-op on a fresh run),
    * :meth:`advance` after each batch of env steps, :meth:`log` for metrics,
    * :meth:`checkpoint_if_due` at the end of each iteration (checkpoints are only taken at
      iteration boundaries, where no episode is in flight, so resume is exact).
    """

    def __init__(self, cfg: TrainConfig, resume_from: Checkpoint | None = None, progress: bool = True):
        self.cfg = cfg
        self.dir = Path(cfg.run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, self.dir / "config.yaml")
        self.device = torch.device(cfg.device)
        torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.step = 0
        self.iteration = 0
        self.stats = EpisodeStats(cfg.stats_window)
        self._resume_from = resume_from
        self._last_checkpoint_step = -1
        if resume_from is not None:
            self.step = resume_from.step
            self.iteration = int(resume_from.state.get("iteration", 0))
            self.rng.bit_generator.state = resume_from.state["numpy_rng"]
            self._last_checkpoint_step = self.step
        self.tracker = Tracker(self.dir, cfg, resume_step=self.step if resume_from else None)
        self.pbar = tqdm(total=cfg.steps, initial=self.step, unit="step", dynamic_ncols=True,
                         disable=not progress, mininterval=0.5, smoothing=0.1)
        self._start_time = time.perf_counter()
        self._start_step = self.step

    def reset_seeds(self, mask: np.ndarray) -> list[int | None]:
        """Fresh seeds for the envs where ``mask`` is True (None elsewhere), for ``VectorEnv.reset``."""
        seeds = self.rng.integers(0, 2**31 - 1, size=int(mask.sum()))
        it = iter(seeds.tolist())
        return [next(it) if m else None for m in mask]

    def restore(self, modules: dict[str, torch.nn.Module], optimizers: dict[str, torch.optim.Optimizer]) -> Checkpoint | None:
        """When resuming, load weights, optimiser and RNG states and return the checkpoint, whose
        ``state["trainer"]`` and ``tensors`` hold what the trainer saved itself (e.g. a replay
        buffer); on a fresh run, return None."""
        if self._resume_from is None:
            return None
        restore(self._resume_from, modules, optimizers)
        return self._resume_from

    def advance(self, steps: int) -> None:
        self.step += int(steps)
        if self.step > self.pbar.total:  # the last batch finishes its episodes past `steps`
            self.pbar.total = self.step
        self.pbar.update(int(steps))
        means = self.stats.means()
        if means:
            self.pbar.set_postfix_str(f"return {means['episode/return']:.2f} (last {len(self.stats.returns)} ep)", refresh=False)

    @property
    def done(self) -> bool:
        """``steps`` reached, or ``max_minutes`` of training spent (in this process)."""
        if self.step >= self.cfg.steps:
            return True
        limit = self.cfg.max_minutes
        return limit is not None and time.perf_counter() - self._start_time >= 60 * limit

    def log(self, metrics: dict[str, float]) -> None:
        elapsed = time.perf_counter() - self._start_time
        metrics = {**self.stats.means(), **metrics,
                   "perf/steps_per_s": (self.step - self._start_step) / max(elapsed, 1e-9)}
        self.tracker.log(self.step, metrics)

    def checkpoint_due(self) -> bool:
        """True when a checkpoint is owed: none yet, ``checkpoint_every`` steps since the last, or
        the end of training (and not already written at this step)."""
        if self.step == self._last_checkpoint_step:
            return False
        return (self._last_checkpoint_step < 0 or self.done
                or self.step >= self._last_checkpoint_step + self.cfg.checkpoint_every)

    def checkpoint_if_due(self, modules: dict[str, torch.nn.Module], optimizers: dict[str, torch.optim.Optimizer],
                          trainer_state: dict[str, Any] | None = None,
                          tensors: dict[str, torch.Tensor] | None = None, force: bool = False) -> Path | None:
        """Save a checkpoint when ``checkpoint_every`` steps have passed since the last one, at the
        end of training, or when forced. ``trainer_state`` (JSON-able) and ``tensors`` are saved
        alongside and come back from :meth:`restore`."""
        if not (force or self.checkpoint_due()):
            return None
        self._last_checkpoint_step = self.step
        state = {
            "iteration": self.iteration,
            "numpy_rng": self.rng.bit_generator.state,
            "config": config_to_dict(self.cfg),
            "trainer": trainer_state or {},
        }
        return save_checkpoint(self.dir, self.step, modules=modules, optimizers=optimizers, tensors=tensors,
                               state=state, keep=self.cfg.keep_checkpoints)

    def close(self) -> None:
        self.pbar.close()
        self.tracker.close()


def default_run_dir(cfg: TrainConfig) -> str:
    safe_env = cfg.env.id.replace("/", "_")
    return str(Path("runs") / f"{cfg.algo}-{safe_env}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}")


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> Path:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.steps`` env steps (continuing the latest
    checkpoint in ``cfg.run_dir`` when ``resume``). Returns the run directory."""
    from drivelab.algos import get_algo

    spec = get_algo(cfg.algo)
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
    from drivelab.envs import env_spaces

    spec.build_policy(cfg, *env_spaces(cfg.env))
    run = Run(cfg, resume_from=checkpoint, progress=progress)
    try:
        spec.train(cfg, run)
    finally:
        run.close()
    return run.dir


def iteration_timing(started: float, collected: float, updated: float, env_seconds: float) -> dict[str, float]:
    """Where an iteration's wall time went; ``perf/overhead`` is the share spent neither stepping
    envs nor in the gradient update (inference, storage, bookkeeping)."""
    total = updated - started
    update_seconds = updated - collected
    return {"perf/env_s": env_seconds, "perf/update_s": update_seconds, "perf/iteration_s": total,
            "perf/overhead": max(0.0, 1.0 - (env_seconds + update_seconds) / total) if total > 0 else 0.0}
