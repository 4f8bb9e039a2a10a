"""PPO: proximal policy optimisation with a clipped surrogate (Schulman et al. 2017).

Each iteration collects T steps in N envs (:class:`drivelab.rollout.RolloutCollector`), computes
GAE(lambda) advantages, then takes ``update_epochs`` passes of minibatch gradient steps on

    L = -E[min(rho * A, clip(rho, 1 - eps, 1 + eps) * A)] + vf_coef * L_V - ent_coef * H,
    rho = pi_theta(a|s) / pi_old(a|s),

with the implementation details that matter (Huang et al. 2022, "The 37 implementation details
of PPO"): advantage normalisation per minibatch, optional value clipping, global gradient-norm
clipping, linear learning-rate annealing, orthogonal initialisation, and an optional early stop
when the approximate KL to the rollout policy exceeds ``target_kl``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
import torch

from drivelab.config import TrainConfig
from drivelab.envs import env_spaces
from drivelab.errors import DrivelabError
from drivelab.losses import approx_kl, clipped_surrogate_loss, explained_variance, value_loss
from drivelab.nets import ActorCritic
from drivelab.rollout import RolloutBatch, train_actor_critic
from drivelab.run import Run


@dataclass
class Params:
    lr: float = 3e-4
    anneal_lr: bool = True
    num_steps: int = 128          # rollout length T per env
    gamma: float = 0.99
    gae_lambda: float = 0.95
    update_epochs: int = 4
    num_minibatches: int = 4
    clip_coef: float = 0.2
    clip_vloss: bool = True
    norm_adv: bool = True
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    target_kl: float | None = None
    normalize_obs: bool = False
    normalize_reward: bool = False
    hidden: list[int] = field(default_factory=lambda: [64, 64])
    activation: str = "tanh"
    log_std_init: float = 0.0

    def validate(self) -> None:
        if self.num_steps < 1 or self.update_epochs < 1 or self.num_minibatches < 1:
            raise DrivelabError("config fields 'ppo.num_steps', 'ppo.update_epochs' and 'ppo.num_minibatches' must be >= 1")
        if not 0 <= self.gae_lambda <= 1 or not 0 <= self.gamma <= 1:
            raise DrivelabError("config fields 'ppo.gamma' and 'ppo.gae_lambda' must be in [0, 1]")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    hp = cfg.algo_params
    return ActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init, obs_norm=hp.normalize_obs)


def update(agent: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch, hp: Params,
           generator: torch.Generator | None = None) -> dict[str, float]:
    """``update_epochs`` passes of minibatch PPO steps over the rollout; returns logged stats."""
    size = batch.obs.shape[0]
    minibatch = max(1, size // hp.num_minibatches)
    stats = torch.zeros(5)  # policy loss, value loss, entropy, approx kl, clip fraction (summed)
    steps = 0
    for _ in range(hp.update_epochs):
        order = torch.randperm(size, generator=generator)
        for start in range(0, size - minibatch + 1, minibatch):
            idx = order[start:start + minibatch]
            dist = agent.distribution(batch.obs[idx])
            log_prob = dist.log_prob(batch.actions[idx])
            adv = batch.advantages[idx]
            if hp.norm_adv:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss, ratio = clipped_surrogate_loss(log_prob, batch.log_probs[idx], adv, hp.clip_coef)
            v_loss = value_loss(agent.value(batch.obs[idx]), batch.values[idx], batch.returns[idx],
                                hp.clip_coef if hp.clip_vloss else None)
            entropy = dist.entropy().mean()
            loss = pg_loss + hp.vf_coef * v_loss - hp.ent_coef * entropy
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(agent.parameters(), hp.max_grad_norm)
            optimizer.step()
            with torch.no_grad():
                kl = approx_kl(log_prob - batch.log_probs[idx])
                clip_frac = ((ratio - 1).abs() > hp.clip_coef).float().mean()
                stats += torch.stack([pg_loss, v_loss, entropy, kl, clip_frac]).detach()
            steps += 1
        if hp.target_kl is not None and kl > hp.target_kl:  # one sync per epoch, not per step
            break
    mean = (stats / steps).tolist()
    ev = explained_variance(batch.values, batch.returns).item()
    return {"loss/policy": mean[0], "loss/value": mean[1], "loss/entropy": mean[2], "loss/approx_kl": mean[3],
            "loss/clip_fraction": mean[4], "loss/explained_variance": ev}


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    agent = build_policy(cfg, *env_spaces(cfg.env)).to(run.device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)
    train_actor_critic(cfg, run, agent, optimizer, lambda batch: update(agent, optimizer, batch, hp))
