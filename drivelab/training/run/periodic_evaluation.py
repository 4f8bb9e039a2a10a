"""Evaluation during training, and the best checkpoint.

Every ``eval.every`` steps the policy plays ``eval.episodes`` deterministic episodes on the
evaluation env (:func:`eval_env_config`), logged as ``eval/*``. A new best ``eval.best_metric``
(ties go to the higher return) is kept as ``checkpoints/best`` with its ``eval.json`` and, with
``eval.video``, one filmed episode ``RUN/videos/step_<N>.mp4``. With ``eval.cost_limit``, an
evaluation whose mean episode cost is within the limit beats any that is not (``new_best``).

Both backends play :func:`~drivelab.training.collection.evaluation.evaluation_round` and finish in
:meth:`RunEvaluation._finish`. ``local``: the trainer pauses and plays on its own envs. ``ray``:
an :class:`~drivelab.training.collection.evaluation.EvalActor` plays a CPU copy of the policy while training
goes on; the state the copy was taken from is saved as ``checkpoints/.eval_pending``, which becomes
``best`` if it wins, and the results are logged at the step the copy was taken.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.config import EnvConfig, TrainConfig
from drivelab.envs import make_vector_env
from drivelab.envs.ray_backend import import_ray
from drivelab.envs.supervised import error_line
from drivelab.training.collection.evaluation import EvalActor, evaluation_round, new_best
from drivelab.training.outputs.tracking import Tracker


class RunEvaluation:
    """Periodic evaluation of a run's policy and its best checkpoint (see the module docstring).
    ``save(name)`` writes the run's current state as ``checkpoints/<name>``."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, tracker: Tracker, device: torch.device,
                 save: Callable[[str], Path], on_restart: Callable[[int], None], best: list[float] | None = None,
                 on_result: Callable[[int, dict[str, float]], None] | None = None):
        self.cfg, self.dir, self.tracker, self.device = cfg, run_dir, tracker, device
        self.env_cfg = eval_env_config(cfg)
        self.best = best                 # the score of checkpoints/best (evaluation.new_best)
        self._save, self._on_restart, self._on_result = save, on_restart, on_result
        self._envs = None                # local: the evaluation envs, built at the first evaluation
        self._actor = None               # ray: the actor ...
        self._pending = None             # ... and (step, result ref) of the evaluation in flight

    def evaluate(self, step: int, policy: torch.nn.Module) -> dict[str, float]:
        """Evaluate ``policy`` as it is at ``step``: its summary, or {} when the Ray actor took it."""
        spec = self.cfg.eval
        if spec.backend == "ray":
            self._submit(step, policy)
            return {}
        if self._envs is None:
            self._envs = make_vector_env(self.env_cfg, num_envs=min(spec.num_envs, spec.episodes),
                                         autoreset_mode=AutoresetMode.DISABLED, on_restart=self._on_restart)
        summary, film = evaluation_round(self._envs, self.env_cfg, policy, spec, self.best, self._video_path(step),
                                         self.device)
        self._finish(step, summary, film, keep=lambda: self._save("best"))
        return summary

    def _submit(self, step: int, policy: torch.nn.Module) -> None:
        """Hand a copy of ``policy`` to the actor (one evaluation at a time) and go on training."""
        ray, spec = import_ray(), self.cfg.eval
        if self._pending is not None:
            self.poll(wait=True)
        if self._actor is None:
            self._actor = ray.remote(num_cpus=self.cfg.env.actor_cpus)(EvalActor).remote(
                self.env_cfg, min(spec.num_envs, spec.episodes))
        self._save(".eval_pending")
        self._pending = (step, self._actor.evaluate.remote(copy.deepcopy(policy).cpu(), spec, self.best))

    def poll(self, wait: bool = False) -> None:
        """Finish the evaluation in flight if it has ended (or, with ``wait``, once it has)."""
        if self._pending is None:
            return
        ray = import_ray()
        step, ref = self._pending
        if not wait and not ray.wait([ref], timeout=0)[0]:
            return
        self._pending = None
        try:
            summary, video, strip = ray.get(ref)
        except Exception as exc:  # noqa: BLE001 - the evaluation env failed: training goes on
            print(f"drivelab: warning: evaluation at step {step} failed ({error_line(exc)})", file=sys.stderr)
            self._actor = None
            return
        film = None
        if video is not None:  # filmed in the actor: the bytes become the run's video file
            film = (self._video_path(step), strip)
            film[0].parent.mkdir(parents=True, exist_ok=True)
            film[0].write_bytes(video)
        self._finish(step, summary, film, keep=self._promote_pending)

    def _finish(self, step: int, summary: dict[str, float], film: tuple[Path, np.ndarray | None] | None,
                keep: Callable[[], Path]) -> None:
        """Log ``eval/*`` at ``step``; on a new best, ``keep()`` makes ``checkpoints/best``, which
        gets the summary as ``eval.json``, and the filmed episode is logged."""
        self.tracker.log(step, {f"eval/{k}": v for k, v in summary.items() if k != "episodes"})
        score = new_best(summary, self.cfg.eval.best_metric, self.best, self.cfg.eval.cost_limit)
        if score is not None:
            self.best = score
            (keep() / "eval.json").write_text(json.dumps({"step": step, **summary}, indent=1))
            if film is not None:
                self.tracker.log_video(step, *film)
        if self._on_result is not None:
            self._on_result(step, summary)

    def _promote_pending(self) -> Path:
        """``checkpoints/.eval_pending`` (the state the actor's copy was taken from) becomes ``best``."""
        root = self.dir / "checkpoints"
        shutil.rmtree(root / "best", ignore_errors=True)
        os.replace(root / ".eval_pending", root / "best")
        return root / "best"

    def _video_path(self, step: int) -> Path:
        return self.dir / "videos" / f"step_{step:012d}.mp4"

    def close(self, interrupted: bool = False) -> None:
        """Wait for the evaluation in flight (so the last one is logged) unless ``interrupted``,
        then release the actor or the envs."""
        if self._pending is not None and not interrupted:
            self.poll(wait=True)
        if self._actor is not None:
            import_ray().kill(self._actor, no_restart=True)
        if self._envs is not None:
            self._envs.close()


def eval_env_config(cfg: TrainConfig) -> EnvConfig:
    """The env config of periodic evaluation: the training env's, or ``eval.env_id`` with the
    training env's wrappers and ``eval.kwargs`` instead of its kwargs (those that shape the
    observation stay: :meth:`EnvConfig.on`)."""
    if cfg.eval.env_id is None or cfg.eval.env_id == cfg.env.id:
        return dataclasses.replace(cfg.env.played(), kwargs={**cfg.env.kwargs, **cfg.eval.kwargs})
    return cfg.env.on(cfg.eval.env_id, cfg.eval.kwargs)
