"""GRPO: group relative policy optimisation, critic-free (Shao et al. 2024, DeepSeekMath).

GRPO replaces PPO's learned critic with a comparison inside a *group*: G rollouts that start from
the same state. A member's advantage is how much better it did than its group,

    A_i = (R_i - mean(R_1..R_G)) / (std(R_1..R_G) + eps)                    (advantage: return)

or, per step, its reward-to-go against the members still running at the same episode step
(advantage: reward_to_go). Whatever the start state is worth cancels out, which is what a
critic's baseline is for, without learning one. The policy is then trained with PPO's clipped
ratio objective plus an optional KL penalty toward the rollout policy.

Design (no public RL library implements same-seed GRPO for Gymnasium envs):

* N envs form N / G groups of G consecutive envs. A group *round* resets its G members with the
  same seed, so they start from the same state (for MetaDrive, the same scenario: map and
  traffic; for Gymnasium envs, the same ``reset(seed=...)``). Differences between members come
  only from the stochastic policy (and any env noise after the start).
* Members whose episode ends early wait, masked: they are reset (an env that has ended must not
  be stepped) and keep stepping, but those steps are not recorded. When the last member of a
  group finishes, the round is complete and the whole group is reset together to a new seed.
  Groups are independent: a fast group starts its next round without waiting for a slow one.
* The envs run with ``AutoresetMode.DISABLED``: this loop decides every reset.
* An update uses every round completed once ``batch_steps`` steps are recorded; no episode is
  cut, because a return is only comparable to its group's when all are complete.

The group size trades variance against cost: G = 2 gives a noisy baseline, larger G a better
estimate of the start state's value but fewer distinct start states per batch and more time
waiting for a group's slowest member. A group whose members all scored the same (e.g. all
reached CartPole's 500-step limit) has zero advantage and teaches nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from drivelab.config import EnvConfig, TrainConfig
from drivelab.envs import make_vector_env
from drivelab.errors import DrivelabError
from drivelab.training.collection.checks import check_finite_step
from drivelab.training.learning.hyperparams import PolicyNetParams
from drivelab.training.learning.losses import approx_kl, clipped_surrogate_loss
from drivelab.training.learning.optim import gradient_step, linear_decay, set_learning_rate
from drivelab.training.learning.policy_nets import ActorCritic, limit_log_std
from drivelab.training.learning.returns import group_relative_advantages, group_relative_step_advantages, reward_to_go
from drivelab.training.learning.rollout_buffers import EpisodeStorage
from drivelab.training.run import Run


@dataclass
class Params(PolicyNetParams):
    group_size: int = 4           # G rollouts per start state; env.num_envs must be a multiple (default 4)
    batch_steps: int = 4000       # minimum recorded steps per update (whole rounds on top)
    advantage: str = "return"     # return | reward_to_go
    gamma: float = 1.0            # discount of returns / rewards-to-go
    lr: float = 3e-4                  # learning rate (Adam)
    anneal_lr: bool = False       # linear decay to 0 over the run
    update_epochs: int = 4            # passes over each rollout
    num_minibatches: int = 4          # minibatches per pass (minibatch = T * N / this)
    clip_coef: float = 0.2            # PPO's epsilon: the ratio is clipped to [1 - eps, 1 + eps]
    kl_coef: float = 0.0          # weight of KL(pi_old || pi_theta), the rollout policy
    ent_coef: float = 0.0             # weight of the entropy bonus
    max_grad_norm: float = 0.5        # clip the global gradient norm to this
    normalize_obs: bool = False   # running observation normalisation (saved with the weights)

    def validate(self) -> None:
        super().validate()
        if self.group_size < 2:
            raise DrivelabError("config field 'grpo.group_size' must be >= 2 (advantages compare members of a group)")
        if self.advantage not in ("return", "reward_to_go"):
            raise DrivelabError(f"config field 'grpo.advantage' must be return or reward_to_go, got {self.advantage!r}")

    def validate_env(self, env: EnvConfig) -> None:
        if env.num_envs % self.group_size:
            raise DrivelabError(
                f"config field 'env.num_envs' ({env.num_envs}) must be a multiple of 'grpo.group_size' ({self.group_size})")


class GroupBatch(NamedTuple):
    """The recorded steps of complete group rounds, flattened (B steps)."""
    obs: torch.Tensor         # (B, *obs_shape)
    actions: torch.Tensor     # (B,) or (B, act_dim)
    log_probs: torch.Tensor   # (B,) log pi_old(a|s)
    advantages: torch.Tensor  # (B,) group-relative


class Round(NamedTuple):
    group: int
    seed: int                 # every member was reset with this seed
    start: int                # storage row of the members' first step


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    hp = cfg.algo_params
    return ActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init,
                       obs_norm=hp.normalize_obs, critic=False)


class GroupRounds:
    """Which group round each env is playing, and whether its current episode is recorded.

    Env i belongs to group ``i // group_size``. ``rounds`` lists every round started in this
    collection; ``round_of[i]`` is the index of the round env i plays (or last played), and
    ``recording[i]`` says whether its current episode is part of the batch.
    """

    def __init__(self, num_envs: int, group_size: int):
        self.num_envs = num_envs
        self.groups = np.arange(num_envs) // group_size
        self.rounds: list[Round] = []
        self.round_of = np.zeros(num_envs, np.int64)
        self.recording = np.zeros(num_envs, bool)

    def start(self, group_ids: list[int], row: int, run: Run) -> tuple[np.ndarray, list[int | None]]:
        """New rounds for ``group_ids`` from storage row ``row``: one fresh seed per group, shared
        by its members. Returns the envs to reset and their seeds (None for the others)."""
        mask = np.isin(self.groups, group_ids)
        seeds: list[int | None] = [None] * self.num_envs
        for g, seed in zip(group_ids, run.reset_seeds(np.ones(len(group_ids), bool))):
            self.rounds.append(Round(int(g), seed, row))
            members = np.flatnonzero(self.groups == g)
            self.round_of[members] = len(self.rounds) - 1
            self.recording[members] = True
            for i in members:
                seeds[i] = seed
        return mask, seeds

    def finish(self, done: np.ndarray) -> list[int]:
        """Stop recording the envs whose recorded episode ended; returns the groups whose round is
        now complete (no member still recording)."""
        finished = done & self.recording
        if not finished.any():
            return []
        self.recording[finished] = False
        return [g for g in np.unique(self.groups[finished]) if not self.recording[self.groups == g].any()]

    def waiting_seeds(self, reset: np.ndarray, seeds: list[int | None]) -> list[int | None]:
        """``seeds`` with the start seed of its round for every env in ``reset`` that got none.

        Envs that ended without starting a new round wait, masked. An ended env must not be
        stepped, so they are reset too, into their round's start state."""
        return [seeds[i] if seeds[i] is not None or not reset[i] else self.rounds[self.round_of[i]].seed
                for i in range(self.num_envs)]


def store_step(storage: EpisodeStorage, t: int, obs: np.ndarray, action: torch.Tensor,
               dist: torch.distributions.Distribution, reward: np.ndarray, done: np.ndarray,
               book: GroupRounds) -> None:
    """Row ``t`` of ``storage``: the step, which envs recorded it, and the round each played."""
    storage.obs[t] = obs
    storage.actions[t] = action.cpu().numpy()
    storage.log_probs[t] = dist.log_prob(action).cpu().numpy()
    storage.rewards[t] = reward
    storage.dones[t] = done
    storage.recorded[t] = book.recording
    storage.tag[t] = np.where(book.recording, book.round_of, -1)


@torch.no_grad()
def collect_group_rounds(envs: VectorEnv, agent: ActorCritic, storage: EpisodeStorage, hp: Params,
                         run: Run, min_steps: int) -> tuple[list[Round], int, int]:
    """Play group rounds until ``min_steps`` steps are recorded and every round is complete.

    Fills ``storage`` rows [0, T): ``tag[t, i]`` is the index (into the returned list) of the
    round member i was playing at step t, and ``recorded`` marks the steps of those episodes.
    Returns (rounds, recorded steps, T).
    """
    n = envs.num_envs
    book = GroupRounds(n, hp.group_size)
    _, seeds = book.start(list(range(n // hp.group_size)), 0, run)
    with run.timing.env:
        obs, _ = envs.reset(seed=seeds)
    run.episodes.restart(np.ones(n, bool))
    recorded_steps = 0
    t = 0
    while book.recording.any():
        storage.ensure(t)
        dist = agent.distribution(torch.as_tensor(obs, device=run.device))
        action = dist.sample()
        with run.timing.env:
            next_obs, reward, terminated, truncated, info = envs.step(agent.to_env(action))
        check_finite_step(next_obs, reward, run.step + recorded_steps)
        done = terminated | truncated
        store_step(storage, t, obs, action, dist, reward, done, book)
        recorded_steps += int(book.recording.sum())
        run.episodes.step(reward, done, info, counted=book.recording)

        # A group whose last member finished starts a new round while the budget is not reached.
        reset, seeds = done.copy(), [None] * n
        complete = book.finish(done)
        if complete and recorded_steps < min_steps:
            new_members, seeds = book.start(complete, t + 1, run)
            reset |= new_members
        if reset.any():
            seeds = book.waiting_seeds(reset, seeds)
            with run.timing.env:
                next_obs, _ = envs.reset(seed=seeds, options={"reset_mask": reset})
            run.episodes.restart(reset)
        obs = next_obs
        t += 1
    return book.rounds, recorded_steps, t


def group_advantages(storage: EpisodeStorage, rounds: list[Round], length: int, hp: Params) -> np.ndarray:
    """(T, N) advantage of every recorded step (0 elsewhere), group by group."""
    size = hp.group_size
    advantages = np.zeros((length, storage.rewards.shape[1]), np.float32)
    for index, rnd in enumerate(rounds):
        cols = slice(rnd.group * size, (rnd.group + 1) * size)
        alive = storage.tag[rnd.start:length, cols] == index          # (L, G) this round's steps
        last = np.flatnonzero(alive.any(axis=1)).max() + 1
        alive = alive[:last]
        rewards = np.where(alive, storage.rewards[rnd.start:rnd.start + last, cols], 0.0)
        if hp.advantage == "return":
            discounts = hp.gamma ** np.arange(last)[:, None]
            returns = (rewards * discounts).sum(axis=0)                 # (G,)
            adv = np.broadcast_to(group_relative_advantages(returns[None])[0], alive.shape)
        else:
            adv = group_relative_step_advantages(reward_to_go(rewards, ~alive, hp.gamma), alive)
        block = advantages[rnd.start:rnd.start + last, cols]
        block[alive] = adv[alive]
    return advantages


def grpo_loss(log_prob: torch.Tensor, old_log_prob: torch.Tensor, advantages: torch.Tensor, clip_coef: float,
              kl_coef: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Clipped surrogate + kl_coef * KL(pi_old || pi_theta) (k3 estimator). Shapes (B,).
    Returns (loss, kl)."""
    pg_loss, _ = clipped_surrogate_loss(log_prob, old_log_prob, advantages, clip_coef)
    kl = approx_kl(log_prob - old_log_prob)
    return pg_loss + kl_coef * kl, kl


def update(agent: ActorCritic, optimizer: torch.optim.Optimizer, batch: GroupBatch, hp: Params) -> dict[str, torch.Tensor]:
    """``update_epochs`` passes of minibatch steps on :func:`grpo_loss` minus the entropy bonus
    over the B recorded steps; returns the means of the logged statistics (0-d tensors)."""
    size = batch.obs.shape[0]
    minibatch = max(1, size // hp.num_minibatches)
    stats = torch.zeros(3, device=batch.obs.device)
    steps = 0
    for _ in range(hp.update_epochs):
        order = torch.randperm(size)
        for start in range(0, size - minibatch + 1, minibatch):
            idx = order[start:start + minibatch]
            dist = agent.distribution(batch.obs[idx])
            loss, kl = grpo_loss(dist.log_prob(batch.actions[idx]), batch.log_probs[idx], batch.advantages[idx],
                                 hp.clip_coef, hp.kl_coef)
            entropy = dist.entropy().mean()
            loss = loss - hp.ent_coef * entropy
            gradient_step(optimizer, loss, agent.parameters(), hp.max_grad_norm)
            stats += torch.stack([loss, kl, entropy]).detach()
            steps += 1
    mean = stats / max(steps, 1)
    return {"loss/policy": mean[0], "loss/approx_kl": mean[1], "loss/entropy": mean[2]}


def train(cfg: TrainConfig, run: Run) -> None:
    hp: Params = cfg.algo_params
    envs = make_vector_env(cfg.env, autoreset_mode=AutoresetMode.DISABLED, on_restart=run.note_env_restart)
    obs_space, act_space = envs.single_observation_space, envs.single_action_space
    agent = build_policy(cfg, obs_space, act_space).to(run.device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)
    run.start({"policy": agent}, {"policy": optimizer}, policy=agent)
    storage = EpisodeStorage(2 * -(-hp.batch_steps // envs.num_envs), envs.num_envs, obs_space, act_space)
    try:
        while not run.done:
            if hp.anneal_lr:
                set_learning_rate(optimizer, linear_decay(hp.lr, run.step, cfg.steps))
            std_log = limit_log_std(agent.actor, hp, run.step, cfg.steps)  # optional std schedule
            # 1. Group rounds (members of a group share a start seed) until batch_steps are recorded
            #    (the last batch: the steps left; its rounds in flight still end).
            budget = min(hp.batch_steps, run.steps_left)
            rounds, steps, length = collect_group_rounds(envs, agent, storage, hp, run, budget)
            # 2. Each recorded step's advantage relative to its group: no critic.
            advantages = group_advantages(storage, rounds, length, hp)
            mask = storage.recorded[:length]
            batch = GroupBatch(*(torch.as_tensor(x[:length][mask], device=run.device)
                                 for x in (storage.obs, storage.actions, storage.log_probs)),
                               advantages=torch.as_tensor(advantages[mask], device=run.device))
            # 3. Clipped-ratio epochs, as PPO's, without a value loss.
            with run.timing.update:
                run.record(update(agent, optimizer, batch, hp))
            if agent.obs_rms is not None:
                agent.obs_rms.update(batch.obs.float())
            run.record({"batch/rounds": len(rounds), "batch/steps": steps,
                        "batch/zero_advantage_fraction": float((advantages[mask] == 0).mean()), **std_log})
            run.end_iteration(steps)
    finally:
        envs.close()
