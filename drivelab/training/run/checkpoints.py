"""A run's checkpoints: when one is due, writing one (never a diverged network), and the state a
resumed run continues from (the numpy RNG, the iteration, the best score, the episode window).

The files themselves (safetensors + ``state.json``) are :mod:`drivelab.training.outputs.checkpoint`'s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from drivelab.config import TrainConfig, config_to_dict
from drivelab.errors import DrivelabError
from drivelab.training.outputs.checkpoint import Checkpoint, save_checkpoint
from drivelab.training.outputs.episodes import EpisodeTracker

# (tensors, JSON-able state) that a trainer saves beside its networks, e.g. a replay buffer.
ExtraState = Callable[[], tuple[dict[str, torch.Tensor], dict[str, Any]]]


class RunCheckpoints:
    """Saves what :meth:`drivelab.training.run.Run.start` registered, with the run's resume state."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, rng: np.random.Generator, episodes: EpisodeTracker):
        self.cfg, self.dir, self.rng, self.episodes = cfg, run_dir, rng, episodes
        self.modules: dict[str, torch.nn.Module] = {}
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.last_step = -1     # the step of the latest numbered checkpoint (-1: none yet)

    def resume(self, checkpoint: Checkpoint) -> tuple[int, int, list[float] | None]:
        """Continue from ``checkpoint``: restore the numpy RNG and the episode window, and return
        (step, iteration, best score) to go on from."""
        state = checkpoint.state
        self.rng.bit_generator.state = state["numpy_rng"]
        if "episodes" in state:
            self.episodes.load_state(state["episodes"])
        self.last_step = checkpoint.step
        best = state.get("best")  # checkpoints of older versions saved the best metric alone
        best = [float(best), -math.inf] if isinstance(best, (int, float)) else best
        return checkpoint.step, int(state.get("iteration", 0)), best

    def due(self, step: int, done: bool) -> bool:
        """None yet, ``checkpoint_every`` steps since the last, or the end of training."""
        if step == self.last_step:
            return False
        return self.last_step < 0 or done or step >= self.last_step + self.cfg.checkpoint_every

    def save(self, step: int, iteration: int, best: list[float] | None, extra_state: ExtraState | None = None,
             name: str | None = None) -> Path:
        """Write checkpoint ``step_<step>`` (the latest), or ``checkpoints/<name>`` beside them
        (``best``, ``.eval_pending``); ``extra_state`` adds what the trainer saves itself."""
        self._refuse_diverged(step)
        tensors, trainer_state = extra_state() if extra_state is not None else ({}, {})
        state = {"iteration": iteration, "numpy_rng": self.rng.bit_generator.state,
                 "config": config_to_dict(self.cfg), "trainer": trainer_state, "best": best,
                 "episodes": self.episodes.state()}
        if name is None:
            self.last_step = step
        return save_checkpoint(self.dir, step, modules=self.modules, optimizers=self.optimizers,
                               tensors=tensors, state=state, keep=self.cfg.keep_checkpoints, dirname=name)

    def _refuse_diverged(self, step: int) -> None:
        """Stop with one line rather than write a network with a non-finite weight."""
        for module_name, module in self.modules.items():
            for key, value in module.state_dict().items():
                if value.is_floating_point() and not torch.isfinite(value).all():
                    raise DrivelabError(f"training diverged at step {step}: '{module_name}' weight {key} is not "
                                        f"finite; not saved (the latest checkpoint, step {self.last_step}, "
                                        "is the last good one); lower the learning rate")
