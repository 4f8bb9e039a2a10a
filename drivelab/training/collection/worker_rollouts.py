"""Rollouts played inside the env workers, each with its own copy of the policy (``act_in_workers``
of A2C and PPO, and of DDPG, TD3 and SAC; the rollout workers of RLlib, which MetaDrive's
reference training uses).

Stepping the envs from the trainer costs a round trip per step: the worker sends its
observation, waits while the trainer runs the policy, and receives the action. On a small
machine that round trip is dear: the worker idles through the trainer's inference, and the
trainer's inference, pickling and wake-ups take CPU from the simulators (``benchmarks/throughput.py``
measures both ways).

Here each env worker holds the policy's network. Once per rollout the trainer sends the current
weights (``collect``); the worker plays T steps on its own (sampling from its own generator,
seeded by the env's reset seed, so a rollout does not depend on timing) and returns what the
rollout buffer needs, including the values for GAE (with a cost critic, also each step's cost and
V_c for the cost's GAE). Episodes end as in ``AutoresetMode.SAME_STEP``
(:mod:`drivelab.training.collection.rollout`): a terminated step bootstraps nothing, a truncated one from
V(final observation), computed in the worker with the same weights.

The off-policy algorithms use :class:`ActorInWorker`: a worker plays a chunk of steps with a copy
of the actor and its exploration, and returns the transitions (s, a, r, s', terminated,
truncated, and the step's cost) for the replay buffer, while the learner updates
(:mod:`drivelab.training.collection.replay`).

Evaluation uses :class:`EpisodesInWorker`: a worker plays whole evaluation episodes with a copy of
the policy, each reset with its own seed, and returns each episode's return, length and metrics
(:func:`drivelab.training.collection.evaluation.run_episodes_in_workers`).
"""

from __future__ import annotations

import pickle
from collections import deque
from collections.abc import Callable
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch

from drivelab.training.collection.checks import check_finite_step
from drivelab.training.collection.exploration import Exploration
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent
from drivelab.training.learning.policy_nets import ActorCritic, sample
from drivelab.training.outputs.episodes import DRIVING_METRICS, is_episode_metric


class WorkerRollout(NamedTuple):
    """T steps of one env, played by its worker (numpy: what crosses the pipe)."""
    obs: np.ndarray           # (T, *obs_shape) observations the actions were chosen for
    actions: np.ndarray       # (T,) Discrete, (T, act_dim) Box: the sampled (unclipped) actions
    log_probs: np.ndarray     # (T,) log pi(a|s)
    values: np.ndarray        # (T,) V(s)
    rewards: np.ndarray       # (T,)
    terminated: np.ndarray    # (T,) bool
    truncated: np.ndarray     # (T,) bool
    final_values: np.ndarray  # (T,) V(final observation) where a time limit cut the episode, else 0
    last_value: float         # V of the observation after step T (where the next rollout starts)
    episode_info: dict[int, dict[str, float]]  # step t -> driving metrics of the episode that ended there
    # with a cost critic (PPO-Lagrangian), the same for the cost; None otherwise
    costs: np.ndarray | None = None              # (T,) the step's info["cost"]
    cost_values: np.ndarray | None = None        # (T,) V_c(s)
    final_cost_values: np.ndarray | None = None  # (T,) V_c(final observation) where a time limit cut the episode
    last_cost_value: float | None = None         # V_c of the observation after step T


class PolicyInWorker(gym.Wrapper):
    """Wraps the env in its worker process; :meth:`rollout` plays T steps with a local policy.

    ``make_policy(observation_space, action_space)`` builds the network (the algorithm's own
    ``build_policy``); the weights come with every rollout. The env is reset by the trainer
    (through the vector env) once, and by the wrapper itself after every episode end.
    """

    def __init__(self, env: gym.Env, make_policy: Callable[[gym.Space, gym.Space], ActorCritic]):
        super().__init__(env)
        self.make_policy = make_policy
        self.policy: ActorCritic | None = None
        self.generator = torch.Generator()
        self.obs: np.ndarray | None = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self.generator.manual_seed(seed)
        self.obs = obs
        return obs, info

    @torch.no_grad()
    def rollout(self, weights: dict[str, np.ndarray], num_steps: int) -> WorkerRollout:
        if self.policy is None:
            torch.set_num_threads(1)  # one core per worker: the workers share the machine
            self.policy = self.make_policy(self.observation_space, self.action_space)
        self.policy.load_state_dict({name: torch.from_numpy(value) for name, value in weights.items()})
        discrete = self.policy.discrete
        critics = 1 if self.policy.cost_critic is None else 2  # column 0: V, column 1: V_c
        obs_buf = np.zeros((num_steps, *self.observation_space.shape), self.observation_space.dtype)
        actions = np.zeros((num_steps,) if discrete else (num_steps, *self.action_space.shape),
                           np.int64 if discrete else np.float32)
        # policy outputs stay tensors (row writes, no per-step .item()); numpy once at the end
        log_probs = torch.zeros(num_steps)
        values, final_values = torch.zeros(num_steps, critics), torch.zeros(num_steps, critics)
        rewards, costs = np.zeros(num_steps, np.float32), np.zeros(num_steps, np.float32)
        terminated, truncated = np.zeros(num_steps, bool), np.zeros(num_steps, bool)
        episode_info = {}
        for t in range(num_steps):
            obs_buf[t] = self.obs
            dist, value = self.policy.distribution_and_value(torch.as_tensor(self.obs).unsqueeze(0))
            action = sample(dist, self.generator)
            actions[t], log_probs[t], values[t, 0] = action[0].numpy(), dist.log_prob(action)[0], value[0]
            if critics == 2:
                values[t, 1] = self.policy.cost_value(torch.as_tensor(self.obs).unsqueeze(0))[0]
            obs, rewards[t], terminated[t], truncated[t], info = self.env.step(self.policy.to_env(action)[0])
            check_finite_step(obs[None], rewards[t:t + 1], None)  # before the policy acts on obs
            costs[t] = info.get("cost", 0.0)  # the step's own info: this wrapper resets the env itself
            if terminated[t] or truncated[t]:
                if truncated[t] and not terminated[t]:  # a time limit: the state had a future
                    final_values[t] = self._values(obs)
                episode_info[t] = {key: float(x) for key, x in info.items() if is_episode_metric(key)}
                obs, _ = self.env.reset()
            self.obs = obs
        last = self._values(self.obs).tolist()
        values, final_values = values.numpy(), final_values.numpy()
        rollout = WorkerRollout(obs_buf, actions, log_probs.numpy(), values[:, 0], rewards, terminated, truncated,
                                final_values[:, 0], last[0], episode_info)
        if critics == 1:
            return rollout
        return rollout._replace(costs=costs, cost_values=values[:, 1], final_cost_values=final_values[:, 1],
                                last_cost_value=last[1])

    def _values(self, obs: np.ndarray) -> torch.Tensor:
        """(critics,) V(obs), and V_c(obs) with a cost critic."""
        obs = torch.as_tensor(obs).unsqueeze(0)
        if self.policy.cost_critic is None:
            return self.policy.value(obs)
        return torch.cat([self.policy.value(obs), self.policy.cost_value(obs)])


class WorkerTransitions(NamedTuple):
    """T consecutive transitions of one env, played by its worker (numpy: what crosses the pipe).
    Row t is (s_t, a_t, r_t, s'_t, terminated_t, truncated_t); at an episode end s'_t is the
    episode's final observation and row t + 1 starts the next episode."""
    obs: np.ndarray           # (T, *obs_shape)
    actions: np.ndarray       # (T, act_dim) in the policy's [-1, 1] units
    rewards: np.ndarray       # (T,)
    next_obs: np.ndarray      # (T, *obs_shape)
    terminated: np.ndarray    # (T,) bool
    truncated: np.ndarray     # (T,) bool
    episode_info: dict[int, dict[str, float]]  # step t -> driving metrics of the episode that ended there
    costs: np.ndarray | None = None  # (T,) the step's info["cost"] (0 where the env reports none)


class ActorInWorker(gym.Wrapper):
    """Wraps the env in its worker process; :meth:`play` plays T steps with a local copy of an
    off-policy actor and its exploration, the env resetting itself after every episode end.

    ``make_agent(observation_space, action_space)`` builds the network (the algorithm's own
    ``build_policy``); the actor's weights come with every chunk. ``make_exploration(1, act_dim,
    seed)`` builds a one-env exploration (:class:`Exploration`). The trainer resets the env through the
    vector env with a seed; that seed also seeds this worker's exploration noise, its heat-up
    actions and its torch generator (SAC samples with it), so what a worker plays depends on
    the seed and the weights, never on timing.
    """

    def __init__(self, env: gym.Env, make_agent: Callable[[gym.Space, gym.Space], OffPolicyAgent],
                 make_exploration: Callable[[int, int, int], Exploration]):
        super().__init__(env)
        self.make_agent, self.make_exploration = make_agent, make_exploration
        self.agent: OffPolicyAgent | None = None
        self.exploration: Exploration | None = None
        self.rng = np.random.default_rng()
        self.obs: np.ndarray | None = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self.rng = np.random.default_rng(seed)
            torch.manual_seed(seed)  # this process's own generator: SAC's samples
            self.exploration = self.make_exploration(1, self.action_space.shape[0], seed)
        self.obs = obs
        return obs, info

    @torch.no_grad()
    def play(self, weights: dict[str, np.ndarray], num_steps: int, step: int, step_stride: int,
             heat_up: bool) -> WorkerTransitions:
        """T = ``num_steps`` transitions: uniform random actions when ``heat_up``, else the
        exploration's, whose schedule sees env step ``step + t * step_stride`` at row t
        (``step_stride`` = N envs, as when the trainer steps them together)."""
        if self.agent is None:
            torch.set_num_threads(1)  # one core per worker: the workers share the machine
            self.agent = self.make_agent(self.observation_space, self.action_space)
        self.agent.load_state_dict({name: torch.from_numpy(value) for name, value in weights.items()}, strict=False)
        obs_buf = np.zeros((num_steps, *self.observation_space.shape), self.observation_space.dtype)
        next_obs_buf = np.zeros_like(obs_buf)
        actions = np.zeros((num_steps, *self.action_space.shape), np.float32)
        rewards, costs = np.zeros(num_steps, np.float32), np.zeros(num_steps, np.float32)
        terminated, truncated = np.zeros(num_steps, bool), np.zeros(num_steps, bool)
        episode_info = {}
        for t in range(num_steps):
            obs_buf[t] = self.obs
            if heat_up:
                actions[t] = self.rng.uniform(-1.0, 1.0, size=actions.shape[1:])
            else:
                actions[t] = self.exploration(self.agent, torch.as_tensor(self.obs).unsqueeze(0), step + t * step_stride)[0]
            obs, rewards[t], terminated[t], truncated[t], info = self.env.step(
                self.agent.to_env(torch.as_tensor(actions[t]).unsqueeze(0))[0])
            check_finite_step(obs[None], rewards[t:t + 1], None)
            next_obs_buf[t] = obs
            costs[t] = info.get("cost", 0.0)  # the step's own info: this wrapper resets the env itself
            if terminated[t] or truncated[t]:
                episode_info[t] = {key: float(x) for key, x in info.items() if is_episode_metric(key)}
                self.exploration.end_episodes(np.ones(1, bool))
                obs, _ = self.env.reset()
            self.obs = obs
        return WorkerTransitions(obs_buf, actions, rewards, next_obs_buf, terminated, truncated, episode_info, costs)


class WorkerEpisode(NamedTuple):
    """One evaluation episode, played whole by a worker (what crosses the pipe)."""
    seed: int                     # the seed the env was reset with: which episode it was
    ret: float                    # undiscounted return, summed step by step as EpisodeTracker sums it
    length: int
    metrics: dict[str, float]     # driving metrics and reward-term sums, under their logged names


class EpisodesInWorker(gym.Wrapper):
    """Wraps the env in its worker process; plays evaluation episodes with a local copy of the policy.

    :meth:`start_episodes` hands the worker the policy and the seeds of the episodes it plays, in
    order; each :meth:`play_episodes` then plays up to T more decisions and returns the episodes
    that ended. The worker resets the env itself, with each episode's seed. ``inner`` (a baseline's
    observation wrapper, see :mod:`drivelab.tools.baselines`) goes on the env first.
    """

    def __init__(self, env: gym.Env, inner: Callable[[gym.Env], gym.Env] | None = None):
        super().__init__(inner(env) if inner is not None else env)
        self.policy = None
        self.deterministic = True
        self.seeds: deque[int] = deque()        # the episodes still to start
        self.obs: np.ndarray | None = None      # None between episodes
        self.episode_seed, self.ret, self.length = 0, 0.0, 0

    def start_episodes(self, policy: bytes, deterministic: bool, seeds: list[int]) -> None:
        """Take the pickled policy (``act(obs, deterministic)``, ``to_env(action)``) and the seeds
        of the episodes to play; any episode in progress is dropped."""
        torch.set_num_threads(1)  # one core per worker: the workers share the machine
        # bytes this run pickled a moment ago in its own process (play), never read from a file
        self.policy, self.deterministic = pickle.loads(policy), deterministic
        self.seeds, self.obs = deque(seeds), None

    @torch.no_grad()
    def play_episodes(self, num_steps: int) -> list[WorkerEpisode]:
        """Play up to ``num_steps`` decisions (fewer when the last episode ends); returns the
        episodes that ended, oldest first."""
        ended = []
        for _ in range(num_steps):
            if self.obs is None:
                if not self.seeds:
                    break
                self.episode_seed, self.ret, self.length = self.seeds.popleft(), 0.0, 0
                obs, _ = self.env.reset(seed=self.episode_seed)
                self.obs = self._as_space(obs)
            action = self.policy.act(torch.as_tensor(self.obs).unsqueeze(0), deterministic=self.deterministic)
            obs, reward, terminated, truncated, info = self.env.step(self.policy.to_env(action)[0])
            self.ret += float(reward)
            self.length += 1
            self.obs = self._as_space(obs)
            if terminated or truncated:
                metrics = {DRIVING_METRICS.get(key, key): float(x) for key, x in info.items() if is_episode_metric(key)}
                ended.append(WorkerEpisode(self.episode_seed, self.ret, self.length, metrics))
                self.obs = None
        return ended

    def _as_space(self, obs) -> np.ndarray:
        """The observation in the space's dtype, as a vector env hands it to the trainer (an env may
        return float64 for a float32 space): the policy then computes what it computes in-process."""
        return np.asarray(obs, dtype=self.observation_space.dtype)
