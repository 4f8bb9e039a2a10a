"""DDPG: deep deterministic policy gradient (Lillicrap et al. 2016), done right.

One critic Q(s, a) regressed on y = r + gamma * (1 - terminated) * Q'(s', mu'(s')); a deterministic
actor mu(s) ascending Q(s, mu(s)) (Silver et al. 2014's deterministic policy gradient); target
networks mu', Q' that trail by Polyak averaging; exploration noise (Ornstein-Uhlenbeck as in the
paper, or Gaussian) with a linear schedule. ``docs/ddpg_notebook_bugs.md`` lists what keeps
notebook 004's DDPG from learning, and how this file avoids each bug.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.algos.td3 import exploration, td_target
from drivelab.buffers import ReplayBatch
from drivelab.config import TrainConfig
from drivelab.envs import env_spaces
from drivelab.errors import DrivelabError
from drivelab.offpolicy import (OffPolicyAgent, OffPolicyParams, StatAccumulator, make_optimizers, make_target,
                                polyak_update, train_off_policy)
from drivelab.run import Run


@dataclass
class Params(OffPolicyParams):
    actor_lr: float = 1e-4            # the paper: 1e-4 actor, 1e-3 critic
    critic_lr: float = 1e-3
    noise: str = "ou"                 # exploration noise: ou | gaussian
    noise_std: float = 0.2
    noise_std_final: float = 0.05
    noise_decay_steps: int = 50_000

    def validate(self) -> None:
        super().validate()
        if self.noise not in ("gaussian", "ou"):
            raise DrivelabError(f"config field 'ddpg.noise' must be gaussian or ou, got {self.noise!r}")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=False, critics=1)


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    obs_space, act_space = env_spaces(cfg.env)
    agent = build_policy(cfg, obs_space, act_space).to(run.device)
    target = make_target(agent)
    optimizers = make_optimizers(agent, hp)
    critic_opt, actor_opt = optimizers["critic"], optimizers["actor"]
    stats = StatAccumulator("loss/critic", "loss/actor", "charts/q")

    def update(batch: ReplayBatch) -> None:
        with torch.no_grad():
            next_features = target.features(batch.next_obs)
            y = td_target(batch.rewards, batch.terminated, target.critic(next_features, target.actor(next_features)), hp.gamma)
        features = agent.features(batch.obs)
        q = agent.critic(features, batch.actions)           # (1, B)
        loss_q = (q - y).pow(2).mean()
        critic_opt.zero_grad()
        loss_q.backward()
        critic_opt.step()
        detached = features.detach()
        loss_pi = -agent.critic(detached, agent.actor(detached)).mean()
        actor_opt.zero_grad()
        loss_pi.backward()
        actor_opt.step()
        polyak_update(target, agent, hp.tau)
        stats.add(loss_q, loss_pi, q.mean())

    explore, reset_noise = exploration(agent, hp, cfg.env.num_envs, act_space.shape[0], cfg.seed)
    train_off_policy(cfg, run, agent, modules={"policy": agent, "target": target},
                     optimizers=optimizers,
                     explore=explore, update=update, end_episodes=reset_noise, flush_stats=stats.flush)
