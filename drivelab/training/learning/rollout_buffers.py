"""Storage of the on-policy family: a fixed-length rollout buffer for A2C and PPO, flattened into
a :class:`RolloutBatch` with GAE advantages, and growing storage of whole episodes for
REINFORCE and GRPO. Both are preallocated and written in place every step."""

from __future__ import annotations

from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch

from drivelab.training.learning.returns import gae


class RolloutBatch(NamedTuple):
    """A rollout flattened to B = T * N samples for the update."""
    obs: torch.Tensor         # (B, *obs_shape)
    actions: torch.Tensor     # (B,) Discrete, (B, act_dim) Box
    log_probs: torch.Tensor   # (B,) log pi_old(a|s)
    values: torch.Tensor      # (B,) V_old(s)
    advantages: torch.Tensor  # (B,)
    returns: torch.Tensor     # (B,) critic targets (advantages + values)
    # the same for the cost, with a cost critic (PPO-Lagrangian; None otherwise)
    cost_values: torch.Tensor | None = None      # (B,) V_c,old(s)
    cost_advantages: torch.Tensor | None = None  # (B,) GAE of the costs
    cost_returns: torch.Tensor | None = None     # (B,) cost critic targets


class RolloutBuffer:
    """Preallocated (T, N, ...) storage, written in place every step. With ``costs`` it also keeps
    each step's cost, V_c(s_t) and V_c(s_{t+1}), for the cost's own GAE (PPO-Lagrangian)."""

    def __init__(self, num_steps: int, num_envs: int, obs_space: gym.Space, act_space: gym.Space,
                 device: torch.device, costs: bool = False):
        discrete = isinstance(act_space, gym.spaces.Discrete)
        obs_dtype = torch.uint8 if obs_space.dtype == np.uint8 else torch.float32
        shape = (num_steps, num_envs)
        self.obs = torch.zeros(shape + obs_space.shape, dtype=obs_dtype, device=device)
        self.actions = torch.zeros(shape + (() if discrete else act_space.shape),
                                   dtype=torch.long if discrete else torch.float32, device=device)
        self.log_probs = torch.zeros(shape, device=device)
        self.values = torch.zeros(shape, device=device)
        # Rewards and episode ends stay in numpy: GAE is a pure numpy function (drivelab.training.learning.returns).
        self.rewards = np.zeros(shape, np.float32)
        self.next_values = np.zeros(shape, np.float32)
        self.terminated = np.zeros(shape, bool)
        self.dones = np.zeros(shape, bool)
        self.costs = np.zeros(shape, np.float32) if costs else None
        self.cost_values = torch.zeros(shape, device=device) if costs else None
        self.cost_next_values = np.zeros(shape, np.float32) if costs else None

    def write_env(self, env: int, rollout) -> None:
        """Column ``env`` from a rollout that an env worker played (a
        :class:`~drivelab.training.collection.worker_rollouts.WorkerRollout`: (T, ...) arrays)."""
        device = self.values.device
        self.obs[:, env] = torch.as_tensor(rollout.obs, device=device)
        self.actions[:, env] = torch.as_tensor(rollout.actions, device=device)
        self.log_probs[:, env] = torch.as_tensor(rollout.log_probs, device=device)
        self.values[:, env] = torch.as_tensor(rollout.values, device=device)
        self.rewards[:, env] = rollout.rewards
        self.terminated[:, env] = rollout.terminated
        self.dones[:, env] = rollout.terminated | rollout.truncated
        self.next_values[:, env] = rollout.final_values
        if self.costs is not None:
            self.costs[:, env] = rollout.costs
            self.cost_values[:, env] = torch.as_tensor(rollout.cost_values, device=device)
            self.cost_next_values[:, env] = rollout.final_cost_values

    def batch(self, gamma: float, gae_lambda: float, cost_gamma: float | None = None) -> RolloutBatch:
        """The flat batch with GAE(``gamma``, ``gae_lambda``) advantages; with costs, also the
        cost's GAE(``cost_gamma``, ``gae_lambda``): the same estimator with c_t for r_t and V_c for V."""
        advantages, returns = gae(self.rewards, self.values.cpu().numpy(), self.next_values, self.terminated,
                                  self.dones, gamma, gae_lambda)
        device = self.values.device
        flat = lambda x: torch.as_tensor(x, device=device).flatten()  # (T, N) -> (B,)
        batch = RolloutBatch(
            obs=self.obs.flatten(0, 1), actions=self.actions.flatten(0, 1), log_probs=self.log_probs.flatten(),
            values=self.values.flatten(), advantages=flat(advantages), returns=flat(returns),
        )
        if self.costs is None:
            return batch
        cost_advantages, cost_returns = gae(self.costs, self.cost_values.cpu().numpy(), self.cost_next_values,
                                            self.terminated, self.dones, cost_gamma, gae_lambda)
        return batch._replace(cost_values=self.cost_values.flatten(), cost_advantages=flat(cost_advantages),
                              cost_returns=flat(cost_returns))


class EpisodeStorage:
    """Preallocated (T, N, ...) arrays for rollouts of whole episodes (REINFORCE, GRPO), whose
    length is not known in advance: T doubles when full, so growth is rare and amortised.

    ``recorded[t, i]`` marks the steps that belong to the batch (envs that finished their share
    keep stepping, masked, until the others are done); ``tag[t, i]`` is free for the trainer
    (GRPO stores the group round of each step).
    """

    def __init__(self, capacity: int, num_envs: int, obs_space: gym.Space, act_space: gym.Space):
        discrete = isinstance(act_space, gym.spaces.Discrete)
        shape = (capacity, num_envs)
        self.obs = np.zeros(shape + obs_space.shape, obs_space.dtype)
        self.actions = np.zeros(shape + (() if discrete else act_space.shape), np.int64 if discrete else np.float32)
        self.log_probs = np.zeros(shape, np.float32)
        self.rewards = np.zeros(shape, np.float32)
        self.dones = np.zeros(shape, bool)
        self.recorded = np.zeros(shape, bool)
        self.tag = np.full(shape, -1, np.int64)

    def ensure(self, t: int) -> None:
        """Make row t writable."""
        if t < len(self.rewards):
            return
        for name in ("obs", "actions", "log_probs", "rewards", "dones", "recorded", "tag"):
            old = getattr(self, name)
            grown = np.zeros((2 * len(old), *old.shape[1:]), old.dtype)
            grown[: len(old)] = old
            setattr(self, name, grown)
