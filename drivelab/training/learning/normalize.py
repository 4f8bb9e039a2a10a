"""Running statistics kept as module buffers, so they travel with the weights in checkpoints and
evaluation uses exactly the statistics the policy was trained with."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


class RunningMeanStd(nn.Module):
    """Running mean and variance over batches (Chan et al.'s parallel update).

    ``update(x)`` takes (B, *shape); ``normalize(x)`` returns clip((x - mean) / sqrt(var + eps)).
    """

    def __init__(self, shape: tuple[int, ...] = (), clip: float = 10.0, eps: float = 1e-8):
        super().__init__()
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(shape, dtype=torch.float64))
        self.register_buffer("count", torch.tensor(1e-4, dtype=torch.float64))
        self.clip, self.eps = clip, eps

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.to(torch.float64)
        batch_mean, batch_var, n = x.mean(0), x.var(0, unbiased=False), x.shape[0]
        delta = batch_mean - self.mean
        total = self.count + n
        self.mean += delta * n / total
        m2 = self.var * self.count + batch_var * n + delta.pow(2) * self.count * n / total
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        z = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.eps)
        return z.clamp(-self.clip, self.clip)

    def scale(self, x: torch.Tensor) -> torch.Tensor:
        """x / std, without centring (reward scaling keeps the reward's sign)."""
        return x / torch.sqrt(self.var.to(x.dtype) + self.eps)


class RewardScaler:
    """Divides rewards by the running std of the discounted return (Engstrom et al. 2020,
    "Implementation Matters"), so the critic's targets keep a stable scale whatever the
    reward's units. The statistics (``rms``) are a module, checkpointed with the agent; the
    per-env discounted returns carry across rollouts and restart at episode ends."""

    def __init__(self, num_envs: int, gamma: float):
        self.rms = RunningMeanStd(())
        self.gamma = gamma
        self.discounted_return = np.zeros(num_envs)

    def scale_in_place(self, rewards: np.ndarray, dones: np.ndarray) -> None:
        """Scale a (T, N) rollout of ``rewards`` in place; ``dones`` (T, N) ends the returns.

        The statistics are updated once per rollout (not per step: cheaper, and every reward
        of a rollout is scaled alike)."""
        returns = np.empty_like(rewards, dtype=np.float64)
        for t in range(len(rewards)):
            self.discounted_return = self.discounted_return * self.gamma + rewards[t]
            returns[t] = self.discounted_return
            self.discounted_return[dones[t]] = 0.0
        self.rms.update(torch.as_tensor(returns.reshape(-1)))
        rewards[:] = self.rms.scale(torch.as_tensor(rewards)).numpy()
