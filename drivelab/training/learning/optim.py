"""Optimisation helpers: the fused Adam of the off-policy learners, one gradient step with
clipping, learning-rate schedules, and the optimisers of DDPG and TD3."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, NamedTuple

import torch

if TYPE_CHECKING:
    from drivelab.training.learning.hyperparams import OffPolicyParams
    from drivelab.training.learning.offpolicy_nets import OffPolicyAgent


def fused_adam(params: Iterable[torch.nn.Parameter], lr: float) -> torch.optim.Adam:
    """Adam whose step is one fused kernel over all ``params`` (on CPU and CUDA; the default
    elsewhere, e.g. on the meta device). On CPU torch's default Adam steps each parameter tensor
    with about ten small ops, a noticeable share of a small network's update on CPU
    (``benchmarks/sac_update_cost.py`` times both). Same algorithm (Kingma & Ba 2015), rounding
    differs in the last bits. A resumed run keeps the Adam its checkpoint was saved with: the
    saved param_groups carry ``fused`` (None in checkpoints written by the default Adam)."""
    params = list(params)
    fused = all(p.device.type in ("cpu", "cuda") for p in params)
    return torch.optim.Adam(params, lr=lr, fused=True if fused else None)


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


class Optimizers(NamedTuple):
    """DDPG's and TD3's optimisers (SAC adds one for its temperature); the field names are the
    optimisers' names in checkpoints."""
    critic: torch.optim.Optimizer     # the critics and the (image) encoder
    actor: torch.optim.Optimizer


def make_optimizers(agent: OffPolicyAgent, hp: OffPolicyParams) -> Optimizers:
    """Adam for the critics (which also train the image encoder) and for the actor, fused: the
    learner bounds an off-policy run on two cores, and the default Adam's many small ops were a
    fifth of its update (:func:`~drivelab.training.learning.optim.fused_adam`)."""
    critic = fused_adam([*agent.encoder.parameters(), *agent.critic.parameters()], lr=hp.critic_lr)
    return Optimizers(critic=critic, actor=fused_adam(agent.actor.parameters(), lr=hp.actor_lr))
