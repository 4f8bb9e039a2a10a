"""Returns and advantages as pure functions over (T, N) arrays: time first, then envs.

``dones[t, i]`` is True when env ``i``'s episode ended at step ``t`` (terminated or truncated):
nothing after step ``t`` is added to the returns of steps ``<= t``.
"""

from __future__ import annotations

import numpy as np


def reward_to_go(rewards: np.ndarray, dones: np.ndarray, gamma: float) -> np.ndarray:
    """Discounted reward-to-go, R_t = sum_{t'=t}^{T_end} gamma^(t'-t) r_t' (the policy-gradient
    theorem's reward-to-go form; Sutton & Barto 2018, section 13.3).

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


def gae(rewards: np.ndarray, values: np.ndarray, next_values: np.ndarray, terminated: np.ndarray,
        dones: np.ndarray, gamma: float, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation (Schulman et al. 2016, eq. 16) over a (T, N) rollout.

    Args:
        rewards: (T, N) r_t.
        values: (T, N) V(s_t) under the rollout's critic.
        next_values: (T, N) V(s_{t+1}) of the *true* next state: ``values[t+1]`` inside an
            episode, the critic's value of the final observation on a truncated step (time limit:
            the episode could have gone on, so we bootstrap), and the value of the observation
            after the rollout on its last step. Ignored where ``terminated``.
        terminated: (T, N) the episode reached a terminal state at t: no future value.
        dones: (T, N) terminated or truncated at t: the next row belongs to a new episode, so the
            lambda-trace stops here.
        gamma, lam: discount and GAE lambda (lam=1: Monte-Carlo returns minus V; lam=0: TD(0)).

    Returns:
        (advantages, returns), both (T, N) float32, with returns = advantages + values (the
        critic's regression target, TD(lambda)).

        delta_t = r_t + gamma * (1 - terminated_t) * V(s_{t+1}) - V(s_t)
        A_t     = delta_t + gamma * lam * (1 - done_t) * A_{t+1}
    """
    rewards, values, next_values = (np.asarray(x, np.float64) for x in (rewards, values, next_values))
    bootstrap = 1.0 - np.asarray(terminated, np.float64)
    carry = 1.0 - np.asarray(dones, np.float64)
    deltas = rewards + gamma * bootstrap * next_values - values
    advantages = np.zeros_like(deltas)
    running = np.zeros_like(deltas[0])
    for t in range(len(deltas) - 1, -1, -1):
        running = deltas[t] + gamma * lam * carry[t] * running
        advantages[t] = running
    return advantages.astype(np.float32), (advantages + values).astype(np.float32)


def group_relative_advantages(returns: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """GRPO's outcome advantage (Shao et al. 2024, DeepSeekMath, eq. 4 of sec. 4.1.2):
    each member's return relative to its group, (R - mean_group) / (std_group + eps).

    Args:
        returns: (num_groups, group_size) episode returns; a row is one group of rollouts that
            started from the same state.
    Returns:
        (num_groups, group_size) float32. A group whose members all scored the same gets zeros:
        it says nothing about which actions were better.
    """
    returns = np.asarray(returns, np.float64)
    mean = returns.mean(axis=1, keepdims=True)
    std = returns.std(axis=1, keepdims=True)
    return ((returns - mean) / (std + eps)).astype(np.float32)


def group_relative_step_advantages(rewards_to_go: np.ndarray, alive: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """Per-step GRPO advantage for one group: each member's reward-to-go at episode step t
    relative to the members of its group still running at step t.

    Args:
        rewards_to_go: (L, G) reward-to-go of member g at its episode step t (0 where not alive).
        alive: (L, G) True where member g's episode is still running at step t.
    Returns:
        (L, G) float32, 0 where not alive and at steps where fewer than two members are alive
        (no comparison is possible).
    """
    rtg = np.asarray(rewards_to_go, np.float64)
    alive = np.asarray(alive, bool)
    count = alive.sum(axis=1, keepdims=True)
    safe = np.maximum(count, 1)
    mean = np.where(alive, rtg, 0.0).sum(axis=1, keepdims=True) / safe
    var = np.where(alive, (rtg - mean) ** 2, 0.0).sum(axis=1, keepdims=True) / safe
    adv = (rtg - mean) / (np.sqrt(var) + eps)
    return np.where(alive & (count >= 2), adv, 0.0).astype(np.float32)
