"""A run's metrics and progress: update means, the divergence guard, the progress bar and the
logged rows (``metrics.csv``, TensorBoard, MLflow through :class:`~drivelab.training.outputs.tracking.Tracker`).

What one log holds: the means of the finished training episodes (``episode/*``), the means of
the update metrics recorded since the last log (``loss/*``, ``charts/*``), for an env with a cost
the cost paid since the run began (``charts/cumulative_cost``, ``charts/cost_rate``), and the
``perf/*`` numbers (see :mod:`drivelab.training.run`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

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
        self.pbar = tqdm(total=cfg.steps, initial=step, unit="step", dynamic_ncols=True, disable=not progress)
        self._steps, self._limit_s = cfg.steps, None if cfg.max_minutes is None else 60 * cfg.max_minutes
        self._step, self._next_draw = step, 0.0
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

    def stop_if_diverged(self, step: int, last_checkpoint_step: int) -> None:
        """One line (:func:`check_finite`) as soon as a recorded loss is non-finite, checked every
        iteration and not only at logs: non-finite weights would make the next rollout fail inside
        torch instead. One host sync for the losses recorded since the last log."""
        losses = {name: value for name, value in self._sums.items() if name.startswith("loss/")}
        if not losses:
            return
        values = torch.stack([torch.as_tensor(v, dtype=torch.float32).detach().cpu() for v in losses.values()])
        if not bool(torch.isfinite(values).all()):
            check_finite(dict(zip(losses, values.tolist())), step, last_checkpoint_step)

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
        logged = {**self.episodes.means(), **self.cost_totals(step), **metrics,
                  **self.timing.fractions(), "perf/steps_per_s": (step - self._start_step) / max(elapsed, 1e-9)}
        self.tracker.log(step, logged)
        return logged

    def cost_totals(self, step: int) -> dict[str, float]:
        """For an env with a cost, the cost paid since the run began, the safe-exploration measure
        of Safety Gym (Ray, Achiam & Amodei 2019): ``charts/cumulative_cost``, summed over the
        finished training episodes, and ``charts/cost_rate``, that sum per env step trained
        (steps of episodes still running count, their cost not yet). {} for an env without cost."""
        if self.episodes.cost_episodes == 0:
            return {}
        total = self.episodes.cost_total
        return {"charts/cumulative_cost": total, "charts/cost_rate": total / max(step, 1)}

    def advance(self, step: int) -> None:
        """Move the progress bar to ``step``. It is redrawn at most twice a second, from the step
        count and the clock only (no host sync), so it costs nothing per env step."""
        self._step = step
        now = time.perf_counter()
        if now >= self._next_draw and not self.pbar.disable:
            self._next_draw = now + 0.5
            self._draw(now)

    def _draw(self, now: float) -> None:
        """Show progress against the bound predicted to end the run first (:func:`bar_view`):
        env steps against ``steps``, or the time spent against ``max_minutes``."""
        elapsed = now - self.start_time
        view = bar_view(self._step, self._steps, elapsed, self._limit_s, self._start_step)
        self.pbar.n = view.n
        if view.total != self.pbar.total:
            self.pbar.total = view.total
            if hasattr(self.pbar, "container"):  # a Jupyter widget (tqdm.auto): its bar keeps its own maximum
                self.pbar.container.children[1].max = view.total
        # tqdm's own format for steps; for time, its bar with our text (tqdm would count seconds as items)
        self.pbar.bar_format = None
        if view.by_time:
            rate = (self._step - self._start_step) / max(elapsed, 1e-9)
            clock = f"{tqdm.format_interval(view.n)}/{tqdm.format_interval(view.total)} of max_minutes"
            self.pbar.bar_format = "{l_bar}{bar}| " + f"{clock} [{self._step:,} steps, {rate:,.0f} step/s" + "{postfix}]"
        means = self.episodes.means()
        if means:
            text = f"return {means['episode/return']:.2f}"
            if "episode/success_rate" in means:
                text += f", success {means['episode/success_rate']:.0%}"
            self.pbar.set_postfix_str(f"{text} (last {len(self.episodes.returns)} ep)", refresh=False)
        self.pbar.refresh()

    def close(self) -> None:
        if not self.pbar.disable:
            self._draw(time.perf_counter())  # where the run ended (the last advance may not have been drawn)
        self.pbar.close()
        self.tracker.close()


class BarView(NamedTuple):
    """What the progress bar shows: env steps against ``steps``, or (``by_time``) the seconds
    spent against ``max_minutes``."""
    by_time: bool
    n: float
    total: float


def bar_view(step: int, steps: int, elapsed: float, limit_s: float | None, start_step: int = 0) -> BarView:
    """Progress against the bound predicted to end the run first, at the rate of this process so
    far (``start_step``: the step it started from, above 0 on resume). A run that ``max_minutes``
    (``limit_s`` seconds) will stop before ``steps`` shows time, as a bar in steps would promise
    an end it never reaches. Until a step is played there is no rate, and the bar counts steps."""
    played = step - start_step
    if limit_s is not None and played > 0 and elapsed > 0:
        seconds_to_steps = (steps - step) * elapsed / played
        if elapsed + seconds_to_steps > limit_s:
            return BarView(True, min(elapsed, limit_s), limit_s)
    # the last batch may finish its episodes past `steps` (REINFORCE, GRPO): the total follows
    return BarView(False, step, max(steps, step))


def check_finite(metrics: dict[str, float], step: int, last_checkpoint_step: int) -> dict[str, float]:
    """``metrics`` unchanged, or a one-line stop when a loss diverged (the last good checkpoint,
    at ``last_checkpoint_step``, stays the latest)."""
    for name, value in metrics.items():
        if name.startswith("loss/") and not math.isfinite(value):
            raise DrivelabError(f"training diverged at step {step}: {name} is {value}; the latest checkpoint "
                                f"(step {last_checkpoint_step}) is the last good one: lower the learning rate "
                                "(or max_grad_norm) and resume from it")
    return metrics
