"""Fixed-length rollouts for actor-critic methods (A2C, PPO): T steps in each of N envs.

The envs run with Gymnasium's ``AutoresetMode.SAME_STEP``: when an episode ends at step t, the
returned observation is already the first one of the next episode, and the true last
observation is in ``info["final_obs"]``. This lets every step of the rollout be a real
transition (NEXT_STEP, Gymnasium 1.x's default, spends one step per episode on a reset whose
action is ignored) and makes the two kinds of episode end explicit:

* ``terminated``: a terminal state (crash, goal, pole fell) has no future: V(s_{t+1}) = 0.
* ``truncated``: a time limit cut the episode; the state had a future, so the advantage
  bootstraps from V(final_obs) (Pardo et al. 2018, "Time Limits in Reinforcement Learning").
"""

from __future__ import annotations

import time
from typing import Callable, NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from drivelab.envs import make_vector_env
from drivelab.episodes import episode_info
from drivelab.nets import ActorCritic
from drivelab.normalize import RunningMeanStd
from drivelab.returns import gae
from drivelab.run import iteration_timing


class RolloutBatch(NamedTuple):
    """A rollout flattened to B = T * N samples for the update."""
    obs: torch.Tensor         # (B, *obs_shape)
    actions: torch.Tensor     # (B,) Discrete, (B, act_dim) Box
    log_probs: torch.Tensor   # (B,) log pi_old(a|s)
    values: torch.Tensor      # (B,) V_old(s)
    advantages: torch.Tensor  # (B,)
    returns: torch.Tensor     # (B,) critic targets (advantages + values)


class RolloutBuffer:
    """Preallocated (T, N, ...) storage, written in place every step."""

    def __init__(self, num_steps: int, num_envs: int, obs_space: gym.Space, act_space: gym.Space,
                 device: torch.device):
        discrete = isinstance(act_space, gym.spaces.Discrete)
        obs_dtype = torch.uint8 if obs_space.dtype == np.uint8 else torch.float32
        shape = (num_steps, num_envs)
        self.obs = torch.zeros(shape + obs_space.shape, dtype=obs_dtype, device=device)
        self.actions = torch.zeros(shape + (() if discrete else act_space.shape),
                                   dtype=torch.long if discrete else torch.float32, device=device)
        self.log_probs = torch.zeros(shape, device=device)
        self.values = torch.zeros(shape, device=device)
        # Rewards and episode ends stay in numpy: GAE is a pure numpy function (drivelab.returns).
        self.rewards = np.zeros(shape, np.float32)
        self.next_values = np.zeros(shape, np.float32)
        self.terminated = np.zeros(shape, bool)
        self.dones = np.zeros(shape, bool)

    def batch(self, gamma: float, gae_lambda: float) -> RolloutBatch:
        advantages, returns = gae(self.rewards, self.values.cpu().numpy(), self.next_values, self.terminated,
                                  self.dones, gamma, gae_lambda)
        device = self.values.device
        return RolloutBatch(
            obs=self.obs.flatten(0, 1), actions=self.actions.flatten(0, 1), log_probs=self.log_probs.flatten(),
            values=self.values.flatten(), advantages=torch.as_tensor(advantages, device=device).flatten(),
            returns=torch.as_tensor(returns, device=device).flatten(),
        )


class RolloutCollector:
    """Steps N envs for T steps at a time, keeping their episodes running across rollouts.

    Tracks the time spent stepping envs (``env_seconds``) so trainers can report their own
    overhead; episode returns/lengths/driving metrics go to ``run.stats``.
    """

    def __init__(self, envs: VectorEnv, run, gamma: float, scale_rewards: bool):
        self.envs, self.run, self.gamma = envs, run, gamma
        n = envs.num_envs
        self.obs, _ = envs.reset(seed=run.reset_seeds(np.ones(n, bool)))
        self.episode_return = np.zeros(n)
        self.episode_length = np.zeros(n, np.int64)
        # Reward scaling (Engstrom et al. 2020): divide rewards by the running std of the
        # discounted return, so the critic's targets keep a stable scale.
        self.reward_rms = RunningMeanStd(()) if scale_rewards else None
        self.discounted_return = np.zeros(n)
        self.env_seconds = 0.0

    @torch.no_grad()
    def collect(self, agent: ActorCritic, buf: RolloutBuffer) -> int:
        """Fill ``buf`` with T steps; returns the number of env steps taken (T * N)."""
        device = buf.values.device
        num_steps = buf.rewards.shape[0]
        for t in range(num_steps):
            obs = torch.as_tensor(self.obs, device=device)
            dist = agent.distribution(obs)
            action = dist.sample()
            buf.obs[t] = obs
            buf.actions[t] = action
            buf.log_probs[t] = dist.log_prob(action)
            buf.values[t] = agent.value(obs)

            started = time.perf_counter()
            self.obs, reward, terminated, truncated, info = self.envs.step(agent.to_env(action))
            self.env_seconds += time.perf_counter() - started

            done = terminated | truncated
            self._record_episodes(reward, done, info)
            buf.rewards[t] = reward
            buf.terminated[t] = terminated
            buf.dones[t] = done
            # V(s_{t+1}) for GAE: the next row's value inside an episode (filled below), the
            # value of the final observation where a time limit cut the episode.
            cut = truncated & ~terminated
            if cut.any():
                final_obs = np.stack(info["final_obs"][cut])
                buf.next_values[t, cut] = agent.value(torch.as_tensor(final_obs, device=device)).cpu().numpy()
        if self.reward_rms is not None:
            self._scale_rewards(buf)
        buf.next_values[:-1] = np.where(buf.dones[:-1], buf.next_values[:-1], buf.values[1:].cpu().numpy())
        last_value = agent.value(torch.as_tensor(self.obs, device=device)).cpu().numpy()
        buf.next_values[-1] = np.where(buf.dones[-1], buf.next_values[-1], last_value)
        return num_steps * self.envs.num_envs

    def _record_episodes(self, reward: np.ndarray, done: np.ndarray, info: dict) -> None:
        self.episode_return += reward
        self.episode_length += 1
        if done.any():
            final_info = info.get("final_info", {})
            for i in np.flatnonzero(done):
                self.run.stats.add(self.episode_return[i], self.episode_length[i], episode_info(final_info, i))
            self.episode_return[done] = 0.0
            self.episode_length[done] = 0

    def _scale_rewards(self, buf: RolloutBuffer) -> None:
        """Divide the rollout's rewards by the running std of the discounted return.

        The statistics are updated once per rollout (not per step: cheaper, and every reward
        of a rollout is scaled alike); the per-env discounted returns carry across rollouts.
        """
        returns = np.empty_like(buf.rewards, dtype=np.float64)
        for t in range(len(buf.rewards)):
            self.discounted_return = self.discounted_return * self.gamma + buf.rewards[t]
            returns[t] = self.discounted_return
            self.discounted_return[buf.dones[t]] = 0.0
        self.reward_rms.update(torch.as_tensor(returns.reshape(-1)))
        buf.rewards[:] = self.reward_rms.scale(torch.as_tensor(buf.rewards)).numpy()


def train_actor_critic(cfg, run, agent: ActorCritic, optimizer: torch.optim.Optimizer,
                       update: Callable[[RolloutBatch], dict[str, float]], log_every: int = 1) -> None:
    """The loop A2C and PPO share: collect T steps in each of N envs, update, log, checkpoint.

    ``update(batch)`` is the algorithm's own part: one gradient step (A2C) or epochs of
    minibatch steps (PPO). ``cfg.algo_params`` provides num_steps, gamma, gae_lambda, lr,
    anneal_lr and normalize_reward.
    """
    hp = cfg.algo_params
    envs = make_vector_env(cfg.env, autoreset_mode=AutoresetMode.SAME_STEP)
    collector = RolloutCollector(envs, run, hp.gamma, hp.normalize_reward)
    modules = {"policy": agent, **({"reward_rms": collector.reward_rms} if collector.reward_rms is not None else {})}
    optimizers = {"policy": optimizer}
    run.restore(modules, optimizers)
    run.checkpoint_if_due(modules, optimizers)
    buf = RolloutBuffer(hp.num_steps, envs.num_envs, envs.single_observation_space, envs.single_action_space,
                        run.device)
    try:
        while not run.done:
            if hp.anneal_lr:  # linear decay to 0 over the run (a function of the step, so resume-safe)
                optimizer.param_groups[0]["lr"] = hp.lr * max(0.0, 1.0 - run.step / cfg.steps)
            started = time.perf_counter()
            env_before = collector.env_seconds
            steps = collector.collect(agent, buf)
            collected = time.perf_counter()
            stats = update(buf.batch(hp.gamma, hp.gae_lambda))
            if agent.obs_rms is not None:  # after the update, so rollout and update saw the same statistics
                agent.obs_rms.update(buf.obs.flatten(0, 1).float())
            updated = time.perf_counter()
            run.iteration += 1
            run.advance(steps)
            if run.iteration % log_every == 0 or run.done:
                run.log({**stats, "charts/lr": optimizer.param_groups[0]["lr"],
                         **iteration_timing(started, collected, updated, collector.env_seconds - env_before)})
            run.checkpoint_if_due(modules, optimizers)
    finally:
        envs.close()


class EpisodeStorage:
    """Preallocated (T, N, ...) arrays for rollouts of whole episodes (REINFORCE, GRPO), whose
    length is not known in advance: T doubles when full, so growth is rare and amortised.

    ``recorded[t, i]`` marks the steps that belong to the batch (envs that finished their share
    keep stepping, masked, until the others are done); ``tag[t, i]`` is free for the trainer
    (GRPO stores the group round of each step).
    """

    def __init__(self, capacity: int, num_envs: int, obs_space: gym.Space, act_space: gym.Space):
        discrete = isinstance(act_space, gym.spaces.Discrete)
        shape = (capacity, num_envs)
        self.obs = np.zeros(shape + obs_space.shape, obs_space.dtype)
        self.actions = np.zeros(shape + (() if discrete else act_space.shape), np.int64 if discrete else np.float32)
        self.log_probs = np.zeros(shape, np.float32)
        self.rewards = np.zeros(shape, np.float32)
        self.dones = np.zeros(shape, bool)
        self.recorded = np.zeros(shape, bool)
        self.tag = np.full(shape, -1, np.int64)

    def ensure(self, t: int) -> None:
        """Make row t writable."""
        if t < len(self.rewards):
            return
        for name in ("obs", "actions", "log_probs", "rewards", "dones", "recorded", "tag"):
            old = getattr(self, name)
            grown = np.zeros((2 * len(old), *old.shape[1:]), old.dtype)
            grown[: len(old)] = old
            setattr(self, name, grown)
