"""TD3: twin delayed deep deterministic policy gradient (Fujimoto et al. 2018).

DDPG plus three fixes for its overestimation and instability:

1. clipped double-Q: the target takes the minimum of twin critics,
       y = r + gamma * (1 - terminated) * min_e Q'_e(s', a'),
2. target policy smoothing: a' = clip(mu'(s') + clip(N(0, policy_noise), -noise_clip, noise_clip), -1, 1),
3. delayed policy updates: the actor and the targets move once every ``policy_delay`` critic updates.

Exploration adds Gaussian (or Ornstein-Uhlenbeck) noise to mu(s), with a linear schedule.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from drivelab.buffers import ReplayBatch
from drivelab.config import TrainConfig
from drivelab.envs import env_spaces
from drivelab.errors import DrivelabError
from drivelab.offpolicy import (OffPolicyAgent, OffPolicyParams, StatAccumulator, linear_schedule, make_noise,
                                make_optimizers, make_target, polyak_update, train_off_policy)
from drivelab.run import Run


@dataclass
class Params(OffPolicyParams):
    policy_delay: int = 2
    policy_noise: float = 0.2         # target smoothing noise std (policy units)
    noise_clip: float = 0.5
    noise: str = "gaussian"           # exploration noise: gaussian | ou
    noise_std: float = 0.1            # exploration noise std at the start ...
    noise_std_final: float = 0.1      # ... and after noise_decay_steps
    noise_decay_steps: int = 0

    def validate(self) -> None:
        super().validate()
        if self.noise not in ("gaussian", "ou"):
            raise DrivelabError(f"config field 'td3.noise' must be gaussian or ou, got {self.noise!r}")
        if self.policy_delay < 1:
            raise DrivelabError(f"config field 'td3.policy_delay' must be >= 1, got {self.policy_delay}")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=False, critics=2)


def td_target(rewards: torch.Tensor, terminated: torch.Tensor, next_q: torch.Tensor, gamma: float) -> torch.Tensor:
    """y = r + gamma * (1 - terminated) * min_e Q'_e(s', a'); next_q (E, B), the rest (B,)."""
    return rewards + gamma * (1.0 - terminated) * next_q.min(dim=0).values


def smoothed_target_action(target_action: torch.Tensor, policy_noise: float, noise_clip: float) -> torch.Tensor:
    """Target policy smoothing: mu'(s') plus clipped Gaussian noise, kept in [-1, 1]."""
    noise = (torch.randn_like(target_action) * policy_noise).clamp(-noise_clip, noise_clip)
    return (target_action + noise).clamp(-1.0, 1.0)


def exploration(agent: OffPolicyAgent, hp, num_envs: int, act_dim: int, seed: int):
    """explore(obs, step) = clip(mu(s) + noise, -1, 1) and the per-env noise reset, for DDPG/TD3."""
    noise = make_noise(hp.noise, num_envs, act_dim, np.random.default_rng([seed, 2]))

    def explore(obs: torch.Tensor, step: int) -> np.ndarray:
        std = linear_schedule(hp.noise_std, hp.noise_std_final, hp.noise_decay_steps, step - hp.learning_starts)
        return np.clip(agent.act(obs, deterministic=True).cpu().numpy() + noise.sample(std), -1.0, 1.0)

    return explore, noise.reset


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    obs_space, act_space = env_spaces(cfg.env)
    agent = build_policy(cfg, obs_space, act_space).to(run.device)
    target = make_target(agent)
    optimizers = make_optimizers(agent, hp)
    critic_opt, actor_opt = optimizers["critic"], optimizers["actor"]
    stats = StatAccumulator("loss/critic", "loss/actor", "charts/q")
    updates = 0

    def update(batch: ReplayBatch) -> None:
        nonlocal updates
        with torch.no_grad():
            next_features = target.features(batch.next_obs)
            next_action = smoothed_target_action(target.actor(next_features), hp.policy_noise, hp.noise_clip)
            y = td_target(batch.rewards, batch.terminated, target.critic(next_features, next_action), hp.gamma)
        features = agent.features(batch.obs)
        q = agent.critic(features, batch.actions)
        loss_q = (q - y).pow(2).mean(dim=1).sum()
        critic_opt.zero_grad()
        loss_q.backward()
        critic_opt.step()
        updates += 1
        if updates % hp.policy_delay == 0:
            detached = features.detach()
            loss_pi = -agent.critic(detached, agent.actor(detached))[0].mean()  # ascend Q_1 (the paper's choice)
            actor_opt.zero_grad()
            loss_pi.backward()
            actor_opt.step()
            polyak_update(target, agent, hp.tau)
            stats.add(loss_q, loss_pi, q.mean())

    explore, reset_noise = exploration(agent, hp, cfg.env.num_envs, act_space.shape[0], cfg.seed)
    train_off_policy(cfg, run, agent, modules={"policy": agent, "target": target},
                     optimizers=optimizers,
                     explore=explore, update=update, end_episodes=reset_noise, flush_stats=stats.flush)
