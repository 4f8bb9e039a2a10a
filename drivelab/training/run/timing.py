"""Where a run's wall time goes: stepping envs, gradient updates, and the rest (``perf/*``),
and what the machine computes fast (:func:`machine`, :func:`native_bf16`).

A loop wraps its env steps in ``with run.timing.env:`` and its updates in
``with run.timing.update:``; :meth:`Timing.fractions` turns the sums into shares at each log.
The sections are reused, so timing allocates nothing per step.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import torch

from drivelab.training.learning.precision import native_bf16


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


def cpu_model() -> str:
    """The CPU's model name as Linux reports it (else what ``platform`` knows)."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.partition(":")[2].strip()
    return platform.processor() or platform.machine()


def machine() -> dict:
    """What a benchmark's JSON records of the machine it ran on: its numbers depend on it."""
    return {"cpu": cpu_model(), "cpu_cores": os.cpu_count(), "bf16_in_hardware": native_bf16(torch.device("cpu")),
            "torch": torch.__version__}
