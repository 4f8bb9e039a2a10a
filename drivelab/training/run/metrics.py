"""A run's metrics and progress: update means, the divergence guard, the progress bar and the
logged rows (``metrics.csv``, TensorBoard, MLflow through :class:`~drivelab.training.outputs.tracking.Tracker`).

What one log holds: the means of the finished training episodes (``episode/*``), the means of
the update metrics recorded since the last log (``loss/*``, ``charts/*``), and the ``perf/*``
numbers (see :mod:`drivelab.training.run`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from pathlib import Path

import torch
from tqdm.auto import tqdm

from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.outputs.tracking import Tracker
from drivelab.training.run.timing import Timing


class RunMetrics:
    """Records update metrics, logs them with the episode means and ``perf/*``, shows progress."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, episodes: EpisodeTracker, timing: Timing,
                 step: int = 0, resumed: bool = False, progress: bool = True):
        self.episodes, self.timing = episodes, timing
        self.tracker = Tracker(run_dir, cfg, resume_step=step if resumed else None)
        self.pbar = tqdm(total=cfg.steps, initial=step, unit="step", dynamic_ncols=True,
                         disable=not progress, mininterval=0.5, smoothing=0.1)
        self._sums: dict[str, torch.Tensor | float] = {}
        self._counts: dict[str, int] = {}
        self.start_time, self._start_step = time.perf_counter(), step

    def record(self, metrics: Mapping[str, torch.Tensor | float]) -> None:
        """Add an update's metrics (0-d tensors or floats); they are logged as means over the
        updates since the last log. Tensors are summed on their device: no host sync per update."""
        for name, value in metrics.items():
            if torch.is_tensor(value):
                value = value.detach()
            self._sums[name] = self._sums[name] + value if name in self._sums else value
            self._counts[name] = self._counts.get(name, 0) + 1

    def flush(self) -> dict[str, float]:
        """The means of the recorded metrics since the last flush, as floats (then starts afresh)."""
        sums = {name: value / self._counts[name] for name, value in self._sums.items()}
        self._sums, self._counts = {}, {}
        if not sums:
            return {}
        # One host sync for all tensors: stack them, then .tolist().
        tensors = {k: v for k, v in sums.items() if torch.is_tensor(v)}
        values = dict(zip(tensors, torch.stack([t.float().cpu() for t in tensors.values()]).tolist())) if tensors else {}
        return {**{k: float(v) for k, v in sums.items() if not torch.is_tensor(v)}, **values}

    def log(self, step: int, metrics: Mapping[str, float]) -> dict[str, float]:
        """Log ``metrics`` with the episode means and the perf/* numbers at ``step``; returns all
        that was logged."""
        elapsed = time.perf_counter() - self.start_time
        logged = {**self.episodes.means(), **metrics, **self.timing.fractions(),
                  "perf/steps_per_s": (step - self._start_step) / max(elapsed, 1e-9)}
        self.tracker.log(step, logged)
        return logged

    def advance(self, step: int, steps: int) -> None:
        """Move the progress bar by ``steps`` to ``step``, showing the recent episodes' return."""
        if step > self.pbar.total:  # the last batch finishes its episodes past `steps`
            self.pbar.total = step
        self.pbar.update(steps)
        means = self.episodes.means()
        if means:
            text = f"return {means['episode/return']:.2f}"
            if "episode/success_rate" in means:
                text += f", success {means['episode/success_rate']:.0%}"
            self.pbar.set_postfix_str(f"{text} (last {len(self.episodes.returns)} ep)", refresh=False)

    def close(self) -> None:
        self.pbar.close()
        self.tracker.close()


def check_finite(metrics: dict[str, float], step: int, last_checkpoint_step: int) -> dict[str, float]:
    """``metrics`` unchanged, or a one-line stop when a loss diverged (the last good checkpoint,
    at ``last_checkpoint_step``, stays the latest)."""
    for name, value in metrics.items():
        if name.startswith("loss/") and not math.isfinite(value):
            raise DrivelabError(f"training diverged at step {step}: {name} is {value}; the latest checkpoint "
                                f"(step {last_checkpoint_step}) is the last good one; lower the learning rate")
    return metrics
