"""SAC: soft actor-critic with automatic entropy tuning (Haarnoja et al. 2018a, 2018b).

Maximises return plus entropy, E[sum_t r_t + alpha * H(pi(.|s_t))], with

* a squashed Gaussian actor a = tanh(u), whose log-probability carries the tanh
  change-of-variables correction (:func:`drivelab.training.learning.offpolicy_nets.squashed_gaussian_log_prob`);
* twin critics and a clipped double-Q target (Fujimoto et al. 2018), computed in one batched pass:
      y = r + gamma * (1 - terminated) * (min_e Q'_e(s', a') - alpha * log pi(a'|s')),  a' ~ pi(.|s');
* the actor loss E[alpha * log pi(a|s) - min_e Q_e(s, a)] with a reparameterised a ~ pi(.|s);
* alpha tuned so the policy's entropy tracks a target (-|A| by default):
      L(alpha) = -E[log alpha * (log pi(a|s) + target_entropy)];
* optionally (``actor_every``) the actor and alpha on every N-th critic step only, and
  (``average_policy``) an exponential average of the weights as the policy that is evaluated.

Shared parts used here: :class:`drivelab.training.collection.replay.ReplayCollector` (env stepping into the
replay buffer, update-to-data ratio), the networks in :mod:`drivelab.training.learning.offpolicy_nets`, and
:class:`drivelab.training.run.Run` (logging, evaluation, checkpoints).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import gymnasium as gym
import torch

from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.collection.exploration import PolicySampling
from drivelab.training.collection.replay import ReplayCollector
from drivelab.training.learning.hyperparams import OffPolicyParams
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, frozen, make_target, polyak_update
from drivelab.training.learning.optim import fused_adam, gradient_step, make_optimizers
from drivelab.training.learning.precision import update_precision
from drivelab.training.learning.replay_buffer import ReplayBatch
from drivelab.training.run import Run


@dataclass
class Params(OffPolicyParams):
    alpha_lr: float = 3e-4            # learning rate of log(alpha)
    # Start well below 1 when rewards per step are small (MetaDrive: ~0.1-1): with alpha = 1 the
    # entropy bonus outweighs the reward, the policy stays near uniform while log(alpha) falls by
    # ~alpha_lr per update, and by the time the policy reacts to rewards alpha is ~0.001 and too
    # slow to come back; exploration is gone. The MetaDrive configs start at 0.05 for this reason
    # (docs/results.md compares the two starts).
    init_alpha: float = 1.0
    autotune: bool = True             # tune alpha toward target_entropy (else fixed at init_alpha)
    target_entropy: float | None = None   # None: -|A|
    actor_every: int = 1                  # actor and alpha update once every N critic updates
    # > 0: evaluation, checkpoints and the exported policy use a running (exponential) average of
    # the agent's weights, moved by this fraction toward them at every actor step; the env workers
    # keep acting with the agent itself. Weight averaging steadies the policy that is evaluated
    # (Nikishin et al. 2018 average uniformly over a window; this is the exponential form).
    average_policy: float = 0.0

    def validate(self) -> None:
        super().validate()
        if self.actor_every < 1:
            raise DrivelabError(f"config field 'actor_every' must be >= 1, got {self.actor_every}")
        if not 0.0 <= self.average_policy < 1.0:
            raise DrivelabError(f"config field 'average_policy' must be in [0, 1), got {self.average_policy}")


class Optimizers(NamedTuple):
    critic: torch.optim.Optimizer         # critics and the (image) encoder
    actor: torch.optim.Optimizer
    alpha: torch.optim.Optimizer          # log(alpha)


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=True, critics=2,
                          critic_layer_norm=hp.critic_layer_norm)


def build_optimizers(agent: OffPolicyAgent, log_alpha: torch.Tensor, hp: Params) -> Optimizers:
    """Adam for the critics (with the encoder) and the actor (:func:`make_optimizers`), and for log(alpha)."""
    return Optimizers(**make_optimizers(agent, hp)._asdict(), alpha=fused_adam([log_alpha], lr=hp.alpha_lr))


def critic_loss(q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Sum over critics of the mean squared TD error: q (E, B), target (B,)."""
    return (q - target).pow(2).mean(dim=1).sum()


def soft_td_target(rewards: torch.Tensor, terminated: torch.Tensor, next_q: torch.Tensor, next_log_prob: torch.Tensor,
                   alpha: torch.Tensor, discount: torch.Tensor | float) -> torch.Tensor:
    """y = r + discount * (1 - terminated) * (min_e Q'_e(s', a') - alpha * log pi(a'|s')).
    rewards, terminated, next_log_prob (B,); next_q (E, B); ``discount`` gamma, or gamma^m per row
    for n-step returns. Truncated steps do bootstrap."""
    return rewards + discount * (1.0 - terminated) * (next_q.min(dim=0).values - alpha * next_log_prob)


def actor_loss(log_prob: torch.Tensor, q_pi: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """E[alpha * log pi(a|s) - min_e Q_e(s, a)], a ~ pi(.|s) reparameterised; shapes (B,)."""
    return (alpha * log_prob - q_pi).mean()


def alpha_loss(log_alpha: torch.Tensor, log_prob: torch.Tensor, target_entropy: float) -> torch.Tensor:
    """-E[log alpha * (log pi(a|s) + target_entropy)]: alpha rises while the entropy -log pi is
    below its target and falls while it is above."""
    return -(log_alpha * (log_prob.detach() + target_entropy)).mean()


def update(agent: OffPolicyAgent, target: OffPolicyAgent, log_alpha: torch.Tensor, opt: Optimizers,
           batch: ReplayBatch, hp: Params, target_entropy: float, update_actor: bool = True) -> dict[str, torch.Tensor]:
    """One critic step on a batch of B transitions, then (when ``update_actor``) one actor and one
    temperature step, then Polyak averaging of the target. Returns the logged values (0-d)."""
    alpha = log_alpha.exp().detach()
    with torch.no_grad():
        next_action, next_log_prob = agent.actor(agent.features(batch.next_obs))
        next_q = target.critic(target.features(batch.next_obs), next_action)
        y = soft_td_target(batch.rewards, batch.terminated, next_q, next_log_prob, alpha, batch.discount)
    features = agent.features(batch.obs)
    q = agent.critic(features, batch.actions)                   # (2, B)
    loss_q = critic_loss(q, y)
    gradient_step(opt.critic, loss_q)
    logged = {"loss/critic": loss_q.detach(), "charts/q": q.mean().detach()}

    if update_actor:
        detached = features.detach()  # the actor does not train the (image) encoder
        action, log_prob = agent.actor(detached)
        with frozen(agent.critic):   # dQ/da only: no weight gradients for the critics in the actor's step
            loss_pi = actor_loss(log_prob, agent.critic(detached, action).min(dim=0).values, alpha)
            gradient_step(opt.actor, loss_pi)
        loss_alpha = alpha_loss(log_alpha, log_prob, target_entropy)
        if hp.autotune:
            gradient_step(opt.alpha, loss_alpha)
        logged.update({"loss/actor": loss_pi.detach(), "loss/alpha": loss_alpha.detach(), "charts/alpha": alpha,
                       "charts/entropy": -log_prob.mean().detach()})
    polyak_update(target, agent, hp.tau)
    return logged


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = ReplayCollector.from_config(cfg, run, build_policy, exploration=PolicySampling)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    log_alpha = torch.nn.Parameter(torch.tensor(float(hp.init_alpha)).log().to(run.device))
    target_entropy = hp.target_entropy if hp.target_entropy is not None else -float(collector.act_space.shape[0])
    # Target networks: a Polyak-averaged copy of the agent (its encoder too, so y does not move
    # with the online critic's features). Only its encoder and critics are used.
    target = make_target(agent)
    # With average_policy the checkpoints' "policy" (what evaluation, drivelab eval and export
    # load) is the averaged copy and the agent that learns is saved as "learner".
    averaged = make_target(agent) if hp.average_policy > 0 else None
    opt = build_optimizers(agent, log_alpha, hp)
    if hp.compile:
        agent.compile_networks()
    modules = {"policy": agent, "target": target, "alpha": torch.nn.ParameterDict({"log_alpha": log_alpha})}
    if averaged is not None:
        modules.update(policy=averaged, learner=agent)
    resumed = run.start(modules, opt._asdict(), policy=modules["policy"])
    collector.start(resumed, exploration=PolicySampling(hp, collector.num_envs, collector.act_space.shape[0], cfg.seed))
    try:
        while not run.done:
            # 1. Act: uniform random during the heat-up, then a sample of the stochastic policy
            #    (SAC explores with its own entropy-regularised policy, no added noise). With
            #    act_in_workers the env workers play a chunk with a copy of the actor while 2. runs.
            steps = collector.collect(agent)
            # 2. utd gradient steps per env step on uniform replay batches.
            for batch in collector.batches():
                update_actor = (collector.updates - 1) % hp.actor_every == 0
                with run.timing.update, update_precision(hp, run.device):
                    run.record(update(agent, target, log_alpha, opt, batch, hp, target_entropy, update_actor))
                    if averaged is not None and update_actor:
                        polyak_update(averaged, agent, hp.average_policy)
            # 3. Log, evaluate and checkpoint (with the replay buffer) when due.
            run.end_iteration(steps, extra_state=collector.state)
    finally:
        collector.close()
