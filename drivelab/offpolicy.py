"""What DDPG, TD3 and SAC share: networks for continuous control, exploration noise, Polyak
averaging, and the training loop (act, store, sample, update, evaluate, checkpoint).

Actions live in the policy's units, [-1, 1] per dimension (actors end in tanh); ``to_env`` maps
them affinely onto the env's Box bounds, so replay, critics and noise never see env units.

Image observations go through one CNN encoder that belongs to the critic and is trained by the
critic loss only; the actor reads its features detached (as in SAC-AE, Yarats et al. 2021), so
the actor's gradient cannot degrade the representation the critic relies on.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from torch import nn

from drivelab.buffers import ReplayBatch, ReplayBuffer
from drivelab.envs import make_vector_env
from drivelab.episodes import episode_info
from drivelab.errors import DrivelabError
from drivelab.evaluate import run_episodes
from drivelab.nets import CNNEncoder, activation, is_image_space, mlp


@dataclass
class OffPolicyParams:
    """Hyperparameters common to DDPG, TD3 and SAC (each adds its own)."""
    buffer_size: int = 1_000_000
    batch_size: int = 256
    learning_starts: int = 5_000      # random-action heat-up steps before any update
    utd: float = 1.0                  # update-to-data ratio: gradient steps per env step
    gamma: float = 0.99
    tau: float = 0.005                # Polyak coefficient of the target networks
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    hidden: list[int] = field(default_factory=lambda: [256, 256])
    activation: str = "relu"
    eval_every: int = 10_000          # env steps between deterministic evaluations (0: never)
    eval_episodes: int = 5
    log_every: int = 1_000
    compile: bool = False             # torch.compile the critic and actor forward passes

    def validate(self) -> None:
        if self.batch_size < 1 or self.buffer_size < self.batch_size:
            raise DrivelabError("config fields 'batch_size' and 'buffer_size' must satisfy 1 <= batch_size <= buffer_size")
        if not 0 < self.tau <= 1 or not 0 <= self.gamma <= 1 or self.utd <= 0:
            raise DrivelabError("config fields 'tau' (0, 1], 'gamma' [0, 1] and 'utd' (> 0) are out of range")


# ---------------------------------------------------------------------------------------------
# Networks


class EnsembleLinear(nn.Module):
    """E independent linear layers applied in one batched matmul: (E, B, in) -> (E, B, out).

    Twin (or single) critics are one module, so both Q-values come from one pass instead of
    one pass per critic."""

    def __init__(self, ensemble: int, in_dim: int, out_dim: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(ensemble, in_dim, out_dim))
        self.bias = nn.Parameter(torch.empty(ensemble, 1, out_dim))
        bound = 1 / math.sqrt(in_dim)  # nn.Linear's default initialisation, per member
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class Critics(nn.Module):
    """E Q-networks Q_e(s, a) over features of s: forward returns (E, B)."""

    def __init__(self, feature_dim: int, act_dim: int, hidden: Sequence[int], act: str, ensemble: int = 2):
        super().__init__()
        layers: list[nn.Module] = []
        width = feature_dim + act_dim
        for h in hidden:
            layers += [EnsembleLinear(ensemble, width, h), activation(act)()]
            width = h
        layers.append(EnsembleLinear(ensemble, width, 1))
        self.net = nn.Sequential(*layers)
        self.ensemble = ensemble

    def forward(self, features: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        x = torch.cat([features, actions], dim=-1)
        return self.net(x.unsqueeze(0).expand(self.ensemble, -1, -1)).squeeze(-1)


class DeterministicActor(nn.Module):
    """mu(s) in [-1, 1]^A (DDPG, TD3)."""

    def __init__(self, feature_dim: int, act_dim: int, hidden: Sequence[int], act: str):
        super().__init__()
        self.net = nn.Sequential(mlp(feature_dim, hidden, act), nn.Linear(hidden[-1], act_dim), nn.Tanh())

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features)


LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


class SquashedGaussianActor(nn.Module):
    """a = tanh(u), u ~ N(mu(s), sigma(s)^2) (SAC)."""

    def __init__(self, feature_dim: int, act_dim: int, hidden: Sequence[int], act: str):
        super().__init__()
        self.trunk = mlp(feature_dim, hidden, act)
        self.mean = nn.Linear(hidden[-1], act_dim)
        self.log_std = nn.Linear(hidden[-1], act_dim)

    def forward(self, features: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns (action (B, A) in [-1, 1], log pi(action|s) (B,))."""
        h = self.trunk(features)
        mean = self.mean(h)
        # Soft clamp of log sigma into [LOG_STD_MIN, LOG_STD_MAX] (keeps gradients everywhere).
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(self.log_std(h)) + 1)
        u = mean if deterministic else mean + log_std.exp() * torch.randn_like(mean)  # reparameterised
        return torch.tanh(u), squashed_gaussian_log_prob(u, mean, log_std)


def squashed_gaussian_log_prob(u: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log pi(tanh(u)) for u ~ N(mean, exp(log_std)^2), summed over action dims: shapes (B, A) -> (B,).

    Change of variables a = tanh(u) (Haarnoja et al. 2018, appendix C, eq. 21):
        log pi(a|s) = log N(u; mean, sigma) - sum_i log(1 - tanh(u_i)^2),
    with log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), which stays finite where tanh saturates.
    """
    normal = -0.5 * ((u - mean) / log_std.exp()).pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    log_det = 2 * (math.log(2) - u - nn.functional.softplus(-2 * u))
    return (normal - log_det).sum(-1)


class OffPolicyAgent(nn.Module):
    """Encoder + actor + E critics. ``act``/``to_env`` make it a policy for ``drivelab eval``.

    Vector observations are flattened (each MLP learns its own features); uint8 images share
    one CNN, trained by the critics (see the module docstring).
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int], act: str,
                 stochastic: bool, critics: int = 2):
        super().__init__()
        if not (isinstance(act_space, gym.spaces.Box) and len(act_space.shape) == 1):
            raise DrivelabError(f"DDPG, TD3 and SAC need a continuous 1-D Box action space, not {act_space} "
                                "(for discrete actions use ppo, a2c or grpo; drop env.action_grid)")
        if is_image_space(obs_space):
            self.encoder: nn.Module = CNNEncoder(obs_space)
            feature_dim = self.encoder.out_dim
        else:
            self.encoder = nn.Flatten()
            feature_dim = int(np.prod(obs_space.shape))
        act_dim = act_space.shape[0]
        actor_cls = SquashedGaussianActor if stochastic else DeterministicActor
        self.actor = actor_cls(feature_dim, act_dim, hidden, act)
        self.critic = Critics(feature_dim, act_dim, hidden, act, ensemble=critics)
        self.stochastic = stochastic
        # [-1, 1] -> [low, high]
        low, high = (torch.as_tensor(b, dtype=torch.float32) for b in (act_space.low, act_space.high))
        self.register_buffer("action_scale", (high - low) / 2)
        self.register_buffer("action_bias", (high + low) / 2)

    def compile_networks(self) -> None:
        """torch.compile the forward passes (state_dict keys stay the same, so checkpoints too)."""
        for module in (self.encoder, self.actor, self.critic):
            module.forward = torch.compile(module.forward)

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        return self.encoder(obs if obs.dtype == torch.uint8 else obs.float())

    def policy(self, features: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(action in [-1, 1] (B, A), log-prob (B,) or None for deterministic actors)."""
        if self.stochastic:
            return self.actor(features, deterministic)
        return self.actor(features), None

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        return self.policy(self.features(obs), deterministic)[0]

    def to_env(self, action: torch.Tensor) -> np.ndarray:
        return (action * self.action_scale + self.action_bias).cpu().numpy()


def polyak_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- (1 - tau) * target + tau * source, for every parameter, in one fused op."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def make_optimizers(agent: OffPolicyAgent, hp) -> dict[str, torch.optim.Optimizer]:
    """Adam for the critics (which also train the image encoder) and for the actor."""
    return {"critic": torch.optim.Adam([*agent.encoder.parameters(), *agent.critic.parameters()], lr=hp.critic_lr),
            "actor": torch.optim.Adam(agent.actor.parameters(), lr=hp.actor_lr)}


def make_target(module: nn.Module) -> nn.Module:
    """A frozen copy that only Polyak averaging changes."""
    target = copy.deepcopy(module)
    target.requires_grad_(False)
    return target


# ---------------------------------------------------------------------------------------------
# Exploration noise (DDPG, TD3), in the policy's [-1, 1] units


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


def make_noise(kind: str, num_envs: int, act_dim: int, rng: np.random.Generator):
    if kind == "gaussian":
        return GaussianNoise(num_envs, act_dim, rng)
    if kind == "ou":
        return OrnsteinUhlenbeckNoise(num_envs, act_dim, rng)
    raise DrivelabError(f"exploration noise must be gaussian or ou, got {kind!r}")


def linear_schedule(start: float, end: float, duration: int, step: int) -> float:
    """start -> end linearly over `duration` steps, then end."""
    if duration <= 0:
        return end
    return start + (end - start) * min(1.0, step / duration)


# ---------------------------------------------------------------------------------------------
# The loop


def train_off_policy(cfg, run, agent: OffPolicyAgent, modules: dict[str, nn.Module],
                     optimizers: dict[str, torch.optim.Optimizer],
                     explore: Callable[[torch.Tensor, int], np.ndarray],
                     update: Callable[[ReplayBatch], None], end_episodes: Callable[[np.ndarray], None],
                     flush_stats: Callable[[], dict[str, float]]) -> None:
    """Heat-up with random actions, then per vector-env step: act (``explore``), store, and take
    ``utd`` gradient steps per env step (``update``); evaluate, log and checkpoint on schedule.

    The replay buffer and its sampling RNG are saved in every checkpoint, so ``--resume``
    continues with the same data. Env state cannot be saved: resumed envs start new episodes.
    """
    hp = cfg.algo_params
    if hp.compile:
        for module in modules.values():
            if isinstance(module, OffPolicyAgent):
                module.compile_networks()
    envs = make_vector_env(cfg.env, autoreset_mode=AutoresetMode.SAME_STEP)
    n = envs.num_envs
    buffer = ReplayBuffer(hp.buffer_size, envs.single_observation_space, envs.single_action_space, run.device)
    sample_rng = np.random.default_rng([cfg.seed, 1])
    resumed = run.restore(modules, optimizers)
    if resumed is not None:
        buffer.load_state(resumed.tensors, resumed.state["trainer"]["replay"])
        sample_rng.bit_generator.state = resumed.state["trainer"]["sample_rng"]

    def checkpoint() -> None:
        if run.checkpoint_due():
            tensors, meta = buffer.state()
            run.checkpoint_if_due(modules, optimizers, tensors=tensors,
                                  trainer_state={"replay": meta, "sample_rng": sample_rng.bit_generator.state})

    checkpoint()
    eval_envs = None
    obs, _ = envs.reset(seed=run.reset_seeds(np.ones(n, bool)))
    episode_return, episode_length = np.zeros(n), np.zeros(n, np.int64)
    updates_owed, updates_done = 0.0, 0
    next_log, next_eval = run.step + hp.log_every, run.step + hp.eval_every
    env_seconds, update_seconds, started = 0.0, 0.0, time.perf_counter()
    act_dim = envs.single_action_space.shape[0]
    try:
        while not run.done:
            if run.step < hp.learning_starts:
                action = sample_rng.uniform(-1.0, 1.0, size=(n, act_dim))
            else:
                action = explore(torch.as_tensor(obs, device=run.device), run.step)
            t0 = time.perf_counter()
            next_obs, reward, terminated, truncated, info = envs.step(agent.to_env(torch.as_tensor(action, dtype=torch.float32)))
            env_seconds += time.perf_counter() - t0
            done = terminated | truncated
            real_next = next_obs
            if done.any():  # SAME_STEP autoreset: the true s' of an ended episode is in final_obs
                real_next = next_obs.copy()
                for i in np.flatnonzero(done):
                    real_next[i] = info["final_obs"][i]
            buffer.add(obs, action, reward, real_next, terminated, truncated)
            episode_return += reward
            episode_length += 1
            if done.any():
                final_info = info.get("final_info", {})
                for i in np.flatnonzero(done):
                    run.stats.add(episode_return[i], episode_length[i], episode_info(final_info, i))
                episode_return[done], episode_length[done] = 0.0, 0
                end_episodes(done)
            obs = next_obs
            run.advance(n)

            if run.step >= hp.learning_starts:
                updates_owed += hp.utd * n
                t0 = time.perf_counter()
                while updates_owed >= 1:
                    update(buffer.sample(hp.batch_size, sample_rng))
                    updates_owed -= 1
                    updates_done += 1
                update_seconds += time.perf_counter() - t0

            if hp.eval_every and run.step >= next_eval:
                next_eval += hp.eval_every
                if eval_envs is None:
                    eval_envs = make_vector_env(cfg.env, num_envs=min(n, hp.eval_episodes),
                                                autoreset_mode=AutoresetMode.DISABLED)
                result = run_episodes(eval_envs, agent, hp.eval_episodes, seed=10_000, device=run.device)
                run.log({f"eval/{k}": v for k, v in result.summary().items() if k != "episodes"})
            if run.step >= next_log or run.done:
                next_log += hp.log_every
                wall = time.perf_counter() - started
                run.log({**flush_stats(), "perf/updates": updates_done, "perf/updates_per_s": updates_done / max(update_seconds, 1e-9),
                         "perf/env_share": env_seconds / wall, "perf/update_share": update_seconds / wall,
                         "buffer/size": len(buffer)})
            checkpoint()
    finally:
        envs.close()
        if eval_envs is not None:
            eval_envs.close()


class StatAccumulator:
    """Sums logged scalars as tensors between log points: no host sync per gradient step."""

    def __init__(self, *names: str):
        self.names = names
        self.total: torch.Tensor | None = None  # lives on the values' device
        self.count = 0

    def add(self, *values: torch.Tensor) -> None:
        stacked = torch.stack([v.detach().float() for v in values])
        self.total = stacked if self.total is None else self.total + stacked
        self.count += 1

    def flush(self) -> dict[str, float]:
        if not self.count:
            return {}
        means = dict(zip(self.names, (self.total / self.count).tolist()))  # the one host sync
        self.total, self.count = None, 0
        return means
