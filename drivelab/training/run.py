"""What surrounds every trainer's loop: the run directory, seeding, episode statistics, metric
logging, periodic evaluation, checkpoints and resume. The loop itself lives in each
``drivelab/algos/<algo>.py`` and calls these parts; nothing here calls the algorithm back.

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

import copy
import dataclasses
import fcntl
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from tqdm.auto import tqdm

from drivelab.training.checkpoint import Checkpoint, restore, save_checkpoint
from drivelab.config import EnvConfig, TrainConfig, config_to_dict, save_config
from drivelab.envs import make_vector_env
from drivelab.errors import DrivelabError
from drivelab.training.episodes import EpisodeTracker
from drivelab.training.evaluation import run_episodes
from drivelab.training.tracking import Tracker
from drivelab.training.video import Recorder

# (tensors, JSON-able state) that a trainer saves beside its networks, e.g. a replay buffer.
ExtraState = Callable[[], tuple[dict[str, torch.Tensor], dict[str, Any]]]


class Section:
    """Accumulates the wall time spent inside ``with section:`` blocks (reused, no allocation)."""

    __slots__ = ("seconds", "_started")

    def __init__(self) -> None:
        self.seconds, self._started = 0.0, 0.0

    def __enter__(self) -> None:
        self._started = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.seconds += time.perf_counter() - self._started


class UpdateSection(Section):
    """The gradient-update section: timed, and run with ``threads`` torch intra-op threads
    (the env workers are idle while the trainer updates, so the update may use their cores;
    collection goes back to ``torch_threads``, where more threads would fight the workers)."""

    __slots__ = ("threads", "_outside")

    def __init__(self, threads: int | None = None) -> None:
        super().__init__()
        self.threads, self._outside = threads, 1

    def __enter__(self) -> None:
        if self.threads is not None:
            self._outside = torch.get_num_threads()
            torch.set_num_threads(self.threads)
        super().__enter__()

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        if self.threads is not None:
            torch.set_num_threads(self._outside)


class Timing:
    """Where wall time goes between two logs: env stepping, gradient updates, the rest."""

    def __init__(self, update_threads: int | None = None) -> None:
        self.env, self.update = Section(), UpdateSection(update_threads)
        self._since = time.perf_counter()

    def fractions(self) -> dict[str, float]:
        """The shares since the last call (then restarts the count)."""
        now = time.perf_counter()
        wall = max(now - self._since, 1e-9)
        env, update = self.env.seconds / wall, self.update.seconds / wall
        self.env.seconds = self.update.seconds = 0.0
        self._since = now
        return {"perf/env_fraction": env, "perf/update_fraction": update,
                "perf/other_fraction": max(0.0, 1.0 - env - update)}


class Run:
    """A training run's state and services (see the module docstring for the loop they serve)."""

    def __init__(self, cfg: TrainConfig, resume_from: Checkpoint | None = None, progress: bool = True):
        self.cfg = cfg
        self.dir = Path(cfg.run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self._lock = lock_run_dir(self.dir)
        remove_stale_temporaries(self.dir)
        save_config(cfg, self.dir / "config.yaml")
        self.device = torch.device(cfg.device)
        torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.step = 0
        self.iteration = 0
        self.episodes = EpisodeTracker(cfg.env.num_envs, cfg.stats_window)
        self.timing = Timing(cfg.update_threads)
        self._resume_from = resume_from
        self._last_checkpoint_step = -1
        self._best: list[float] | None = None   # (best_metric, return) of checkpoints/best
        if resume_from is not None:
            self.step = resume_from.step
            self.iteration = int(resume_from.state.get("iteration", 0))
            self.rng.bit_generator.state = resume_from.state["numpy_rng"]
            self._last_checkpoint_step = self.step
            best = resume_from.state.get("best")
            self._best = [float(best), -math.inf] if isinstance(best, (int, float)) else best
            if "episodes" in resume_from.state:
                self.episodes.load_state(resume_from.state["episodes"])
        self._next_log = self._after(self.step, cfg.log_every)
        self._next_eval = self._after(self.step, cfg.eval.every) if cfg.eval.every else math.inf
        self._sums: dict[str, torch.Tensor | float] = {}
        self._counts: dict[str, int] = {}
        self._modules: dict[str, torch.nn.Module] = {}
        self._optimizers: dict[str, torch.optim.Optimizer] = {}
        self._policy: torch.nn.Module | None = None
        self._eval_envs = None
        self._eval_worker = None                 # eval.backend ray: the actor ...
        self._eval_pending = None                # ... and (step, result ref) of the evaluation in flight
        self._extra_state: ExtraState | None = None
        self.env_restarts = 0
        self.tracker = Tracker(self.dir, cfg, resume_step=self.step if resume_from else None)
        self.pbar = tqdm(total=cfg.steps, initial=self.step, unit="step", dynamic_ncols=True,
                         disable=not progress, mininterval=0.5, smoothing=0.1)
        self._start_time = time.perf_counter()
        self._start_step = self.step

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
        self._modules, self._optimizers, self._policy = modules, optimizers, policy
        if self._resume_from is not None:
            restore(self._resume_from, modules, optimizers)
            return self._resume_from
        self._save()
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
        for name, value in metrics.items():
            if torch.is_tensor(value):
                value = value.detach()
            self._sums[name] = self._sums[name] + value if name in self._sums else value
            self._counts[name] = self._counts.get(name, 0) + 1

    def end_iteration(self, steps: int, extra_state: ExtraState | None = None) -> None:
        """Count ``steps`` new env steps, then log, evaluate and checkpoint when each is due.

        Call it where no update is half done; ``extra_state`` is called only when a checkpoint
        is written."""
        self._extra_state = extra_state
        self.step += int(steps)
        self.iteration += 1
        self._progress(int(steps))
        if self.step >= self._next_log or self.done:
            self._next_log = self._after(self.step, self.cfg.log_every)
            self.log(self._check_finite(self._flush()))
        if self._eval_pending is not None:
            self._take_evaluation(wait=False)
        if self.step >= self._next_eval:
            self._next_eval = self._after(self.step, self.cfg.eval.every)
            self.evaluate()
        if self._checkpoint_due():
            self._save(extra_state)

    @property
    def done(self) -> bool:
        """``steps`` reached, or ``max_minutes`` of training spent (in this process)."""
        if self.step >= self.cfg.steps:
            return True
        limit = self.cfg.max_minutes
        return limit is not None and time.perf_counter() - self._start_time >= 60 * limit

    def _progress(self, steps: int) -> None:
        if self.step > self.pbar.total:  # the last batch finishes its episodes past `steps`
            self.pbar.total = self.step
        self.pbar.update(steps)
        means = self.episodes.means()
        if means:
            text = f"return {means['episode/return']:.2f}"
            if "episode/success_rate" in means:
                text += f", success {means['episode/success_rate']:.0%}"
            self.pbar.set_postfix_str(f"{text} (last {len(self.episodes.returns)} ep)", refresh=False)

    def _flush(self) -> dict[str, float]:
        sums = {name: value / self._counts[name] for name, value in self._sums.items()}
        self._sums, self._counts = {}, {}
        if not sums:
            return {}
        # One host sync for all tensors: stack them, then .tolist().
        tensors = {k: v for k, v in sums.items() if torch.is_tensor(v)}
        values = dict(zip(tensors, torch.stack([t.float().cpu() for t in tensors.values()]).tolist())) if tensors else {}
        return {**{k: float(v) for k, v in sums.items() if not torch.is_tensor(v)}, **values}

    def _check_finite(self, metrics: dict[str, float]) -> dict[str, float]:
        """Stop a diverged run with one line (the last good checkpoint stays the latest)."""
        for name, value in metrics.items():
            if name.startswith("loss/") and not math.isfinite(value):
                raise DrivelabError(f"training diverged at step {self.step}: {name} is {value}; the latest checkpoint "
                                    f"(step {self._last_checkpoint_step}) is the last good one; lower the learning rate")
        return metrics

    def log(self, metrics: Mapping[str, float]) -> None:
        """Log ``metrics`` with the episode means and the perf/* numbers at the current step."""
        elapsed = time.perf_counter() - self._start_time
        self.tracker.log(self.step, {**self.episodes.means(), **metrics, **self.timing.fractions(),
                                     "perf/steps_per_s": (self.step - self._start_step) / max(elapsed, 1e-9)})

    # ---- evaluation and checkpoints -------------------------------------------------------

    def evaluate(self) -> dict[str, float]:
        """Deterministic episodes of the registered policy on the evaluation env (``cfg.eval``),
        logged as ``eval/*``; a new best ``eval.best_metric`` is saved as ``checkpoints/best``.
        With ``eval.backend: ray`` this only starts the evaluation (see :meth:`_submit_evaluation`)
        and returns {}."""
        spec = self.cfg.eval
        if spec.backend == "ray":
            self._submit_evaluation()
            return {}
        if self._eval_envs is None:
            self._eval_envs = make_vector_env(eval_env_config(self.cfg), num_envs=min(spec.num_envs, spec.episodes),
                                              autoreset_mode=AutoresetMode.DISABLED, on_restart=self.note_env_restart)
        self._policy.eval()
        summary = run_episodes(self._eval_envs, self._policy, spec.episodes, seed=spec.seed,
                               device=self.device).summary()
        self._policy.train()
        if self._record_evaluation(self.step, summary):
            best = self._save(name="best")
            (best / "eval.json").write_text(json.dumps({"step": self.step, **summary}, indent=1))
            if spec.video:
                self._film_best()
        return summary

    def _record_evaluation(self, step: int, summary: dict[str, float]) -> bool:
        """Log an evaluation's ``eval/*`` at ``step``; True when it is a new best (ties, frequent
        for rates over few episodes, go to the higher return)."""
        self.tracker.log(step, {f"eval/{k}": v for k, v in summary.items() if k != "episodes"})
        metric = self.cfg.eval.best_metric
        score = [summary[metric], summary["return_mean"]] if metric in summary else None
        if score is None or (self._best is not None and score <= self._best):
            return False
        self._best = score
        return True

    def _submit_evaluation(self) -> None:
        """Hand a copy of the policy to the evaluation actor and go on training. The state it was
        taken from is saved as ``checkpoints/.eval_pending``, which becomes ``best`` if it wins."""
        from drivelab.envs.ray_backend import EvalWorker, import_ray

        ray, spec = import_ray(), self.cfg.eval
        if self._eval_pending is not None:  # one evaluation at a time: wait for the previous one
            self._take_evaluation(wait=True)
        if self._eval_worker is None:
            self._eval_worker = ray.remote(num_cpus=self.cfg.env.actor_cpus)(EvalWorker).remote(
                eval_env_config(self.cfg), min(spec.num_envs, spec.episodes))
        self._save(name=".eval_pending")
        policy = copy.deepcopy(self._policy).cpu()
        ref = self._eval_worker.evaluate.remote(policy, spec.episodes, spec.seed, spec.best_metric, self._best, spec.video)
        self._eval_pending = (self.step, ref)

    def _take_evaluation(self, wait: bool) -> None:
        """Log the evaluation in flight if it has finished (or, with ``wait``, once it has)."""
        from drivelab.envs.ray_backend import import_ray
        from drivelab.envs.supervised import error_line

        ray = import_ray()
        step, ref = self._eval_pending
        if not wait and not ray.wait([ref], timeout=0)[0]:
            return
        self._eval_pending = None
        try:
            summary, video, strip = ray.get(ref)
        except Exception as exc:  # noqa: BLE001 - the evaluation env failed: training goes on
            print(f"drivelab: warning: evaluation at step {step} failed ({error_line(exc)})", file=sys.stderr)
            self._eval_worker = None
            return
        root = self.dir / "checkpoints"
        if not self._record_evaluation(step, summary):
            return
        shutil.rmtree(root / "best", ignore_errors=True)
        os.replace(root / ".eval_pending", root / "best")
        (root / "best" / "eval.json").write_text(json.dumps({"step": step, **summary}, indent=1))
        if video is not None:
            path = self.dir / "videos" / f"step_{step:012d}.mp4"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(video)
            self.tracker.log_video(step, path, strip)

    def _film_best(self) -> None:
        """One evaluation episode of the new best policy as ``RUN/videos/step_<N>.mp4`` (notebook
        003's habit), in TensorBoard as a strip of frames and in MLflow as an artifact."""
        recorder = Recorder(self.dir / "videos" / f"step_{self.step:012d}.mp4", max_episodes=1, thumbnails=8)
        envs = make_vector_env(eval_env_config(self.cfg), num_envs=1, autoreset_mode=AutoresetMode.DISABLED,
                               render_mode="rgb_array")
        self._policy.eval()
        try:
            run_episodes(envs, self._policy, 1, seed=self.cfg.eval.seed, device=self.device, recorder=recorder)
        finally:
            envs.close()
            self._policy.train()
        self.tracker.log_video(self.step, recorder.paths[0], recorder.strip())

    def _checkpoint_due(self) -> bool:
        """None yet, ``checkpoint_every`` steps since the last, or the end of training."""
        if self.step == self._last_checkpoint_step:
            return False
        return (self._last_checkpoint_step < 0 or self.done
                or self.step >= self._last_checkpoint_step + self.cfg.checkpoint_every)

    def _save(self, extra_state: ExtraState | None = None, name: str | None = None) -> Path:
        for module_name, module in self._modules.items():  # never write a diverged network
            for key, value in module.state_dict().items():
                if value.is_floating_point() and not torch.isfinite(value).all():
                    raise DrivelabError(f"training diverged at step {self.step}: '{module_name}' weight {key} is not "
                                        f"finite; not saved (the latest checkpoint, step {self._last_checkpoint_step}, "
                                        "is the last good one); lower the learning rate")
        tensors, trainer_state = extra_state() if extra_state is not None else ({}, {})
        state = {"iteration": self.iteration, "numpy_rng": self.rng.bit_generator.state,
                 "config": config_to_dict(self.cfg), "trainer": trainer_state, "best": self._best,
                 "episodes": self.episodes.state()}
        if name is None:
            self._last_checkpoint_step = self.step
        return save_checkpoint(self.dir, self.step, modules=self._modules, optimizers=self._optimizers,
                               tensors=tensors, state=state, keep=self.cfg.keep_checkpoints, dirname=name)

    def checkpoint_now(self) -> Path | None:
        """After an interrupt (Ctrl-C, SIGTERM): save the current state unless it is saved already
        (the networks as after the last update, at the step count of the last full iteration)."""
        if not self._modules or self.step == self._last_checkpoint_step:
            return None
        return self._save(self._extra_state)

    def close(self, interrupted: bool = False) -> None:
        """Release envs, workers, trackers and the lock; the evaluation in flight is waited for
        (so the last one is logged) unless the run was ``interrupted``."""
        if self._eval_pending is not None and not interrupted:
            self._take_evaluation(wait=True)
        if self._eval_worker is not None:
            from drivelab.envs.ray_backend import import_ray

            import_ray().kill(self._eval_worker, no_restart=True)
        if self._eval_envs is not None:
            self._eval_envs.close()
        self.pbar.close()
        self.tracker.close()
        self._lock.close()  # releases the lock


def lock_run_dir(run_dir: Path):
    """An exclusive lock on ``RUN/.lock`` for the lifetime of the returned file: a second writer
    (a fresh run or a --resume) is refused; a killed process's lock goes with it (flock)."""
    handle = open(run_dir / ".lock", "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        owner = handle.read().strip() or "?"
        handle.close()
        raise DrivelabError(f"run directory {run_dir} is in use by another drivelab process (pid {owner})") from None
    handle.seek(0)
    handle.truncate()
    handle.write(str(os.getpid()))
    handle.flush()
    return handle


def remove_stale_temporaries(run_dir: Path) -> None:
    """Checkpoint directories half-written by a killed process (``checkpoints/.tmp_*``): with the
    lock held, none of them can still be in use."""
    for tmp in [*(run_dir / "checkpoints").glob(".tmp_*"), run_dir / "checkpoints" / ".eval_pending"]:
        shutil.rmtree(tmp, ignore_errors=True)


def eval_env_config(cfg: TrainConfig) -> EnvConfig:
    """The env config of periodic evaluation: the training env's, or ``eval.env_id`` with the
    training env's wrappers and ``eval.kwargs`` instead of its kwargs."""
    if cfg.eval.env_id is None or cfg.eval.env_id == cfg.env.id:
        return dataclasses.replace(cfg.env, kwargs={**cfg.env.kwargs, **cfg.eval.kwargs})
    return dataclasses.replace(cfg.env, id=cfg.eval.env_id, kwargs=dict(cfg.eval.kwargs))

