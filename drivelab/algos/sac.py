"""SAC: soft actor-critic with automatic entropy tuning (Haarnoja et al. 2018a, 2018b).

Maximises return plus entropy, E[sum_t r_t + alpha * H(pi(.|s_t))], with

* a squashed Gaussian actor a = tanh(u), whose log-probability carries the tanh
  change-of-variables correction (:func:`drivelab.offpolicy.squashed_gaussian_log_prob`);
* twin critics and a clipped double-Q target (Fujimoto et al. 2018), computed in one batched pass:
      y = r + gamma * (1 - terminated) * (min_e Q'_e(s', a') - alpha * log pi(a'|s')),  a' ~ pi(.|s');
* the actor loss E[alpha * log pi(a|s) - min_e Q_e(s, a)] with a reparameterised a ~ pi(.|s);
* alpha tuned so the policy's entropy tracks a target (-|A| by default):
      L(alpha) = -E[log alpha * (log pi(a|s) + target_entropy)].

The shared loop (replay, heat-up, update-to-data ratio, evaluation, checkpoints) is
:func:`drivelab.offpolicy.train_off_policy`.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.buffers import ReplayBatch
from drivelab.config import TrainConfig
from drivelab.envs import env_spaces
from drivelab.offpolicy import (OffPolicyAgent, OffPolicyParams, StatAccumulator, make_optimizers, make_target,
                                polyak_update, train_off_policy)
from drivelab.run import Run


@dataclass
class Params(OffPolicyParams):
    alpha_lr: float = 3e-4
    # Start well below 1 when rewards per step are small (MetaDrive: ~0.1-1): with alpha = 1 the
    # entropy bonus outweighs the reward, the policy stays near uniform while log(alpha) falls by
    # ~alpha_lr per update, and by the time the policy reacts to rewards alpha is ~0.001 and too
    # slow to come back; exploration is gone (MetaDrive, 20 minutes: route completion 5.8%,
    # vs 28.2% with 0.05).
    init_alpha: float = 1.0
    autotune: bool = True
    target_entropy: float | None = None   # None: -|A|
    actor_every: int = 1                  # actor and alpha update once every N critic updates


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> OffPolicyAgent:
    hp = cfg.algo_params
    return OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=True, critics=2)


def critic_loss(q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Sum over critics of the mean squared TD error: q (E, B), target (B,)."""
    return (q - target).pow(2).mean(dim=1).sum()


def soft_td_target(rewards: torch.Tensor, terminated: torch.Tensor, next_q: torch.Tensor, next_log_prob: torch.Tensor,
                   alpha: torch.Tensor, gamma: float) -> torch.Tensor:
    """y = r + gamma * (1 - terminated) * (min_e Q'_e(s', a') - alpha * log pi(a'|s')).
    rewards, terminated, next_log_prob (B,); next_q (E, B). Truncated steps do bootstrap."""
    return rewards + gamma * (1.0 - terminated) * (next_q.min(dim=0).values - alpha * next_log_prob)


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    obs_space, act_space = env_spaces(cfg.env)
    agent = build_policy(cfg, obs_space, act_space).to(run.device)
    # Target networks: a Polyak-averaged copy of the agent (its encoder too, so y does not move
    # with the online critic's features). Only its encoder and critics are used.
    target = make_target(agent)
    log_alpha = torch.nn.Parameter(torch.tensor(float(hp.init_alpha)).log().to(run.device))
    target_entropy = hp.target_entropy if hp.target_entropy is not None else -float(act_space.shape[0])
    optimizers = make_optimizers(agent, hp)
    critic_opt, actor_opt = optimizers["critic"], optimizers["actor"]
    alpha_opt = torch.optim.Adam([log_alpha], lr=hp.alpha_lr)
    alpha_holder = torch.nn.ParameterDict({"log_alpha": log_alpha})
    stats = StatAccumulator("loss/critic", "loss/actor", "loss/alpha", "charts/alpha", "charts/entropy", "charts/q")
    updates = 0

    def update(batch: ReplayBatch) -> None:
        nonlocal updates
        alpha = log_alpha.exp().detach()
        with torch.no_grad():
            next_action, next_log_prob = agent.actor(agent.features(batch.next_obs))
            next_q = target.critic(target.features(batch.next_obs), next_action)
            y = soft_td_target(batch.rewards, batch.terminated, next_q, next_log_prob, alpha, hp.gamma)
        features = agent.features(batch.obs)
        q = agent.critic(features, batch.actions)
        loss_q = critic_loss(q, y)
        critic_opt.zero_grad()
        loss_q.backward()
        critic_opt.step()

        if updates % hp.actor_every == 0:
            detached = features.detach()  # the actor does not train the (image) encoder
            action, log_prob = agent.actor(detached)
            q_pi = agent.critic(detached, action).min(dim=0).values
            loss_pi = (alpha * log_prob - q_pi).mean()
            actor_opt.zero_grad()
            loss_pi.backward()
            actor_opt.step()
            loss_alpha = -(log_alpha * (log_prob.detach() + target_entropy)).mean()
            if hp.autotune:
                alpha_opt.zero_grad()
                loss_alpha.backward()
                alpha_opt.step()
            stats.add(loss_q, loss_pi, loss_alpha, alpha, -log_prob.mean(), q.mean())
        polyak_update(target, agent, hp.tau)
        updates += 1

    def explore(obs: torch.Tensor, step: int):
        return agent.act(obs).cpu().numpy()  # SAC explores by sampling its own stochastic policy

    train_off_policy(cfg, run, agent,
                     modules={"policy": agent, "target": target, "alpha": alpha_holder},
                     optimizers={**optimizers, "alpha": alpha_opt},
                     explore=explore, update=update, end_episodes=lambda done: None, flush_stats=stats.flush)

