"""TD3: twin delayed deep deterministic policy gradient (Fujimoto et al. 2018).

DDPG plus three fixes for its overestimation and instability:

1. clipped double-Q: the target takes the minimum of twin critics,
       y = r + gamma * (1 - terminated) * min_e Q'_e(s', a'),
2. target policy smoothing: a' = clip(mu'(s') + clip(N(0, policy_noise), -noise_clip, noise_clip), -1, 1),
3. delayed policy updates: the actor and the targets move once every ``policy_delay`` critic updates.

Exploration adds Gaussian (or Ornstein-Uhlenbeck) noise to mu(s), with a linear schedule
(:class:`drivelab.training.offpolicy.NoisyExploration`). The replay collector, networks and run services
are the shared parts (:mod:`drivelab.training.offpolicy`, :mod:`drivelab.training.nets`, :mod:`drivelab.training.run`).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.training.buffers import ReplayBatch
from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.losses import deterministic_actor_loss, gradient_step, saturated_share
from drivelab.training.nets import OffPolicyAgent, frozen, make_target, polyak_update
from drivelab.training.offpolicy import (NoisyExploration, NoisyExplorationParams, Optimizers, ReplayCollector,
                                        make_optimizers)
from drivelab.training.run import Run


@dataclass
class Params(NoisyExplorationParams):
    policy_delay: int = 2
    policy_noise: float = 0.2         # target smoothing noise std (policy units)
    noise_clip: float = 0.5

    def validate(self) -> None:
        super().validate()
        if self.policy_delay < 1:
            raise DrivelabError(f"config field 'td3.policy_delay' must be >= 1, got {self.policy_delay}")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=False, critics=2,
                          critic_layer_norm=hp.critic_layer_norm)


def td_target(rewards: torch.Tensor, terminated: torch.Tensor, next_q: torch.Tensor,
              discount: torch.Tensor | float) -> torch.Tensor:
    """y = r + discount * (1 - terminated) * min_e Q'_e(s', a'); next_q (E, B), the rest (B,).
    ``discount`` is gamma, or gamma^m per row for n-step returns (r then sums m rewards).
    With one critic (E = 1) this is DDPG's target."""
    return rewards + discount * (1.0 - terminated) * next_q.min(dim=0).values


def smoothed_target_action(target_action: torch.Tensor, policy_noise: float, noise_clip: float) -> torch.Tensor:
    """Target policy smoothing: mu'(s') plus clipped Gaussian noise, kept in [-1, 1]. (B, A)."""
    noise = (torch.randn_like(target_action) * policy_noise).clamp(-noise_clip, noise_clip)
    return (target_action + noise).clamp(-1.0, 1.0)


def update(agent: OffPolicyAgent, target: OffPolicyAgent, opt: Optimizers, batch: ReplayBatch, hp: Params,
           update_actor: bool) -> dict[str, torch.Tensor]:
    """One critic step on B transitions; when ``update_actor`` (every ``policy_delay``-th call)
    also one actor step on Q_1 and Polyak averaging of the targets. Returns the logged values."""
    with torch.no_grad():
        next_features = target.features(batch.next_obs)
        next_action = smoothed_target_action(target.actor(next_features), hp.policy_noise, hp.noise_clip)
        y = td_target(batch.rewards, batch.terminated, target.critic(next_features, next_action), batch.discount)
    features = agent.features(batch.obs)
    q = agent.critic(features, batch.actions)                   # (2, B)
    loss_q = (q - y).pow(2).mean(dim=1).sum()
    gradient_step(opt.critic, loss_q)
    logged = {"loss/critic": loss_q.detach(), "charts/q": q.mean().detach()}
    if update_actor:
        detached = features.detach()
        pre_tanh = agent.actor.pre_tanh(detached)
        with frozen(agent.critic):
            q_pi = agent.critic(detached, torch.tanh(pre_tanh), members=1)[0]   # ascend Q_1 (the paper's choice)
            loss_pi = deterministic_actor_loss(q_pi, pre_tanh, hp.pre_tanh_l2)
            gradient_step(opt.actor, loss_pi)
        polyak_update(target, agent, hp.tau)
        logged["loss/actor"] = loss_pi.detach()
        logged["charts/actor_saturation"] = saturated_share(pre_tanh)
    return logged


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = ReplayCollector.from_config(cfg, run, build_policy, exploration=NoisyExploration)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    target = make_target(agent)
    opt = make_optimizers(agent, hp)
    if hp.compile:
        agent.compile_networks()
    explore = NoisyExploration(hp, collector.num_envs, collector.act_space.shape[0], seed=cfg.seed)
    collector.start(run.start({"policy": agent, "target": target}, opt._asdict(), policy=agent), exploration=explore)
    try:
        while not run.done:
            # 1. Act: uniform random during the heat-up, then mu(s) + exploration noise. In this
            #    process one vector step; with act_in_workers the env workers play a chunk with
            #    a copy of the actor while 2. runs (ReplayCollector).
            steps = collector.collect(agent)
            # 2. Critic steps at the update-to-data ratio; the actor every policy_delay-th.
            for batch in collector.batches():
                with run.timing.update:
                    run.record(update(agent, target, opt, batch, hp, update_actor=collector.updates % hp.policy_delay == 0))
            # 3. Log, evaluate and checkpoint (with the replay buffer) when due.
            run.end_iteration(steps, extra_state=collector.state)
    finally:
        collector.close()
