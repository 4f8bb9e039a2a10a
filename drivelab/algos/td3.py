"""TD3: twin delayed deep deterministic policy gradient (Fujimoto et al. 2018).

DDPG plus three fixes for its overestimation and instability:

1. clipped double-Q: the target takes the minimum of twin critics,
       y = r + gamma * (1 - terminated) * min_e Q'_e(s', a'),
2. target policy smoothing: a' = clip(mu'(s') + clip(N(0, policy_noise), -noise_clip, noise_clip), -1, 1),
3. delayed policy updates: the actor and the targets move once every ``policy_delay`` critic updates.

With ``crossq`` (Bhatt et al. 2024, "CrossQ") there are no target networks: the critics batch-normalise
the input of every layer, and one train-mode pass takes (s, a) and (s', mu(s') + smoothing noise)
together, so both halves are normalised with the statistics of their mixture; Q(s', a') of that
pass, detached, bootstraps y. The actor's step reads the critics in eval mode (running statistics).
The paper's wider critics and Batch Renormalization are left out (batch norm with a learned gain
and bias, momentum 0.01). Keep ``pre_tanh_l2`` > 0 with it: on Pendulum the actor otherwise
saturates at the bounds within 1,000 updates (docs/history.md, "What each lever did in 30 minutes").

Exploration adds Gaussian (or Ornstein-Uhlenbeck) noise to mu(s), with a linear schedule
(:class:`drivelab.training.collection.exploration.NoisyExploration`). The replay collector, networks and run services
are the shared parts (:mod:`drivelab.training.collection.replay`, :mod:`drivelab.training.learning.offpolicy_nets`, :mod:`drivelab.training.run`).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
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
    policy_delay: int = 2
    policy_noise: float = 0.2         # target smoothing noise std (policy units)
    noise_clip: float = 0.5
    crossq: bool = False              # batch-normalised critics, no target networks (module docstring)

    def validate(self) -> None:
        super().validate()
        if self.policy_delay < 1:
            raise DrivelabError(f"config field 'td3.policy_delay' must be >= 1, got {self.policy_delay}")
        if self.crossq and self.bf16_updates:
            raise DrivelabError("config fields 'td3.crossq' and 'td3.bf16_updates' exclude each other: "
                                "batch norm's statistics need float32")
        if self.crossq and self.critic_layer_norm:
            raise DrivelabError("config fields 'td3.crossq' and 'td3.critic_layer_norm' exclude each other: "
                                "CrossQ normalises the critics with batch norm")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=False, critics=2,
                          critic_layer_norm=hp.critic_layer_norm, critic_batch_norm=hp.crossq)


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


def q_and_target(agent: OffPolicyAgent, target: OffPolicyAgent, batch: ReplayBatch,
                 hp: Params) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Features of s (B, F), Q_e(s, a) (2, B) and the TD target y (B,) from the target networks."""
    with torch.no_grad():
        next_features = target.features(batch.next_obs)
        next_action = smoothed_target_action(target.actor(next_features), hp.policy_noise, hp.noise_clip)
        y = td_target(batch.rewards, batch.terminated, target.critic(next_features, next_action), batch.discount)
    features = agent.features(batch.obs)
    return features, agent.critic(features, batch.actions), y


def crossq_q_and_target(agent: OffPolicyAgent, batch: ReplayBatch,
                        hp: Params) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """As :func:`q_and_target`, without target networks (CrossQ): one pass of the batch-normalised
    critics over [(s, a); (s', a')], (2, 2B), so that both halves share the normalisation."""
    size = batch.actions.shape[0]
    features = agent.features(torch.cat([batch.obs, batch.next_obs]))   # (2B, F)
    with torch.no_grad():
        next_action = smoothed_target_action(agent.actor(features[size:]), hp.policy_noise, hp.noise_clip)
    q_both = agent.critic(features, torch.cat([batch.actions, next_action]))
    y = td_target(batch.rewards, batch.terminated, q_both[:, size:].detach(), batch.discount)
    return features[:size], q_both[:, :size], y


def update(agent: OffPolicyAgent, target: OffPolicyAgent | None, opt: Optimizers, batch: ReplayBatch, hp: Params,
           update_actor: bool) -> dict[str, torch.Tensor]:
    """One critic step on B transitions; when ``update_actor`` (every ``policy_delay``-th call)
    also one actor step on Q_1 and Polyak averaging of the targets (``target`` None: CrossQ, none).
    Returns the logged values."""
    agent.critic.train()   # batch norm (CrossQ) uses this batch's statistics; other critics ignore the mode
    if target is None:
        features, q, y = crossq_q_and_target(agent, batch, hp)
    else:
        features, q, y = q_and_target(agent, target, batch, hp)
    loss_q = (q - y).pow(2).mean(dim=1).sum()
    gradient_step(opt.critic, loss_q)
    logged = {"loss/critic": loss_q.detach(), "charts/q": q.mean().detach()}
    if update_actor:
        detached = features.detach()
        pre_tanh = agent.actor.pre_tanh(detached)
        agent.critic.eval()   # the running statistics: the actor's batch must not move them
        with frozen(agent.critic):
            q_pi = agent.critic(detached, torch.tanh(pre_tanh), members=1)[0]   # ascend Q_1 (the paper's choice)
            loss_pi = deterministic_actor_loss(q_pi, pre_tanh, hp.pre_tanh_l2)
            gradient_step(opt.actor, loss_pi)
        agent.critic.train()
        if target is not None:
            polyak_update(target, agent, hp.tau)
        logged["loss/actor"] = loss_pi.detach()
        logged["charts/actor_saturation"] = saturated_share(pre_tanh)
    return logged


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = ReplayCollector.from_config(cfg, run, build_policy, exploration=NoisyExploration)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    target = None if hp.crossq else make_target(agent)
    opt = make_optimizers(agent, hp)
    if hp.compile:
        agent.compile_networks()
    explore = NoisyExploration(hp, collector.num_envs, collector.act_space.shape[0], seed=cfg.seed)
    checkpointed = {"policy": agent} if target is None else {"policy": agent, "target": target}
    collector.start(run.start(checkpointed, opt._asdict(), policy=agent), exploration=explore)
    try:
        while not run.done:
            # 1. Act: uniform random during the heat-up, then mu(s) + exploration noise. In this
            #    process one vector step; with act_in_workers the env workers play a chunk with
            #    a copy of the actor while 2. runs (ReplayCollector).
            steps = collector.collect(agent)
            # 2. Critic steps at the update-to-data ratio; the actor every policy_delay-th.
            for batch in collector.batches():
                with run.timing.update, update_precision(hp, run.device):
                    update_actor = collector.updates % hp.policy_delay == 0
                    run.record(update(agent, target, opt, batch, hp, update_actor=update_actor))
            # 3. Log, evaluate and checkpoint (with the replay buffer) when due.
            run.end_iteration(steps, extra_state=collector.state)
    finally:
        collector.close()
