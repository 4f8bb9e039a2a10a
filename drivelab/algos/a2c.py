"""A2C: synchronous advantage actor-critic (Mnih et al. 2016, the synchronous variant of A3C).

Each iteration collects a short rollout (``num_steps`` per env, 5 by default) in N envs, computes
GAE(lambda) advantages (Schulman et al. 2016; lambda=1 gives the n-step returns of the original
A2C), and takes ONE gradient step on

    L = -mean(log pi(a|s) * A) + vf_coef * 0.5 * mean((V(s) - R)^2) - ent_coef * H[pi(.|s)].

No clipping, no epochs: every sample is used once, by the policy that collected it (which is
what makes the plain policy gradient unbiased). The collector is PPO's
(:class:`drivelab.training.collection.rollout.RolloutCollector`); the iterations are tiny (T * N = 40 steps by
default), so metrics are averaged over the iterations between two logs.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.collection.rollout import RolloutCollector
from drivelab.training.learning.hyperparams import ActorCriticParams
from drivelab.training.learning.losses import explained_variance, policy_gradient_loss, value_loss
from drivelab.training.learning.optim import gradient_step, linear_decay, set_learning_rate
from drivelab.training.learning.policy_nets import ActorCritic, limit_log_std
from drivelab.training.learning.rollout_buffers import RolloutBatch
from drivelab.training.run import Run


@dataclass
class Params(ActorCriticParams):
    """A2C's defaults (A3C's paper and SB3); the shared fields are in
    :class:`drivelab.training.learning.hyperparams.ActorCriticParams`."""
    lr: float = 7e-4
    anneal_lr: bool = False
    num_steps: int = 5            # n in n-step returns
    gae_lambda: float = 1.0       # lambda = 1: the n-step returns of the original A2C
    norm_adv: bool = False
    optimizer: str = "rmsprop"    # rmsprop (as in the A3C paper and SB3) or adam

    def validate(self) -> None:
        super().validate()
        if self.optimizer not in ("rmsprop", "adam"):
            raise DrivelabError(f"config field 'a2c.optimizer' must be rmsprop or adam, got {self.optimizer!r}")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    hp = cfg.algo_params
    return ActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init, obs_norm=hp.normalize_obs)


def update(agent: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch, hp: Params) -> dict[str, torch.Tensor]:
    """One gradient step on the whole rollout (B = T * N samples); returns the losses (0-d)."""
    dist = agent.distribution(batch.obs)
    adv = batch.advantages
    if hp.norm_adv:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = policy_gradient_loss(dist.log_prob(batch.actions), adv)
    v_loss = value_loss(agent.value(batch.obs), batch.values, batch.returns, clip_coef=None)
    entropy = dist.entropy().mean()
    loss = pg_loss + hp.vf_coef * v_loss - hp.ent_coef * entropy
    gradient_step(optimizer, loss, agent.parameters(), hp.max_grad_norm)
    return {"loss/policy": pg_loss.detach(), "loss/value": v_loss.detach(), "loss/entropy": entropy.detach(),
            "loss/explained_variance": explained_variance(batch.values, batch.returns)}


def make_optimizer(agent: ActorCritic, hp: Params) -> torch.optim.Optimizer:
    if hp.optimizer == "rmsprop":  # A3C's settings (alpha 0.99, eps 1e-5)
        return torch.optim.RMSprop(agent.parameters(), lr=hp.lr, alpha=0.99, eps=1e-5)
    return torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = RolloutCollector.from_config(cfg, run, build_policy)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    optimizer = make_optimizer(agent, hp)
    run.start({"policy": agent, **collector.modules()}, {"policy": optimizer}, policy=agent)
    try:
        while not run.done:
            lr = linear_decay(hp.lr, run.step, cfg.steps) if hp.anneal_lr else hp.lr
            set_learning_rate(optimizer, lr)
            std_log = limit_log_std(agent.actor, hp, run.step, cfg.steps)  # optional std schedule
            batch = collector.collect(agent)                  # T steps x N envs, GAE(lambda)
            with run.timing.update:
                losses = update(agent, optimizer, batch, hp)  # one gradient step
            if agent.obs_rms is not None:                     # after the update: both saw the same statistics
                agent.obs_rms.update(batch.obs.float())
            run.record({**losses, "charts/lr": lr, **std_log})
            run.end_iteration(collector.steps_per_rollout)
    finally:
        collector.close()
