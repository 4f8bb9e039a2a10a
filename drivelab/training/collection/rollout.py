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

For the constrained algorithms (PPO-Lagrangian) the collector also stores each step's cost
(``info["cost"]``, :func:`~drivelab.training.outputs.episodes.step_costs`) and the cost critic's
V_c, with the same two kinds of end, and returns the cost's GAE beside the reward's.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.config import EnvConfig, TrainConfig
from drivelab.envs.groups import EnvGroups
from drivelab.training.collection.checks import check_finite_step
from drivelab.training.collection.worker_rollouts import PolicyInWorker, WorkerRollout
from drivelab.training.learning.hyperparams import ActorCriticParams
from drivelab.training.learning.normalize import RewardScaler
from drivelab.training.learning.policy_nets import ActorCritic, sample
from drivelab.training.learning.rollout_buffers import RolloutBatch, RolloutBuffer
from drivelab.training.outputs.episodes import stack_infos, step_costs

if TYPE_CHECKING:  # the collector calls the run's services; run/ sits above collection/
    from drivelab.training.run import Run


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
    builds and the trainer's weights of the moment (:mod:`drivelab.training.collection.worker_rollouts`): no round
    trip per step. The buffer is filled as if the trainer had stepped the envs.

    Episode returns, lengths and driving metrics go to ``run.episodes``; time spent waiting on
    the envs to ``run.timing.env``. With ``scale_rewards`` the rewards are divided by the running
    std of the discounted return (:class:`~drivelab.training.learning.normalize.RewardScaler`);
    its statistics are a module (``reward_rms``) to checkpoint with the agent. With ``cost_gamma``
    (a cost critic) the costs and V_c are stored too, for the cost's own GAE; costs are never scaled.
    """

    def __init__(self, env_cfg: EnvConfig, run: Run, *, num_steps: int, gamma: float, gae_lambda: float,
                 scale_rewards: bool, policy_factory: Callable[[gym.Space, gym.Space], ActorCritic] | None = None,
                 cost_gamma: float | None = None):
        # act_in_workers (the config checks that the envs are subprocesses stepping together)
        wrapper = functools.partial(PolicyInWorker, make_policy=policy_factory) if policy_factory else None
        self.act_in_workers = policy_factory is not None
        self.step_timeout = env_cfg.step_timeout
        self.envs = EnvGroups(env_cfg, env_cfg.resolved_step_groups(), autoreset_mode=AutoresetMode.SAME_STEP,
                              on_restart=run.note_env_restart, wrapper=wrapper)
        self.run, self.gamma, self.gae_lambda, self.cost_gamma = run, gamma, gae_lambda, cost_gamma
        n = env_cfg.num_envs
        self.obs_space, self.act_space = self.envs.single_observation_space, self.envs.single_action_space
        self.buffer = RolloutBuffer(num_steps, n, self.obs_space, self.act_space, run.device, cost_gamma is not None)
        self.steps_per_rollout = num_steps * n
        self.obs = self.envs.reset(run.reset_seeds(np.ones(n, bool)))
        self.generators: list[torch.Generator | None] = [None]
        if len(self.envs) > 1:
            seeds = run.rng.integers(0, 2**63 - 1, size=len(self.envs)).tolist()
            self.generators = [torch.Generator(run.device).manual_seed(seed) for seed in seeds]
        self.reward_scaler = RewardScaler(n, gamma) if scale_rewards else None

    @classmethod
    def from_config(cls, cfg: TrainConfig, run: Run,
                    build_policy: Callable[[TrainConfig, gym.Space, gym.Space], ActorCritic],
                    costs: bool = False) -> RolloutCollector:
        """The collector an actor-critic config (``cfg.algo_params``, :class:`ActorCriticParams`) asks
        for: T = ``num_steps``, GAE(``gamma``, ``gae_lambda``), reward scaling with
        ``normalize_reward``, and with ``act_in_workers`` env workers that build their copy of the
        policy with ``build_policy(cfg, obs_space, act_space)``; with ``costs``, GAE(``cost_gamma``) of the costs."""
        hp: ActorCriticParams = cfg.algo_params
        return cls(cfg.env, run, num_steps=hp.num_steps, gamma=hp.gamma, gae_lambda=hp.gae_lambda,
                   scale_rewards=hp.normalize_reward,
                   policy_factory=functools.partial(build_policy, cfg) if hp.act_in_workers else None,
                   cost_gamma=hp.cost_gamma if costs else None)

    def modules(self) -> dict[str, torch.nn.Module]:
        """What a checkpoint must keep of the collector (the reward-scaling statistics)."""
        return {"reward_rms": self.reward_scaler.rms} if self.reward_scaler is not None else {}

    @torch.no_grad()
    def collect(self, agent: ActorCritic) -> RolloutBatch:
        """Fill the buffer with T steps of ``agent`` in each env; return them with GAE(lambda)
        advantages as a flat batch of B = T * N samples."""
        buf = self.buffer
        if self.act_in_workers:
            last_value, last_cost_value = self._play_in_workers(agent, buf)
        else:
            self._play(agent, buf)
            obs = torch.as_tensor(self.obs, device=buf.values.device)
            last_value, last_cost_value = _values(agent, obs, costs=buf.costs is not None)
        if self.reward_scaler is not None:
            self.reward_scaler.scale_in_place(buf.rewards, buf.dones)
        _next_values(buf.next_values, buf.values, last_value, buf.dones)
        if buf.costs is not None:
            _next_values(buf.cost_next_values, buf.cost_values, last_cost_value, buf.dones)
        return buf.batch(self.gamma, self.gae_lambda, self.cost_gamma)

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
            check_finite_step(obs, reward, self.run.step, first_env=envs.start)
            self.obs[envs] = obs
            done = terminated | truncated
            self.run.episodes.step(reward, done, info, first_env=envs.start)
            buf.rewards[t, envs] = reward
            if buf.costs is not None:
                buf.costs[t, envs] = step_costs(info, done)
            buf.terminated[t, envs] = terminated
            buf.dones[t, envs] = done
            # V(s_{t+1}) for GAE: the next row's value inside an episode (filled below), the
            # value of the final observation where a time limit cut the episode.
            cut = truncated & ~terminated
            if cut.any():
                final_obs = torch.as_tensor(np.stack(info["final_obs"][cut]), device=buf.values.device)
                buf.next_values[t, envs][cut] = agent.value(final_obs).cpu().numpy()
                if buf.costs is not None:
                    buf.cost_next_values[t, envs][cut] = agent.cost_value(final_obs).cpu().numpy()
            row[group] = t + 1
            if t + 1 < num_steps:
                self._act(agent, group, t + 1)
            else:
                in_flight.remove(group)

    def _play_in_workers(self, agent: ActorCritic, buf: RolloutBuffer) -> tuple[np.ndarray, np.ndarray | None]:
        """Each env's worker plays the T steps with a copy of ``agent``; their data go into
        ``buf`` and the episode bookkeeping. Returns the (N,) values of the observations after
        the last step, and their (N,) cost values (None without costs). A worker that fails
        restarts them all and the rollout is played anew."""
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
        return _take_rollouts(rollouts, buf, self.run)

    def _act(self, agent: ActorCritic, group: int, t: int) -> None:
        """Sample the group's actions for its current observations, send them, and store row t
        (observation, action, log-prob, V(s_t), and V_c(s_t) with costs) while the group's envs simulate."""
        buf, envs = self.buffer, self.envs.slices[group]
        obs = torch.as_tensor(self.obs[envs], device=buf.values.device)
        dist, value = agent.distribution_and_value(obs)
        action = sample(dist, self.generators[group % len(self.generators)])
        self.envs.send(group, agent.to_env(action))
        buf.obs[t, envs] = obs
        buf.actions[t, envs] = action
        buf.log_probs[t, envs] = dist.log_prob(action)
        buf.values[t, envs] = value
        if buf.costs is not None:
            buf.cost_values[t, envs] = agent.cost_value(obs)

    def close(self) -> None:
        self.envs.close()


def _values(agent: ActorCritic, obs: torch.Tensor, costs: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(n,) V(obs), and with ``costs`` (n,) V_c(obs) (else None)."""
    return agent.value(obs).cpu().numpy(), agent.cost_value(obs).cpu().numpy() if costs else None


def _take_rollouts(rollouts: list[WorkerRollout], buf: RolloutBuffer, run: Run) -> tuple[np.ndarray, np.ndarray | None]:
    """Write the env workers' rollouts into ``buf`` and count their episodes step by step, as if
    the trainer had stepped the envs; returns the (N,) values after the last step (and cost values)."""
    for env, rollout in enumerate(rollouts):
        check_finite_step(rollout.obs[None], rollout.rewards[None], run.step, first_env=env)
        buf.write_env(env, rollout)
    for t in range(len(buf.rewards)):
        info = stack_infos([rollout.episode_info.get(t, {}) for rollout in rollouts]) if buf.dones[t].any() else {}
        run.episodes.step(buf.rewards[t], buf.dones[t], info)
    last_cost_value = np.array([r.last_cost_value for r in rollouts], np.float32) if buf.costs is not None else None
    return np.array([rollout.last_value for rollout in rollouts], np.float32), last_cost_value


def _next_values(next_values: np.ndarray, values: torch.Tensor, last_value: np.ndarray, dones: np.ndarray) -> None:
    """Complete the (T, N) V(s_{t+1}) for GAE in place: the next row's value inside an episode and
    ``last_value`` (N,) after the rollout; where an episode ended, what the rollout stored (the
    value of the final observation on a truncation, ignored on a termination)."""
    next_values[:-1] = np.where(dones[:-1], next_values[:-1], values[1:].cpu().numpy())
    next_values[-1] = np.where(dones[-1], next_values[-1], last_value)
