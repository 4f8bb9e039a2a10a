"""DDPG: deep deterministic policy gradient (Lillicrap et al. 2016), done right.

One critic Q(s, a) regressed on y = r + gamma * (1 - terminated) * Q'(s', mu'(s')); a deterministic
actor mu(s) ascending Q(s, mu(s)) (Silver et al. 2014's deterministic policy gradient); target
networks mu', Q' that trail by Polyak averaging; exploration noise (Ornstein-Uhlenbeck as in the
paper, or Gaussian) with a linear schedule. ``docs/ddpg_pitfalls.md`` lists the bugs that
keep a DDPG implementation from learning (learning rates 50x too large, BatchNorm and dropout in
the networks, time limits stored as terminal states, ...) and how this file avoids each.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.config import TrainConfig
from drivelab.training.collection.exploration import NoisyExploration
from drivelab.training.collection.replay import ReplayCollector
from drivelab.training.learning.hyperparams import NoisyExplorationParams
from drivelab.training.learning.losses import deterministic_actor_loss, saturated_share
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, frozen, make_target, polyak_update
from drivelab.training.learning.optim import Optimizers, gradient_step, make_optimizers
from drivelab.training.learning.precision import update_precision
from drivelab.training.learning.replay_buffer import ReplayBatch
from drivelab.training.run import Run


@dataclass
class Params(NoisyExplorationParams):
    actor_lr: float = 1e-4            # the paper: 1e-4 actor, 1e-3 critic
    critic_lr: float = 1e-3           # critic (and image encoder) learning rate (Adam)
    noise: str = "ou"
    noise_std: float = 0.2
    noise_std_final: float = 0.05
    noise_decay_steps: int = 50_000


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=False, critics=1,
                          critic_layer_norm=hp.critic_layer_norm)


def ddpg_target(rewards: torch.Tensor, terminated: torch.Tensor, next_q: torch.Tensor,
                discount: torch.Tensor | float) -> torch.Tensor:
    """y = r + discount * (1 - terminated) * Q'(s', mu'(s')); next_q (1, B), the rest (B,);
    ``discount`` gamma, or gamma^m per row for n-step returns. Truncated steps bootstrap: a time
    limit is not a terminal state."""
    return rewards + discount * (1.0 - terminated) * next_q[0]


def update(agent: OffPolicyAgent, target: OffPolicyAgent, opt: Optimizers, batch: ReplayBatch,
           hp: Params) -> dict[str, torch.Tensor]:
    """One critic step and one actor step on B transitions, then Polyak averaging of the targets."""
    with torch.no_grad():
        next_features = target.features(batch.next_obs)
        y = ddpg_target(batch.rewards, batch.terminated, target.critic(next_features, target.actor(next_features)), batch.discount)
    features = agent.features(batch.obs)
    q = agent.critic(features, batch.actions)           # (1, B)
    loss_q = (q - y).pow(2).mean()
    gradient_step(opt.critic, loss_q)
    detached = features.detach()
    pre_tanh = agent.actor.pre_tanh(detached)
    with frozen(agent.critic):   # dQ/da only: no weight gradients for the critic in the actor's step
        loss_pi = deterministic_actor_loss(agent.critic(detached, torch.tanh(pre_tanh))[0], pre_tanh, hp.pre_tanh_l2)
        gradient_step(opt.actor, loss_pi)
    polyak_update(target, agent, hp.tau)
    return {"loss/critic": loss_q.detach(), "loss/actor": loss_pi.detach(), "charts/q": q.mean().detach(),
            "charts/actor_saturation": saturated_share(pre_tanh)}


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = ReplayCollector.from_config(cfg, run, build_policy, exploration=NoisyExploration)
    explore = NoisyExploration(hp, collector.num_envs, collector.act_space.shape[0], seed=cfg.seed)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    target = make_target(agent)
    opt = make_optimizers(agent, hp)
    if hp.compile:
        agent.compile_networks()
    collector.start(run.start({"policy": agent, "target": target}, opt._asdict(), policy=agent), exploration=explore)
    try:
        while not run.done:
            # 1. Act: uniform random during the heat-up, then mu(s) + exploration noise (the OU
            #    process restarts with each episode); with act_in_workers the env workers play a
            #    chunk with a copy of the actor while 2. runs.
            steps = collector.collect(agent)
            # 2. utd gradient steps per env step stored.
            for batch in collector.batches():
                with run.timing.update, update_precision(hp, run.device):
                    run.record(update(agent, target, opt, batch, hp))
            run.end_iteration(steps, extra_state=collector.state)
    finally:
        collector.close()
