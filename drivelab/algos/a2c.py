"""A2C: synchronous advantage actor-critic (Mnih et al. 2016, the synchronous variant of A3C).

Each iteration collects a short rollout (``num_steps`` per env, 5 by default) in N envs, computes
GAE(lambda) advantages (Schulman et al. 2016; lambda=1 gives the n-step returns of the original
A2C), and takes ONE gradient step on

    L = -mean(log pi(a|s) * A) + vf_coef * 0.5 * mean((V(s) - R)^2) - ent_coef * H[pi(.|s)].

No clipping, no epochs: every sample is used once, by the policy that collected it (which is
what makes the plain policy gradient unbiased). The rollout loop is PPO's (:func:`drivelab.rollout.train_actor_critic`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
import torch

from drivelab.config import TrainConfig
from drivelab.envs import env_spaces
from drivelab.errors import DrivelabError
from drivelab.losses import explained_variance, policy_gradient_loss, value_loss
from drivelab.nets import ActorCritic
from drivelab.rollout import RolloutBatch, train_actor_critic
from drivelab.run import Run


@dataclass
class Params:
    lr: float = 7e-4
    anneal_lr: bool = False
    num_steps: int = 5            # rollout length T per env (n in n-step returns)
    gamma: float = 0.99
    gae_lambda: float = 1.0
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    norm_adv: bool = False
    # rmsprop (as in the A3C paper and SB3) or adam
    optimizer: str = "rmsprop"
    normalize_obs: bool = False
    normalize_reward: bool = False
    hidden: list[int] = field(default_factory=lambda: [64, 64])
    activation: str = "tanh"
    log_std_init: float = 0.0

    def validate(self) -> None:
        if self.optimizer not in ("rmsprop", "adam"):
            raise DrivelabError(f"config field 'a2c.optimizer' must be rmsprop or adam, got {self.optimizer!r}")
        if self.num_steps < 1:
            raise DrivelabError("config field 'a2c.num_steps' must be >= 1")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    hp = cfg.algo_params
    return ActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init, obs_norm=hp.normalize_obs)


def update(agent: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch, hp: Params) -> dict[str, float]:
    """One gradient step on the whole rollout."""
    dist = agent.distribution(batch.obs)
    adv = batch.advantages
    if hp.norm_adv:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = policy_gradient_loss(dist.log_prob(batch.actions), adv)
    v_loss = value_loss(agent.value(batch.obs), batch.values, batch.returns, clip_coef=None)
    entropy = dist.entropy().mean()
    loss = pg_loss + hp.vf_coef * v_loss - hp.ent_coef * entropy
    optimizer.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(agent.parameters(), hp.max_grad_norm)
    optimizer.step()
    logged = torch.stack([pg_loss, v_loss, entropy, explained_variance(batch.values, batch.returns)]).tolist()
    return dict(zip(("loss/policy", "loss/value", "loss/entropy", "loss/explained_variance"), logged))


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    agent = build_policy(cfg, *env_spaces(cfg.env)).to(run.device)
    if hp.optimizer == "rmsprop":  # A3C's settings (alpha 0.99, eps 1e-5)
        optimizer = torch.optim.RMSprop(agent.parameters(), lr=hp.lr, alpha=0.99, eps=1e-5)
    else:
        optimizer = torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)
    # A2C iterations are tiny (T * N steps): log about every 1000 steps to keep tracking cheap.
    log_every = max(1, 1000 // (hp.num_steps * cfg.env.num_envs))
    train_actor_critic(cfg, run, agent, optimizer, lambda batch: update(agent, optimizer, batch, hp), log_every)
