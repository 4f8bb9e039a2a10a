"""How an off-policy collector picks its actions beyond the heat-up: noise on a deterministic
actor (DDPG, TD3: Gaussian or Ornstein-Uhlenbeck, with a linear schedule) or a sample of a
stochastic policy (SAC). All in the policy's [-1, 1] units; each keeps its state for checkpoints."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
import torch

from drivelab.training.learning.hyperparams import NoisyExplorationParams, OffPolicyParams
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent


class GaussianNoise:
    def __init__(self, num_envs: int, act_dim: int, rng: np.random.Generator):
        self.shape, self.rng = (num_envs, act_dim), rng

    def sample(self, std: float) -> np.ndarray:
        return std * self.rng.standard_normal(self.shape)

    def reset(self, mask: np.ndarray) -> None:
        pass


class OrnsteinUhlenbeckNoise:
    """Temporally correlated noise dx = theta (mu - x) dt + sigma sqrt(dt) dW, one process per
    env, restarted at episode ends (Lillicrap et al. 2016 used theta=0.15, dt=1e-2)."""

    def __init__(self, num_envs: int, act_dim: int, rng: np.random.Generator, theta: float = 0.15, dt: float = 1e-2):
        self.x = np.zeros((num_envs, act_dim))
        self.rng, self.theta, self.dt = rng, theta, dt

    def sample(self, std: float) -> np.ndarray:
        self.x += self.theta * -self.x * self.dt + std * math.sqrt(self.dt) * self.rng.standard_normal(self.x.shape)
        return self.x.copy()

    def reset(self, mask: np.ndarray) -> None:
        self.x[mask] = 0.0


class PolicySampling:
    """SAC's exploration: a sample of its own stochastic policy (no added noise), drawn with
    torch's generator of the process that acts."""

    def __init__(self, hp: OffPolicyParams, num_envs: int, act_dim: int, seed: int):
        pass

    def __call__(self, agent: OffPolicyAgent, obs: torch.Tensor, step: int) -> np.ndarray:
        return agent.act(obs).cpu().numpy()

    def end_episodes(self, done: np.ndarray) -> None:
        pass

    def state(self) -> dict:
        return {}

    def load_state(self, state: dict) -> None:
        pass


class NoisyExploration:
    """a = clip(mu(s) + noise, -1, 1) for a deterministic actor, with the noise std moving
    linearly from ``noise_std`` to ``noise_std_final`` over ``noise_decay_steps`` after the heat-up."""

    def __init__(self, hp: NoisyExplorationParams, num_envs: int, act_dim: int, seed: int):
        rng = np.random.default_rng([seed, 2])
        self.noise = OrnsteinUhlenbeckNoise(num_envs, act_dim, rng) if hp.noise == "ou" else GaussianNoise(num_envs, act_dim, rng)
        self.hp = hp

    def std(self, step: int) -> float:
        hp = self.hp
        if hp.noise_decay_steps <= 0:
            return hp.noise_std_final
        progress = min(1.0, (step - hp.learning_starts) / hp.noise_decay_steps)
        return hp.noise_std + (hp.noise_std_final - hp.noise_std) * progress

    def __call__(self, agent: OffPolicyAgent, obs: torch.Tensor, step: int) -> np.ndarray:
        """(N, A) exploratory actions for (N, ...) observations."""
        return np.clip(agent.act(obs, deterministic=True).cpu().numpy() + self.noise.sample(self.std(step)), -1.0, 1.0)

    def end_episodes(self, done: np.ndarray) -> None:
        self.noise.reset(done)

    def state(self) -> dict:
        """The noise's RNG and (Ornstein-Uhlenbeck) process, so a resumed run draws what it would have."""
        return {"rng": self.noise.rng.bit_generator.state, "x": getattr(self.noise, "x", np.zeros(0)).tolist()}

    def load_state(self, state: dict) -> None:
        self.noise.rng.bit_generator.state = state["rng"]
        if hasattr(self.noise, "x"):
            self.noise.x[:] = np.asarray(state["x"], dtype=self.noise.x.dtype).reshape(self.noise.x.shape)


class Exploration(Protocol):
    """How an off-policy agent acts while it trains (:mod:`drivelab.training.collection.replay`)."""

    def __call__(self, agent: OffPolicyAgent, obs: torch.Tensor, step: int) -> np.ndarray:
        """(N, A) actions in [-1, 1] for (N, ...) observations at env step ``step``."""

    def end_episodes(self, done: np.ndarray) -> None:
        """The (N,) envs in ``done`` start new episodes (e.g. an Ornstein-Uhlenbeck process restarts)."""
