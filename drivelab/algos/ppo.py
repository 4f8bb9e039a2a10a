"""PPO: proximal policy optimisation with a clipped surrogate (Schulman et al. 2017).

Each iteration collects T steps in N envs, computes GAE(lambda) advantages, then takes
``update_epochs`` passes of minibatch gradient steps on

    L = -E[min(rho * A, clip(rho, 1 - eps, 1 + eps) * A)] + vf_coef * L_V - ent_coef * H,
    rho = pi_theta(a|s) / pi_old(a|s),

with the implementation details that matter (Huang et al. 2022, "The 37 implementation details
of PPO"): advantage normalisation per minibatch, optional value clipping, global gradient-norm
clipping, linear learning-rate annealing, orthogonal initialisation, and an optional early stop
when the approximate KL to the rollout policy exceeds ``target_kl``.

With ``overlap_update`` the update runs in a background thread while the envs collect the next
rollout with a copy of the weights from before it, so the env workers no longer wait through the
update (on-policy PPO leaves them idle for 10-15% of the wall time on MetaDrive). That rollout is
then one update old when it is trained on: the loss clips the ratio around the policy at the start
of its update and weights each sample by pi_prox / mu, the decoupled objective of Hilton et al.
2021 (see :func:`drivelab.training.losses.clipped_surrogate_loss`). Meant for CPU training beside env
subprocesses; on CUDA both threads share the default stream, which hides less of the update.

Shared parts used here: :class:`drivelab.training.rollout.RolloutCollector` (env stepping, episode ends,
GAE from :func:`drivelab.training.returns.gae`), the losses in :mod:`drivelab.training.losses`, and
:class:`drivelab.training.run.Run` (logging, evaluation, checkpoints).
"""

from __future__ import annotations

import copy
import functools
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.losses import approx_kl, clipped_surrogate_loss, explained_variance, value_loss
from drivelab.training.nets import ActorCritic, limit_log_std
from drivelab.training.rollout import ActorCriticParams, RolloutBatch, RolloutCollector
from drivelab.training.optim import gradient_step, linear_decay, set_learning_rate
from drivelab.training.run import Run


@dataclass
class Params(ActorCriticParams):
    """PPO's own hyperparameters; lr, num_steps, gamma, gae_lambda, ent_coef, ... are in
    :class:`drivelab.training.rollout.ActorCriticParams`."""
    update_epochs: int = 4            # passes over each rollout
    num_minibatches: int = 4          # minibatches per pass (minibatch = T * N / this)
    clip_coef: float = 0.2            # PPO's epsilon: the ratio is clipped to [1 - eps, 1 + eps]
    clip_vloss: bool = True           # clip the value update as well (PPO2)
    target_kl: float | None = None    # stop an update's epochs once the approximate KL exceeds this (None: never)
    overlap_update: bool = False      # update in the background while the next rollout is collected (see above)

    def validate(self) -> None:
        super().validate()
        if self.update_epochs < 1 or self.num_minibatches < 1:
            raise DrivelabError("config fields 'ppo.update_epochs' and 'ppo.num_minibatches' must be >= 1")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    hp = cfg.algo_params
    return ActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init, obs_norm=hp.normalize_obs)


def proximal(agent: ActorCritic, batch: RolloutBatch) -> tuple[RolloutBatch, torch.Tensor]:
    """For a rollout collected by an older policy mu (``overlap_update``): the batch with the
    current policy's log-probs and values in place of mu's, which the update clips around
    (the critic targets, ``returns``, stay those of mu's critic), and the (B,) weights
    pi_prox(a|s) / mu(a|s) of the decoupled objective (Hilton et al. 2021)."""
    with torch.no_grad():
        dist, values = agent.distribution_and_value(batch.obs)
        log_probs = dist.log_prob(batch.actions)
    return batch._replace(log_probs=log_probs, values=values), (log_probs - batch.log_probs).exp()


def update(agent: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch, hp: Params,
           generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """``update_epochs`` passes of minibatch PPO steps over the rollout (B samples, minibatches of
    B // num_minibatches, shuffled with ``generator``, None: torch's global one); returns the
    means of the logged statistics as 0-d tensors. With ``overlap_update`` the rollout is one
    update old: clip around the current policy, weight by pi_prox / mu (:func:`proximal`)."""
    size = batch.obs.shape[0]
    behaviour_weights = torch.ones(size, device=batch.obs.device)  # on-policy: pi_prox = mu
    logged: dict[str, torch.Tensor] = {}
    if hp.overlap_update:
        batch, behaviour_weights = proximal(agent, batch)
        logged = {"loss/behaviour_weight_mean": behaviour_weights.mean(), "loss/behaviour_weight_max": behaviour_weights.max()}
    minibatch = max(1, size // hp.num_minibatches)
    stats = torch.zeros(5)  # policy loss, value loss, entropy, approx kl, clip fraction (summed)
    steps = epochs = 0
    for epochs in range(1, hp.update_epochs + 1):
        order = torch.randperm(size, generator=generator)
        for start in range(0, size - minibatch + 1, minibatch):
            idx = order[start:start + minibatch]
            dist, value = agent.distribution_and_value(batch.obs[idx])
            log_prob = dist.log_prob(batch.actions[idx])
            adv = batch.advantages[idx]
            if hp.norm_adv:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss, ratio = clipped_surrogate_loss(log_prob, batch.log_probs[idx], adv, hp.clip_coef,
                                                    behaviour_weights[idx])
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
            "loss/epochs": torch.tensor(float(epochs)), **logged}


def wait_for(job: Future) -> tuple[dict[str, torch.Tensor], bool]:
    """The background update's statistics, and whether a Ctrl-C came while waiting: it is held
    back until the update has ended, as nothing may save or copy half-updated weights."""
    interrupted = False
    while True:
        try:
            return job.result(), interrupted
        except KeyboardInterrupt:
            interrupted = True


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    collector = RolloutCollector(cfg.env, run, num_steps=hp.num_steps, gamma=hp.gamma, gae_lambda=hp.gae_lambda,
                                 scale_rewards=hp.normalize_reward, buffers=2 if hp.overlap_update else 1,
                                 policy_factory=functools.partial(build_policy, cfg) if hp.act_in_workers else None)
    agent = build_policy(cfg, collector.obs_space, collector.act_space).to(run.device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)
    run.start({"policy": agent, **collector.modules()}, {"policy": optimizer}, policy=agent)

    def finish_iteration(batch: RolloutBatch, stats: dict[str, torch.Tensor], std_log: dict[str, float]) -> None:
        run.record(stats)
        # 3. Observation statistics move after the update (the next update's minibatches, and
        #    with overlap_update its proximal pass, see the statistics its rollout is scored with).
        if agent.obs_rms is not None:
            agent.obs_rms.update(batch.obs.float())
        run.record({"charts/lr": optimizer.param_groups[0]["lr"], **std_log})
        # 4. Log, evaluate and checkpoint when due.
        run.end_iteration(collector.steps_per_rollout)

    # overlap_update: `actor`, a copy of the weights, acts in the envs while `agent` learns in a
    # background thread, which shuffles minibatches with a generator of its own (torch's global
    # one samples the actions meanwhile; sharing it would make runs depend on thread timing).
    actor, background, shuffle = agent, None, None
    if hp.overlap_update:
        actor, background = copy.deepcopy(agent), ThreadPoolExecutor(max_workers=1)
        shuffle = torch.Generator().manual_seed(int(run.rng.integers(2**63 - 1)))
    following = None  # overlap_update: the rollout collected while the previous update ran
    try:
        while not run.done:
            if hp.anneal_lr:
                set_learning_rate(optimizer, linear_decay(hp.lr, run.step, cfg.steps))
            std_log = limit_log_std(agent.actor, hp, run.step, cfg.steps)  # optional std schedule
            interrupted = False  # overlap_update: a Ctrl-C held back until the update in flight is counted
            if background is None:
                # 1. Collect T steps in each of the N envs; GAE(lambda) advantages and critic targets.
                batch = collector.collect(agent)
                # 2. Epochs of clipped minibatch steps on that batch.
                with run.timing.update:
                    stats = update(agent, optimizer, batch, hp)
            else:
                # 1 and 2 overlapped: the update on the last rollout runs in the background while
                # the envs collect the next one with `actor`, the weights from before that update.
                actor.load_state_dict(agent.state_dict())
                batch = following if following is not None else collector.collect(actor)
                job = background.submit(update, agent, optimizer, batch, hp, shuffle)
                following = None
                try:
                    if run.step + collector.steps_per_rollout < cfg.steps:
                        following = collector.collect(actor)
                except KeyboardInterrupt:
                    interrupted = True
                with run.timing.update:  # the part of the update that collecting did not hide
                    stats, interrupted_while_waiting = wait_for(job)
                interrupted |= interrupted_while_waiting
            finish_iteration(batch, stats, std_log)
            if interrupted:  # raised now, so the checkpoint that follows holds whole, counted updates
                raise KeyboardInterrupt
    finally:
        if background is not None:
            background.shutdown()
        collector.close()
