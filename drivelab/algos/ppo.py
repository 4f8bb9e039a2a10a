"""PPO: proximal policy optimisation with a clipped surrogate (Schulman et al. 2017).

Each iteration collects T steps in N envs, computes GAE(lambda) advantages, then takes
``update_epochs`` passes of minibatch gradient steps on

    L = -E[min(rho * A, clip(rho, 1 - eps, 1 + eps) * A)] + vf_coef * L_V - ent_coef * H,
    rho = pi_theta(a|s) / pi_old(a|s),

with the implementation details that matter (Huang et al. 2022, "The 37 implementation details
of PPO"): advantage normalisation per minibatch, optional value clipping, global gradient-norm
clipping, linear learning-rate annealing, orthogonal initialisation, and an optional early stop
when the approximate KL to the rollout policy exceeds ``target_kl``.

Shared parts used here: :class:`drivelab.training.collection.rollout.RolloutCollector` (env stepping, episode ends,
GAE from :func:`drivelab.training.learning.returns.gae`), the losses in :mod:`drivelab.training.learning.losses`, and
:class:`drivelab.training.run.Run` (logging, evaluation, checkpoints).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.config import EnvConfig, TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.collection.rollout import RolloutCollector
from drivelab.training.learning.hyperparams import ActorCriticParams
from drivelab.training.learning.losses import approx_kl, clipped_surrogate_loss, explained_variance, value_loss
from drivelab.training.learning.optim import gradient_step, linear_decay, set_learning_rate
from drivelab.training.learning.policy_nets import ActorCritic, limit_log_std
from drivelab.training.learning.rollout_buffers import RolloutBatch
from drivelab.training.run import Run


@dataclass
class Params(ActorCriticParams):
    """PPO's own hyperparameters; lr, num_steps, gamma, gae_lambda, ent_coef, ... are in
    :class:`drivelab.training.learning.hyperparams.ActorCriticParams`."""
    update_epochs: int = 4            # passes over each rollout
    num_minibatches: int = 4          # minibatches per pass (minibatch = T * N / this)
    clip_coef: float = 0.2            # PPO's epsilon: the ratio is clipped to [1 - eps, 1 + eps]
    clip_vloss: bool = True           # clip the value update as well (PPO2)
    target_kl: float | None = None    # stop an update's epochs once the approximate KL exceeds this (None: never)

    def validate(self) -> None:
        super().validate()
        if self.update_epochs < 1 or self.num_minibatches < 1:
            raise DrivelabError("config fields 'ppo.update_epochs' and 'ppo.num_minibatches' must be >= 1")

    def validate_env(self, env: EnvConfig) -> None:
        # A minibatch needs 2 samples at least: the advantages are normalised by their std.
        samples = self.num_steps * env.num_envs
        if self.num_minibatches > samples // 2:
            raise DrivelabError(f"config field 'ppo.num_minibatches' is {self.num_minibatches}, but a rollout holds "
                                f"ppo.num_steps x env.num_envs = {samples} samples: use at most {max(1, samples // 2)} "
                                "(2 samples per minibatch)")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    hp = cfg.algo_params
    return ActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init, obs_norm=hp.normalize_obs)


def update(agent: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch,
           hp: Params) -> dict[str, torch.Tensor]:
    """``update_epochs`` passes of minibatch PPO steps over the rollout (B samples, minibatches of
    B // num_minibatches, shuffled with torch's global generator); returns the means of the
    logged statistics as 0-d tensors."""
    size = batch.obs.shape[0]
    minibatch = max(1, size // hp.num_minibatches)
    stats = torch.zeros(5, device=batch.obs.device)  # policy loss, value loss, entropy, approx kl, clip fraction (summed)
    steps = epochs = 0
    for epochs in range(1, hp.update_epochs + 1):
        order = torch.randperm(size)
        for start in range(0, size - minibatch + 1, minibatch):
            idx = order[start:start + minibatch]
            dist, value = agent.distribution_and_value(batch.obs[idx])
            log_prob = dist.log_prob(batch.actions[idx])
            adv = batch.advantages[idx]
            if hp.norm_adv:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss, ratio = clipped_surrogate_loss(log_prob, batch.log_probs[idx], adv, hp.clip_coef)
            v_loss = value_loss(value, batch.values[idx], batch.returns[idx],
                                hp.clip_coef if hp.clip_vloss else None)
            entropy = dist.entropy().mean()
            loss = pg_loss + hp.vf_coef * v_loss - hp.ent_coef * entropy
            gradient_step(optimizer, loss, agent.parameters(), hp.max_grad_norm)
            with torch.no_grad():
                kl = approx_kl(log_prob - batch.log_probs[idx])
                clip_frac = ((ratio - 1).abs() > hp.clip_coef).float().mean()
                stats += torch.stack([pg_loss, v_loss, entropy, kl, clip_frac]).detach()
            steps += 1
        if hp.target_kl is not None and kl > hp.target_kl:  # one sync per epoch, not per step
            break
    mean = stats / steps
    return {"loss/policy": mean[0], "loss/value": mean[1], "loss/entropy": mean[2], "loss/approx_kl": mean[3],
            "loss/clip_fraction": mean[4], "loss/explained_variance": explained_variance(batch.values, batch.returns),
            "loss/epochs": torch.tensor(float(epochs), device=batch.obs.device)}


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = RolloutCollector.from_config(cfg, run, build_policy)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)
    run.start({"policy": agent, **collector.modules()}, {"policy": optimizer}, policy=agent)
    try:
        while not run.done:
            if hp.anneal_lr:
                set_learning_rate(optimizer, linear_decay(hp.lr, run.step, cfg.steps))
            std_log = limit_log_std(agent.actor, hp, run.step, cfg.steps)  # optional std schedule
            # 1. Collect T steps in each of the N envs; GAE(lambda) advantages and critic targets.
            batch = collector.collect(agent)
            # 2. Epochs of clipped minibatch steps on that batch.
            with run.timing.update:
                stats = update(agent, optimizer, batch, hp)
            run.record(stats)
            # 3. Observation statistics move after the update (the update's minibatches see the
            #    statistics its rollout was scored with).
            if agent.obs_rms is not None:
                agent.obs_rms.update(batch.obs.float())
            run.record({"charts/lr": optimizer.param_groups[0]["lr"], **std_log})
            # 4. Log, evaluate and checkpoint when due.
            run.end_iteration(collector.steps_per_rollout)
    finally:
        collector.close()
