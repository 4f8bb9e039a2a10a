"""Optimiser steps and learning-rate schedules, shared by every algorithm's update."""

from __future__ import annotations

from collections.abc import Iterable

import torch


def gradient_step(optimizer: torch.optim.Optimizer, loss: torch.Tensor,
                  clip_params: Iterable[torch.nn.Parameter] | None = None, max_grad_norm: float = float("inf")) -> torch.Tensor | None:
    """zero_grad, backward, optionally clip the global gradient norm of ``clip_params`` to
    ``max_grad_norm``, step. Returns the gradient norm before clipping when ``clip_params`` is given."""
    optimizer.zero_grad()
    loss.backward()
    norm = torch.nn.utils.clip_grad_norm_(clip_params, max_grad_norm) if clip_params is not None else None
    optimizer.step()
    return norm


def set_learning_rate(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


def linear_decay(start: float, step: int, total: int) -> float:
    """``start`` decayed linearly to 0 at ``total`` steps: a function of the step, so resume-safe."""
    return start * max(0.0, 1.0 - step / max(total, 1))
