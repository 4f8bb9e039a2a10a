"""Where a run's wall time goes: stepping envs, gradient updates, and the rest (``perf/*``),
and what the machine computes fast (:func:`machine`, :func:`native_bf16`).

A loop wraps its env steps in ``with run.timing.env:`` and its updates in
``with run.timing.update:``; :meth:`Timing.fractions` turns the sums into shares at each log.
The sections are reused, so timing allocates nothing per step.
"""

from __future__ import annotations

import functools
import os
import platform
import time
from pathlib import Path

import torch


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


@functools.cache  # asked at every update (offpolicy.update_precision); the answer never changes
def native_bf16(device: torch.device) -> bool | None:
    """Whether ``device`` computes bfloat16 in hardware: on x86 CPUs AVX512-BF16 or AMX, on NVIDIA
    GPUs compute capability 8.0 (Ampere) or newer, on ROCm always; None where torch cannot tell
    (other CPUs). Without it torch emulates bfloat16 through float32, and a bfloat16 update is
    slower, not faster (7x slower than float32 on an AVX2-only CPU:
    benchmarks/results/sac_update_cost_avx2.json)."""
    if device.type == "cuda":
        return torch.version.hip is not None or torch.cuda.get_device_capability(device)[0] >= 8
    if device.type != "cpu" or platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    probes = [getattr(torch.cpu, name) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
              if hasattr(torch.cpu, name)]  # private probes: a torch without them cannot tell
    return any(probe() for probe in probes) if probes else None


def machine() -> dict:
    """What a benchmark's JSON records of the machine it ran on: its numbers depend on it."""
    return {"cpu": cpu_model(), "cpu_cores": os.cpu_count(), "bf16_in_hardware": native_bf16(torch.device("cpu")),
            "torch": torch.__version__}
