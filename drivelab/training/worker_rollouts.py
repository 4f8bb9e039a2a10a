"""Rollouts played inside the env workers, each with its own copy of the policy (``act_in_workers``
of A2C and PPO; the rollout workers of RLlib, which MetaDrive's reference training uses).

Stepping the envs from the trainer costs a round trip per step: the worker sends its
observation, waits while the trainer runs the policy, and receives the action. On a small
machine that round trip is dear: the worker idles through the trainer's inference, and the
trainer's inference, pickling and wake-ups take CPU from the simulators (2 cores, 2 MetaDrive
workers: PPO trained at 70-80% of the envs' random-action speed, benchmarks/throughput.py).

Here each env worker holds the policy's network. Once per rollout the trainer sends the current
weights (``collect``); the worker plays T steps on its own (sampling from its own generator,
seeded by the env's reset seed, so a rollout does not depend on timing) and returns what the
rollout buffer needs, including the values for GAE. Episodes end as in ``AutoresetMode.SAME_STEP``
(:mod:`drivelab.training.rollout`): a terminated step bootstraps nothing, a truncated one from
V(final observation), computed in the worker with the same weights.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch

from drivelab.training.episodes import is_episode_metric
from drivelab.training.nets import ActorCritic, sample


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
        obs_buf = np.zeros((num_steps, *self.observation_space.shape), self.observation_space.dtype)
        actions = np.zeros((num_steps,) if discrete else (num_steps, *self.action_space.shape),
                           np.int64 if discrete else np.float32)
        # policy outputs stay tensors (row writes, no per-step .item()); numpy once at the end
        log_probs, values, final_values = (torch.zeros(num_steps) for _ in range(3))
        rewards = np.zeros(num_steps, np.float32)
        terminated, truncated = np.zeros(num_steps, bool), np.zeros(num_steps, bool)
        episode_info = {}
        for t in range(num_steps):
            obs_buf[t] = self.obs
            dist, value = self.policy.distribution_and_value(torch.as_tensor(self.obs).unsqueeze(0))
            action = sample(dist, self.generator)
            actions[t], log_probs[t], values[t] = action[0].numpy(), dist.log_prob(action)[0], value[0]
            obs, rewards[t], terminated[t], truncated[t], info = self.env.step(self.policy.to_env(action)[0])
            if terminated[t] or truncated[t]:
                if truncated[t] and not terminated[t]:  # a time limit: the state had a future
                    final_values[t] = self.policy.value(torch.as_tensor(obs).unsqueeze(0))[0]
                episode_info[t] = {key: float(x) for key, x in info.items() if is_episode_metric(key)}
                obs, _ = self.env.reset()
            self.obs = obs
        last_value = self.policy.value(torch.as_tensor(self.obs).unsqueeze(0)).item()
        return WorkerRollout(obs_buf, actions, log_probs.numpy(), values.numpy(), rewards, terminated, truncated,
                             final_values.numpy(), last_value, episode_info)
