"""Rollout parts of the on-policy family: fixed-length rollouts for actor-critic methods (A2C,
PPO), T steps in each of N envs, and growing storage for whole episodes (REINFORCE, GRPO).

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

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.config import EnvConfig, TrainConfig
from drivelab.envs.groups import EnvGroups
from drivelab.errors import DrivelabError
from drivelab.training.episodes import stack_infos
from drivelab.training.nets import ActorCritic, PolicyNetParams, sample
from drivelab.training.normalize import RunningMeanStd
from drivelab.training.returns import gae
from drivelab.training.run import Run
from drivelab.training.worker_rollouts import PolicyInWorker


@dataclass
class ActorCriticParams(PolicyNetParams):
    """Hyperparameters that A2C and PPO share (each file sets its own defaults where they differ)."""
    lr: float = 3e-4                  # learning rate (Adam)
    anneal_lr: bool = True        # linear decay to 0 over the run
    num_steps: int = 128          # rollout length T per env
    gamma: float = 0.99               # discount factor
    gae_lambda: float = 0.95          # GAE lambda (1: Monte-Carlo returns, 0: TD(0))
    norm_adv: bool = True         # standardise advantages (per minibatch)
    ent_coef: float = 0.0             # weight of the entropy bonus
    vf_coef: float = 0.5              # weight of the value loss
    max_grad_norm: float = 0.5        # clip the global gradient norm to this
    normalize_obs: bool = False   # running observation normalisation (saved with the weights)
    normalize_reward: bool = False  # divide rewards by the running std of the discounted return
    act_in_workers: bool = False  # each env subprocess plays the rollout with its own copy of the policy (see drivelab/training/worker_rollouts.py)

    def validate(self) -> None:
        super().validate()
        if self.num_steps < 1:
            raise DrivelabError(f"config field 'num_steps' must be >= 1, got {self.num_steps}")
        if not 0 <= self.gae_lambda <= 1 or not 0 <= self.gamma <= 1:
            raise DrivelabError("config fields 'gamma' and 'gae_lambda' must be in [0, 1]")

    def iteration_steps(self, num_envs: int) -> int:
        """Env steps of one iteration (a rollout of ``num_steps`` in each env): ``steps`` is
        rounded up to a multiple of it, so a run ends where its config says."""
        return self.num_steps * num_envs


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
        # Rewards and episode ends stay in numpy: GAE is a pure numpy function (drivelab.training.returns).
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
    """N envs (``AutoresetMode.SAME_STEP``) stepped T steps at a time into a preallocated
    :class:`RolloutBuffer`, their episodes running on across rollouts.

    The envs form ``env.step_groups`` groups (:class:`drivelab.envs.groups.EnvGroups`) that
    step on their own: each group fills its own columns of the buffer, row by row, and the
    collector serves whichever group answers first. Every group samples its actions from its
    own random generator, so a rollout's data do not depend on that order (with one group,
    torch's global generator, as before groups existed).

    With ``policy_factory`` (``act_in_workers``) the env subprocesses play the rollouts
    themselves, each with a copy of the policy that ``policy_factory(obs_space, act_space)``
    builds and the trainer's weights of the moment (:mod:`drivelab.training.worker_rollouts`): no round
    trip per step. The buffer is filled as if the trainer had stepped the envs.

    Episode returns, lengths and driving metrics go to ``run.episodes``; time spent waiting on
    the envs to ``run.timing.env``. With ``scale_rewards`` the rewards are divided by the running
    std of the discounted return (Engstrom et al. 2020), so the critic's targets keep a stable
    scale; its statistics are a module (``reward_rms``) to checkpoint with the agent.
    """

    def __init__(self, env_cfg: EnvConfig, run: Run, *, num_steps: int, gamma: float, gae_lambda: float,
                 scale_rewards: bool, policy_factory: Callable[[gym.Space, gym.Space], ActorCritic] | None = None):
        # act_in_workers (the config checks that the envs are subprocesses stepping together)
        wrapper = functools.partial(PolicyInWorker, make_policy=policy_factory) if policy_factory else None
        self.act_in_workers = policy_factory is not None
        self.step_timeout = env_cfg.step_timeout
        self.envs = EnvGroups(env_cfg, env_cfg.resolved_step_groups(), autoreset_mode=AutoresetMode.SAME_STEP,
                              on_restart=run.note_env_restart, wrapper=wrapper)
        self.run, self.gamma, self.gae_lambda = run, gamma, gae_lambda
        n = env_cfg.num_envs
        self.obs_space, self.act_space = self.envs.single_observation_space, self.envs.single_action_space
        self.buffer = RolloutBuffer(num_steps, n, self.obs_space, self.act_space, run.device)
        self.steps_per_rollout = num_steps * n
        self.obs = self.envs.reset(run.reset_seeds(np.ones(n, bool)))
        self.generators: list[torch.Generator | None] = [None]
        if len(self.envs) > 1:
            seeds = run.rng.integers(0, 2**63 - 1, size=len(self.envs)).tolist()
            self.generators = [torch.Generator(run.device).manual_seed(seed) for seed in seeds]
        self.reward_rms = RunningMeanStd(()) if scale_rewards else None
        self.discounted_return = np.zeros(n)

    @classmethod
    def from_config(cls, cfg: TrainConfig, run: Run,
                    build_policy: Callable[[TrainConfig, gym.Space, gym.Space], ActorCritic]) -> RolloutCollector:
        """The collector an actor-critic config (``cfg.algo_params``, :class:`ActorCriticParams`) asks
        for: T = ``num_steps``, GAE(``gamma``, ``gae_lambda``), reward scaling with
        ``normalize_reward``, and with ``act_in_workers`` env workers that build their copy of the
        policy with ``build_policy(cfg, obs_space, act_space)``."""
        hp: ActorCriticParams = cfg.algo_params
        return cls(cfg.env, run, num_steps=hp.num_steps, gamma=hp.gamma, gae_lambda=hp.gae_lambda,
                   scale_rewards=hp.normalize_reward,
                   policy_factory=functools.partial(build_policy, cfg) if hp.act_in_workers else None)

    def modules(self) -> dict[str, torch.nn.Module]:
        """What a checkpoint must keep of the collector (the reward-scaling statistics)."""
        return {"reward_rms": self.reward_rms} if self.reward_rms is not None else {}

    @torch.no_grad()
    def collect(self, agent: ActorCritic) -> RolloutBatch:
        """Fill the buffer with T steps of ``agent`` in each env; return them with GAE(lambda)
        advantages as a flat batch of B = T * N samples."""
        buf = self.buffer
        if self.act_in_workers:
            last_value = self._play_in_workers(agent, buf)
        else:
            self._play(agent, buf)
            last_value = agent.value(torch.as_tensor(self.obs, device=buf.values.device)).cpu().numpy()
        if self.reward_rms is not None:
            self._scale_rewards(buf)
        buf.next_values[:-1] = np.where(buf.dones[:-1], buf.next_values[:-1], buf.values[1:].cpu().numpy())
        buf.next_values[-1] = np.where(buf.dones[-1], buf.next_values[-1], last_value)
        return buf.batch(self.gamma, self.gae_lambda)

    def _play(self, agent: ActorCritic, buf: RolloutBuffer) -> None:
        """Step the env groups T steps with ``agent``, storing every step in ``buf``."""
        num_steps = len(buf.rewards)
        row = [0] * len(self.envs)             # the next row of each group
        for group in range(len(self.envs)):
            self._act(agent, group, 0)
        in_flight = list(range(len(self.envs)))
        while in_flight:
            with self.run.timing.env:
                group = self.envs.wait_any(in_flight)
                obs, reward, terminated, truncated, info = self.envs.receive(group)
            envs, t = self.envs.slices[group], row[group]
            self.obs[envs] = obs
            done = terminated | truncated
            self.run.episodes.step(reward, done, info, first_env=envs.start)
            buf.rewards[t, envs] = reward
            buf.terminated[t, envs] = terminated
            buf.dones[t, envs] = done
            # V(s_{t+1}) for GAE: the next row's value inside an episode (filled below), the
            # value of the final observation where a time limit cut the episode.
            cut = truncated & ~terminated
            if cut.any():
                final_obs = torch.as_tensor(np.stack(info["final_obs"][cut]), device=buf.values.device)
                buf.next_values[t, envs][cut] = agent.value(final_obs).cpu().numpy()
            row[group] = t + 1
            if t + 1 < num_steps:
                self._act(agent, group, t + 1)
            else:
                in_flight.remove(group)

    def _play_in_workers(self, agent: ActorCritic, buf: RolloutBuffer) -> np.ndarray:
        """Each env's worker plays the T steps with a copy of ``agent``; their data go into
        ``buf`` and the episode bookkeeping. Returns the (N,) values of the observations after
        the last step. A worker that fails restarts them all and the rollout is played anew."""
        num_steps, num_envs = buf.rewards.shape
        weights = {name: value.cpu().numpy() for name, value in agent.state_dict().items()}
        (envs,) = self.envs.envs
        while True:
            with self.run.timing.env:
                rollouts = envs.call_or_restart("rollout", weights, num_steps, steps=num_steps,
                                                timeout=self.step_timeout and self.step_timeout * num_steps)
            if rollouts is not None:
                break
            every_env = np.ones(num_envs, bool)
            self.run.episodes.restart(every_env)
            self.envs.reset(self.run.reset_seeds(every_env))
        device = buf.values.device
        for env, rollout in enumerate(rollouts):
            buf.obs[:, env] = torch.as_tensor(rollout.obs, device=device)
            buf.actions[:, env] = torch.as_tensor(rollout.actions, device=device)
            buf.log_probs[:, env] = torch.as_tensor(rollout.log_probs, device=device)
            buf.values[:, env] = torch.as_tensor(rollout.values, device=device)
            buf.rewards[:, env] = rollout.rewards
            buf.terminated[:, env] = rollout.terminated
            buf.dones[:, env] = rollout.terminated | rollout.truncated
            buf.next_values[:, env] = rollout.final_values
        # Episode bookkeeping step by step, as if the trainer had stepped the envs.
        for t in range(num_steps):
            info = stack_infos([rollout.episode_info.get(t, {}) for rollout in rollouts]) if buf.dones[t].any() else {}
            self.run.episodes.step(buf.rewards[t], buf.dones[t], info)
        return np.array([rollout.last_value for rollout in rollouts], np.float32)

    def _act(self, agent: ActorCritic, group: int, t: int) -> None:
        """Sample the group's actions for its current observations, send them, and store row t
        (observation, action, log-prob, V(s_t)) while the group's envs simulate."""
        buf, envs = self.buffer, self.envs.slices[group]
        obs = torch.as_tensor(self.obs[envs], device=buf.values.device)
        dist, value = agent.distribution_and_value(obs)
        action = sample(dist, self.generators[group % len(self.generators)])
        self.envs.send(group, agent.to_env(action))
        buf.obs[t, envs] = obs
        buf.actions[t, envs] = action
        buf.log_probs[t, envs] = dist.log_prob(action)
        buf.values[t, envs] = value

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

    def close(self) -> None:
        self.envs.close()


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
