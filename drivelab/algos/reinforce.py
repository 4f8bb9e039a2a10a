"""REINFORCE: the vanilla policy gradient with reward-to-go and an entropy bonus.

The update is the policy-gradient estimator with reward-to-go (Williams 1992; Spinning Up, "VPG")::

    grad J(theta) = E_tau [ sum_t  grad log pi_theta(a_t | s_t) * R_t ],
    R_t = sum_{t' >= t} gamma^(t' - t) r_t'                      (discounted reward-to-go)

implemented as the loss ``-(1/B) sum_i log pi(a_i|s_i) * Psi_i - ent_coef * H[pi(.|s_i)]`` over
the B steps of a batch of *whole* episodes. ``Psi`` is the reward-to-go itself (``advantage:
rtg``), minus its batch mean (``mean``, a constant baseline), or standardised (``normalize``,
the default: a baseline and a per-batch step size). Every option leaves the gradient's
expectation pointing the same way; the last two cut its variance.

One iteration = reset every env with fresh seeds, run episodes until at least ``batch_steps``
steps are recorded, let the episodes in flight finish (envs that finish after the budget is
reached idle, and their steps are not recorded), then one gradient step. No episode is cut:
REINFORCE has no critic to bootstrap a cut episode with. A time-limit truncation just ends the
sum (the standard finite-horizon treatment).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from drivelab.config import TrainConfig
from drivelab.envs import make_vector_env
from drivelab.errors import DrivelabError
from drivelab.training.collection.checks import check_finite_step
from drivelab.training.learning.hyperparams import PolicyNetParams
from drivelab.training.learning.losses import policy_gradient_loss
from drivelab.training.learning.optim import gradient_step
from drivelab.training.learning.policy_nets import Policy, limit_log_std
from drivelab.training.learning.returns import normalize, reward_to_go
from drivelab.training.learning.rollout_buffers import EpisodeStorage
from drivelab.training.run import Run


@dataclass
class Params(PolicyNetParams):
    lr: float = 3e-3                  # learning rate (Adam)
    gamma: float = 0.99               # discount factor
    # Minimum recorded env steps per update; the episodes in flight are completed on top.
    batch_steps: int = 4000
    ent_coef: float = 0.0             # weight of the entropy bonus
    # rtg | mean | normalize: what multiplies grad log pi (see the module docstring).
    advantage: str = "normalize"
    max_grad_norm: float = 0.0        # clip the global gradient norm to this (0: off)

    def validate(self) -> None:
        super().validate()
        if self.advantage not in ("rtg", "mean", "normalize"):
            raise DrivelabError(f"config field 'reinforce.advantage' must be rtg, mean or normalize, got {self.advantage!r}")
        if not 0.0 <= self.gamma <= 1.0:
            raise DrivelabError(f"config field 'reinforce.gamma' must be in [0, 1], got {self.gamma}")
        if self.batch_steps < 1 or self.lr <= 0:
            raise DrivelabError("config fields 'reinforce.batch_steps' and 'reinforce.lr' must be positive")


class EpisodeBatch(NamedTuple):
    """Flat batch of the recorded steps of whole episodes (B = number of steps)."""
    obs: torch.Tensor      # (B, *obs_shape)
    actions: torch.Tensor  # (B,) for Discrete, (B, act_dim) for Box
    returns: torch.Tensor  # (B,) discounted reward-to-go


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> Policy:
    hp: Params = cfg.algo_params
    return Policy(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init)


def advantage_weights(returns: np.ndarray, mode: str) -> np.ndarray:
    """Psi from the (B,) rewards-to-go: as is, minus the batch mean, or standardised."""
    if mode == "rtg":
        return returns
    if mode == "mean":
        return returns - returns.mean()
    return normalize(returns)


def collect_episodes(envs: VectorEnv, policy: Policy, storage: EpisodeStorage, min_steps: int, gamma: float,
                     run: Run) -> tuple[EpisodeBatch, int]:
    """Run whole episodes until at least ``min_steps`` steps are recorded.

    ``envs`` must use ``AutoresetMode.DISABLED``: this loop resets finished envs itself, with
    seeds from ``run``, so that no step is wasted on Gymnasium's next-step autoreset and every
    episode's seed is reproducible. Returns the batch and the number of recorded steps.
    """
    num_envs = envs.num_envs
    everyone = np.ones(num_envs, bool)
    with run.timing.env:
        obs, _ = envs.reset(seed=run.reset_seeds(everyone))
    run.episodes.restart(everyone)
    recording = everyone.copy()      # env i's current episode belongs to the batch
    recorded_steps = 0
    t = 0
    while recording.any():
        storage.ensure(t)
        action = policy.act(torch.as_tensor(obs, device=run.device))
        with run.timing.env:
            next_obs, reward, terminated, truncated, info = envs.step(policy.to_env(action))
        check_finite_step(next_obs, reward, run.step + recorded_steps)
        done = terminated | truncated
        storage.obs[t] = obs
        storage.actions[t] = action.cpu().numpy()
        storage.rewards[t] = reward
        storage.dones[t] = done
        storage.recorded[t] = recording
        recorded_steps += int(recording.sum())
        run.episodes.step(reward, done, info, counted=recording)
        if done.any():
            # Finished envs start a new recorded episode only while the budget is not reached.
            recording[done] &= recorded_steps < min_steps
            # Every finished env is reset (idle ones too: a finished env must not be stepped).
            with run.timing.env:
                next_obs, _ = envs.reset(seed=run.reset_seeds(done), options={"reset_mask": done})
        obs = next_obs
        t += 1

    mask = storage.recorded[:t]
    returns = reward_to_go(storage.rewards[:t], storage.dones[:t], gamma)
    batch = EpisodeBatch(
        obs=torch.as_tensor(storage.obs[:t][mask], device=run.device),
        actions=torch.as_tensor(storage.actions[:t][mask], device=run.device),
        returns=torch.as_tensor(returns[mask], device=run.device),
    )
    return batch, recorded_steps


def update(policy: Policy, optimizer: torch.optim.Optimizer, batch: EpisodeBatch, hp: Params) -> dict[str, torch.Tensor]:
    """One gradient step on the REINFORCE loss over the B steps of ``batch``; returns the logged
    losses (0-d tensors)."""
    weights = torch.as_tensor(advantage_weights(batch.returns.cpu().numpy(), hp.advantage), device=batch.returns.device)
    dist = policy.distribution(batch.obs)
    pg_loss = policy_gradient_loss(dist.log_prob(batch.actions), weights)
    entropy = dist.entropy().mean()
    loss = pg_loss - hp.ent_coef * entropy
    grad_norm = gradient_step(optimizer, loss, policy.parameters(), hp.max_grad_norm if hp.max_grad_norm > 0 else float("inf"))
    return {"loss/policy": pg_loss.detach(), "loss/entropy": entropy.detach(), "loss/grad_norm": grad_norm,
            "batch/return_to_go_mean": batch.returns.mean()}


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    envs = make_vector_env(cfg.env, autoreset_mode=AutoresetMode.DISABLED, on_restart=run.note_env_restart)
    obs_space, act_space = envs.single_observation_space, envs.single_action_space
    policy = build_policy(cfg, obs_space, act_space).to(run.device)
    optimizer = torch.optim.Adam(policy.parameters(), lr=hp.lr)
    run.start({"policy": policy}, {"policy": optimizer}, policy=policy)
    storage = EpisodeStorage(2 * -(-hp.batch_steps // envs.num_envs), envs.num_envs, obs_space, act_space)
    try:
        while not run.done:
            std_log = limit_log_std(policy, hp, run.step, cfg.steps)  # optional std schedule
            # 1. Whole episodes until batch_steps steps are recorded; discounted rewards-to-go.
            #    The last batch asks only for the steps left (its episodes in flight still end).
            budget = min(hp.batch_steps, run.steps_left)
            batch, steps = collect_episodes(envs, policy, storage, budget, hp.gamma, run)
            # 2. One policy-gradient step.
            with run.timing.update:
                run.record(update(policy, optimizer, batch, hp))
            run.record({"batch/steps": steps, **std_log})
            # 3. Log, evaluate and checkpoint when due (between iterations: no episode in flight).
            run.end_iteration(steps)
    finally:
        envs.close()
