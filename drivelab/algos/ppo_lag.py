"""PPO-Lagrangian: PPO that keeps the mean episode cost under a limit (Ray, Achiam & Amodei 2019).

Constrained RL maximises the return J_r subject to J_c <= d, the mean episode cost at most
``cost_limit`` (Altman 1999). PPO-Lagrangian solves the saddle point of the Lagrangian
J_r - lambda (J_c - d) by alternating two steps each iteration:

1. **the multiplier** (dual ascent): lambda rises while the episodes of the last rollout cost more
   than d, and falls towards 0 when they cost less
   (:class:`drivelab.training.learning.lagrange.LagrangeMultiplier`, gradient or PID update);
2. **the policy** (PPO on the Lagrangian): the clipped surrogate of :mod:`drivelab.algos.ppo`
   with the advantage of r - lambda c,

       A = (A_r - lambda * A_c) / (1 + lambda),

   where A_c is GAE applied to the costs with a second critic V_c(s), trained like V(s).

The multiplier is updated first, from the measured cost of the episodes that ended in the
rollout just played (as in OmniSafe's PPOLag), then the policy takes PPO's epochs. With
``norm_adv`` the two advantages are standardised separately in each minibatch before they are
combined. The multiplier is checkpointed with the weights (``module/lagrange/*``), so a resumed
run goes on exactly.

Everything else is PPO's (:mod:`drivelab.algos.ppo`): its hyperparameters (section ``ppo_lag``,
plus those of :class:`drivelab.training.learning.hyperparams.ConstraintParams`), its rollouts
(:class:`drivelab.training.collection.rollout.RolloutCollector` with costs) and its losses.
The env must report a cost: ``info["cost"]`` per step (MetaDrive and SafeMetaDrive do; any env
gets one with ``env.cost`` terms, see :mod:`drivelab.envs.costs`).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.algos import ppo
from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.collection.rollout import RolloutCollector
from drivelab.training.learning.hyperparams import ConstraintParams
from drivelab.training.learning.lagrange import LagrangeMultiplier
from drivelab.training.learning.losses import (
    approx_kl,
    clipped_surrogate_loss,
    explained_variance,
    lagrangian_advantages,
    standardize,
    value_loss,
)
from drivelab.training.learning.optim import gradient_step, linear_decay, set_learning_rate
from drivelab.training.learning.policy_nets import ActorCritic, limit_log_std
from drivelab.training.learning.rollout_buffers import RolloutBatch
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.run import Run


@dataclass
class Params(ppo.Params, ConstraintParams):
    """PPO's hyperparameters (:class:`drivelab.algos.ppo.Params`) and the cost constraint's
    (cost_limit, cost_gamma, the multiplier's update: :class:`ConstraintParams`)."""

    def validate(self) -> None:
        super().validate()
        self.validate_constraint("ppo_lag")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    hp = cfg.algo_params
    return ActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init, obs_norm=hp.normalize_obs,
                       cost_critic=True)


def update(agent: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch, hp: Params,
           lam: float) -> dict[str, torch.Tensor]:
    """``update_epochs`` passes of minibatch PPO steps on the Lagrangian's advantage with
    multiplier ``lam`` (B samples, minibatches of B // num_minibatches, shuffled with torch's
    global generator), the cost critic trained beside the critic; returns the means of the
    logged statistics as 0-d tensors.

    Per minibatch: L = clip_surrogate((A_r - lam A_c) / (1 + lam)) + vf_coef (L_V + L_Vc) - ent_coef H.
    """
    size = batch.obs.shape[0]
    minibatch = max(1, size // hp.num_minibatches)
    stats = torch.zeros(6, device=batch.obs.device)  # 3 losses (policy, value, cost value), entropy, kl, clip fraction
    steps = epochs = 0
    for epochs in range(1, hp.update_epochs + 1):
        order = torch.randperm(size)
        for start in range(0, size - minibatch + 1, minibatch):
            idx = order[start:start + minibatch]
            dist, value = agent.distribution_and_value(batch.obs[idx])
            cost_value = agent.cost_value(batch.obs[idx])
            log_prob = dist.log_prob(batch.actions[idx])
            adv, cost_adv = batch.advantages[idx], batch.cost_advantages[idx]
            if hp.norm_adv:  # each on its own scale, so lambda weighs like against like
                adv, cost_adv = standardize(adv), standardize(cost_adv)
            pg_loss, ratio = clipped_surrogate_loss(log_prob, batch.log_probs[idx],
                                                    lagrangian_advantages(adv, cost_adv, lam), hp.clip_coef)
            clip_v = hp.clip_coef if hp.clip_vloss else None
            v_loss = value_loss(value, batch.values[idx], batch.returns[idx], clip_v)
            c_loss = value_loss(cost_value, batch.cost_values[idx], batch.cost_returns[idx], clip_v)
            entropy = dist.entropy().mean()
            loss = pg_loss + hp.vf_coef * (v_loss + c_loss) - hp.ent_coef * entropy
            gradient_step(optimizer, loss, agent.parameters(), hp.max_grad_norm)
            with torch.no_grad():
                kl = approx_kl(log_prob - batch.log_probs[idx])
                clip_frac = ((ratio - 1).abs() > hp.clip_coef).float().mean()
                stats += torch.stack([pg_loss, v_loss, c_loss, entropy, kl, clip_frac]).detach()
            steps += 1
        if hp.target_kl is not None and kl > hp.target_kl:  # one sync per epoch, not per step
            break
    mean = stats / steps
    return {"loss/policy": mean[0], "loss/value": mean[1], "loss/cost_value": mean[2], "loss/entropy": mean[3],
            "loss/approx_kl": mean[4], "loss/clip_fraction": mean[5],
            "loss/explained_variance": explained_variance(batch.values, batch.returns),
            "loss/explained_variance_cost": explained_variance(batch.cost_values, batch.cost_returns),
            "charts/cost_value_mean": batch.cost_values.mean(),
            "loss/epochs": torch.tensor(float(epochs), device=batch.obs.device)}


def update_multiplier(multiplier: LagrangeMultiplier, episodes: EpisodeTracker) -> dict[str, float]:
    """Move lambda from the mean cost of the training episodes that ended since its last update
    (none ended: lambda stays). Returns what to log, lambda always."""
    if episodes.total_episodes > 0 and episodes.cost_episodes == 0:
        raise DrivelabError("ppo_lag needs an env that reports a cost (info['cost'] each step), but this one's "
                            "episodes end without one: add env.cost terms, e.g. env.cost: {crash: {}}")
    measured = multiplier.measured_cost(episodes.cost_total, episodes.cost_episodes)
    logs = multiplier.update(measured) if measured is not None else {}
    return {**logs, "charts/lagrange_multiplier": multiplier.lam}


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = RolloutCollector.from_config(cfg, run, build_policy, costs=True)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)
    multiplier = LagrangeMultiplier(hp)  # float64 state on the CPU, saved with the weights
    run.start({"policy": agent, "lagrange": multiplier, **collector.modules()}, {"policy": optimizer}, policy=agent)
    try:
        while not run.done:
            if hp.anneal_lr:
                set_learning_rate(optimizer, linear_decay(hp.lr, run.step, cfg.steps))
            std_log = limit_log_std(agent.actor, hp, run.step, cfg.steps)  # optional std schedule
            # 1. Collect T steps in each of the N envs; GAE(lambda) advantages of the reward and of the cost.
            batch = collector.collect(agent)
            # 2. The multiplier, from the cost of the episodes that ended in this rollout.
            run.record(update_multiplier(multiplier, run.episodes))
            # 3. Epochs of clipped minibatch steps on the Lagrangian's advantage.
            with run.timing.update:
                stats = update(agent, optimizer, batch, hp, multiplier.lam)
            run.record(stats)
            # 4. Observation statistics move after the update (as in PPO).
            if agent.obs_rms is not None:
                agent.obs_rms.update(batch.obs.float())
            run.record({"charts/lr": optimizer.param_groups[0]["lr"], **std_log})
            # 5. Log, evaluate and checkpoint when due.
            run.end_iteration(collector.steps_per_rollout)
    finally:
        collector.close()
