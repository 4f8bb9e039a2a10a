"""SAC-Lagrangian: SAC that keeps the mean episode cost at or below a limit d (Ha et al. 2020,
"Learning to Walk in the Real World with Minimal Human Effort"; OmniSafe's SACLag), with the
multiplier driven by the measured episode cost (Ray, Achiam & Amodei 2019; Stooke et al. 2020).

The constrained problem max_pi J_r(pi) s.t. J_c(pi) <= d becomes the saddle point
min_{lambda >= 0} max_pi J_r(pi) - lambda (J_c(pi) - d). On top of :mod:`drivelab.algos.sac`:

* a cost critic Q_c(s, a) (the discounted cost to come) with its Polyak target, trained on
      y_c = c + gamma_c^m * (1 - terminated) * Q_c'(s', a'),
  with a' the same next action as SAC's target and **no entropy term** (the entropy bonus is a
  reward, not a cost); c is the m-step cost sum of the replay buffer;
* the actor loss E[alpha * log pi(a|s) - min_e Q_e(s, a) + lambda * Q_c(s, a)];
* lambda (:class:`~drivelab.training.learning.lagrange.LagrangeMultiplier`) moved every
  ``lagrange_every`` env steps from J_c, the mean cost of the training episodes that finished
  since its last move (gradient ascent, or ``lagrange: pid``). Its state is checkpointed with the
  networks, so a resumed run continues exactly.

The env must report a cost per step (``info["cost"]``: SafeMetaDrive does, any env does with
``env.cost`` terms). ``cost_limit`` is in the units evaluation counts: the undiscounted sum of the
env's per-step costs over an episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.algos import sac
from drivelab.algos.sac import Optimizers, alpha_loss, critic_loss, soft_td_target
from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.collection.exploration import PolicySampling
from drivelab.training.collection.replay import ReplayCollector
from drivelab.training.learning.hyperparams import ConstraintParams
from drivelab.training.learning.lagrange import LagrangeMultiplier
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, frozen, make_target, polyak_update
from drivelab.training.learning.optim import fused_adam, gradient_step
from drivelab.training.learning.precision import update_precision
from drivelab.training.learning.replay_buffer import ReplayBatch
from drivelab.training.run import Run


@dataclass
class Params(sac.Params, ConstraintParams):
    # env steps between two moves of lambda: enough finished episodes for J_c to be a fair mean
    # (the drive recipe's 10k steps hold some 20-50 MetaDrive episodes)
    lagrange_every: int = 10_000

    def validate(self) -> None:
        super().validate()
        self.validate_constraint("sac_lag")
        if isinstance(self.lagrange_every, bool) or not isinstance(self.lagrange_every, int) or self.lagrange_every < 1:
            raise DrivelabError(f"config field 'sac_lag.lagrange_every' must be an integer >= 1, got {self.lagrange_every!r}")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=True, critics=2,
                          critic_layer_norm=hp.critic_layer_norm, cost_critics=1)


def build_optimizers(agent: OffPolicyAgent, log_alpha: torch.Tensor, hp: Params) -> Optimizers:
    """SAC's three Adams; the critics' one also steps the cost critic. Its loss is added to the
    reward critics' (they share no parameters, so each gets its own gradient, and Adam scales each
    parameter on its own): one backward pass and one fused step for both."""
    critics = [*agent.encoder.parameters(), *agent.critic.parameters(), *agent.cost_critic.parameters()]
    return Optimizers(critic=fused_adam(critics, lr=hp.critic_lr), actor=fused_adam(agent.actor.parameters(), lr=hp.actor_lr),
                      alpha=fused_adam([log_alpha], lr=hp.alpha_lr))


def cost_td_target(costs: torch.Tensor, terminated: torch.Tensor, next_qc: torch.Tensor,
                   discount: torch.Tensor | float) -> torch.Tensor:
    """y_c = c + discount * (1 - terminated) * Q_c'(s', a'): costs, terminated, next_qc (B,);
    ``discount`` gamma_c^m per row. No entropy term: the entropy bonus belongs to the reward."""
    return costs + discount * (1.0 - terminated) * next_qc


def lagrangian_actor_loss(log_prob: torch.Tensor, q_pi: torch.Tensor, qc_pi: torch.Tensor, alpha: torch.Tensor,
                          lam: float) -> torch.Tensor:
    """E[alpha * log pi(a|s) - min_e Q_e(s, a) + lambda * Q_c(s, a)], a ~ pi(.|s); shapes (B,).

    Not divided by (1 + lambda), unlike PPO-Lagrangian's advantage: alpha weighs the entropy against
    Q in reward units, and its tuning toward the target entropy assumes that scale. Dividing the
    Q terms alone would make the same alpha weigh the entropy more as lambda grows; dividing the
    whole loss changes nothing under Adam, which is invariant to the scale of the loss."""
    return (alpha * log_prob - q_pi + lam * qc_pi).mean()


def update(agent: OffPolicyAgent, target: OffPolicyAgent, log_alpha: torch.Tensor, opt: Optimizers,
           batch: ReplayBatch, hp: Params, target_entropy: float, lam: float,
           update_actor: bool = True) -> dict[str, torch.Tensor]:
    """One step of the critics and the cost critic on a batch of B transitions, then (when
    ``update_actor``) one actor step on the Lagrangian with multiplier ``lam`` and one temperature
    step, then Polyak averaging of the target. Returns the logged values (0-d)."""
    alpha = log_alpha.exp().detach()
    with torch.no_grad():
        next_action, next_log_prob = agent.actor(agent.features(batch.next_obs))   # a' ~ pi(.|s'), shared
        next_features = target.features(batch.next_obs)
        y = soft_td_target(batch.rewards, batch.terminated, target.critic(next_features, next_action), next_log_prob,
                           alpha, batch.discount)
        y_c = cost_td_target(batch.costs, batch.terminated, target.cost_critic(next_features, next_action)[0],
                             batch.cost_discount)
    features = agent.features(batch.obs)
    q = agent.critic(features, batch.actions)                          # (2, B)
    qc = agent.cost_critic(features.detach(), batch.actions)           # (1, B): the encoder is the critics'
    loss_q, loss_qc = critic_loss(q, y), critic_loss(qc, y_c)
    gradient_step(opt.critic, loss_q + loss_qc)   # disjoint parameters: each critic gets its own loss's gradient
    logged = {"loss/critic": loss_q.detach(), "charts/q": q.mean().detach(),
              "loss/cost_critic": loss_qc.detach(), "charts/qc": qc.mean().detach()}

    if update_actor:
        detached = features.detach()  # the actor does not train the (image) encoder
        action, log_prob = agent.actor(detached)
        with frozen(agent.critic), frozen(agent.cost_critic):   # dQ/da and dQ_c/da only
            q_pi = agent.critic(detached, action).min(dim=0).values
            loss_pi = lagrangian_actor_loss(log_prob, q_pi, agent.cost_critic(detached, action)[0], alpha, lam)
            gradient_step(opt.actor, loss_pi)
        loss_alpha = alpha_loss(log_alpha, log_prob, target_entropy)
        if hp.autotune:
            gradient_step(opt.alpha, loss_alpha)
        logged.update({"loss/actor": loss_pi.detach(), "loss/alpha": loss_alpha.detach(), "charts/alpha": alpha,
                       "charts/entropy": -log_prob.mean().detach()})
    polyak_update(target, agent, hp.tau)
    return logged


def move_multiplier(multiplier: LagrangeMultiplier, run: Run, learning: bool) -> None:
    """Move lambda from J_c, the mean cost of the training episodes finished since its last move
    (none finished: it stays). During the heat-up (``learning`` False) only the count moves on:
    the random actions' episodes say nothing about the policy's cost."""
    episodes = run.episodes
    if episodes.total_episodes > 0 and episodes.cost_episodes == 0:
        raise DrivelabError("sac_lag needs an env that reports a cost per step (info['cost'], as SafeMetaDrive "
                            "does); add env.cost terms, e.g. env.cost: {crash: {}}")
    measured = multiplier.measured_cost(episodes.cost_total, episodes.cost_episodes)
    if measured is not None and learning:
        run.record(multiplier.update(measured))


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = ReplayCollector.from_config(cfg, run, build_policy, exploration=PolicySampling, costs=True)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    log_alpha = torch.nn.Parameter(torch.tensor(float(hp.init_alpha)).log().to(run.device))
    target_entropy = hp.target_entropy if hp.target_entropy is not None else -float(collector.act_space.shape[0])
    target = make_target(agent)   # Polyak copy: its encoder, critics and cost critic give the targets
    averaged = make_target(agent) if hp.average_policy > 0 else None   # as in sac.py
    # lambda and its state (float64 buffers) on the CPU: one small tensor, read once per iteration
    multiplier = LagrangeMultiplier(hp)
    opt = build_optimizers(agent, log_alpha, hp)
    if hp.compile:
        agent.compile_networks()
    modules = {"policy": agent, "target": target, "alpha": torch.nn.ParameterDict({"log_alpha": log_alpha}),
               "lagrange": multiplier}
    if averaged is not None:
        modules.update(policy=averaged, learner=agent)
    resumed = run.start(modules, opt._asdict(), policy=modules["policy"])
    collector.start(resumed, exploration=PolicySampling(hp, collector.num_envs, collector.act_space.shape[0], cfg.seed))
    try:
        while not run.done:
            # 1. Act (as SAC), storing each step's cost beside its reward.
            before = collector.steps
            steps = collector.collect(agent)
            # 2. Every lagrange_every env steps (a schedule of the step count, so it survives a
            #    resume), move lambda from the measured cost of the episodes finished since.
            if before // hp.lagrange_every != collector.steps // hp.lagrange_every:
                move_multiplier(multiplier, run, learning=collector.steps >= hp.learning_starts)
            lam = multiplier.lam
            # 3. utd gradient steps per env step, the actor on the Lagrangian with this lambda.
            for batch in collector.batches():
                update_actor = (collector.updates - 1) % hp.actor_every == 0
                with run.timing.update, update_precision(hp, run.device):
                    run.record(update(agent, target, log_alpha, opt, batch, hp, target_entropy, lam, update_actor))
                    if averaged is not None and update_actor:
                        polyak_update(averaged, agent, hp.average_policy)
            # 4. Log, evaluate and checkpoint (with the replay buffer and lambda) when due.
            run.end_iteration(steps, extra_state=collector.state)
    finally:
        collector.close()
