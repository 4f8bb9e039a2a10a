"""Returns and advantages as pure functions over (T, N) arrays: time first, then envs.

``dones[t, i]`` is True when env ``i``'s episode ended at step ``t`` (terminated or truncated):
nothing after step ``t`` is added to the returns of steps ``<= t``.
"""

from __future__ import annotations

import numpy as np


def reward_to_go(rewards: np.ndarray, dones: np.ndarray, gamma: float) -> np.ndarray:
    """Discounted reward-to-go, R_t = sum_{t'=t}^{T_end} gamma^(t'-t) r_t' (notebook 001).

    Args:
        rewards: (T, N) or (T,) rewards.
        dones: same shape; True where an episode ends at that step.
        gamma: discount factor.

    Returns:
        (T, N) or (T,) float32 array of rewards-to-go. The tail of an episode that has not ended
        by step T-1 gets the discounted sum of the rewards seen so far (no bootstrap: REINFORCE
        has no critic; collect whole episodes to avoid the bias).
    """
    rewards = np.asarray(rewards, dtype=np.float64)
    not_done = 1.0 - np.asarray(dones, dtype=np.float64)
    out = np.zeros_like(rewards)
    running = np.zeros_like(rewards[0])
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running * not_done[t]
        out[t] = running
    return out.astype(np.float32)


def normalize(x: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """(x - mean) / (std + eps) over all elements."""
    return (x - x.mean()) / (x.std() + eps)
