"""bfloat16 updates: whether the hardware computes bfloat16, the context of an update, and the
float32 output layers inside it (the ``bf16_updates`` option of DDPG, TD3 and SAC)."""

from __future__ import annotations

import contextlib
import functools
import platform
from typing import TYPE_CHECKING

import torch
from torch import nn

if TYPE_CHECKING:
    from drivelab.training.learning.hyperparams import OffPolicyParams


def in_float32(layer: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """layer(x) computed in float32, also inside a bfloat16 autocast region (``bf16_updates``).

    bfloat16 keeps 8 bits of mantissa: a Q-value near 300 would be rounded to steps of 2, larger
    than a step's reward, so the output layers (Q, the actor's mean and log sigma) stay float32
    while the hidden layers, where the time goes, run in bfloat16. Outside autocast (acting,
    evaluation) it is layer(x), without the context's cost."""
    device = x.device.type
    if not (torch.amp.is_autocast_available(device) and torch.is_autocast_enabled(device)):
        return layer(x)
    with torch.autocast(device, enabled=False):
        return layer(x.float())


@functools.cache  # asked at every update (update_precision); the answer never changes
def native_bf16(device: torch.device) -> bool | None:
    """Whether ``device`` computes bfloat16 in hardware: on x86 CPUs AVX512-BF16 or AMX, on NVIDIA
    GPUs compute capability 8.0 (Ampere) or newer, on ROCm always; None where torch cannot tell
    (other CPUs). Without it torch emulates bfloat16 through float32, and a bfloat16 update is
    slower, not faster (``benchmarks/sac_update_cost.py`` times both precisions)."""
    if device.type == "cuda":
        return torch.version.hip is not None or torch.cuda.get_device_capability(device)[0] >= 8
    if device.type != "cpu" or platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    probes = [getattr(torch.cpu, name) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
              if hasattr(torch.cpu, name)]  # private probes: a torch without them cannot tell
    return any(probe() for probe in probes) if probes else None


def updates_in_bf16(hp: OffPolicyParams, device: torch.device) -> bool:
    """Whether the learner's updates run in bfloat16: ``bf16_updates`` true, or auto on a device
    that computes bfloat16 in hardware."""
    return hp.bf16_updates is True or (hp.bf16_updates == "auto" and native_bf16(device) is True)


def update_precision(hp: OffPolicyParams, device: torch.device) -> contextlib.AbstractContextManager:
    """The context of the learner's updates: bfloat16 autocast where :func:`updates_in_bf16`, else a no-op."""
    if not updates_in_bf16(hp, device):
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)
