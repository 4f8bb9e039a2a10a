"""Parts that DDPG, TD3 and SAC call from their loops: shared hyperparameters, the collector that
steps envs into a replay buffer, and exploration noise. Their networks are in
:mod:`drivelab.training.nets`, the buffer in :mod:`drivelab.training.buffers`; the loops are in the algorithm files.

Actions are stored in the policy's units, [-1, 1] per dimension; the agent's ``to_env`` maps
them onto the env's Box bounds.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.config import EnvConfig, TrainConfig
from drivelab.envs import make_vector_env
from drivelab.errors import DrivelabError
from drivelab.training.buffers import ReplayBatch, ReplayBuffer
from drivelab.training.checkpoint import Checkpoint
from drivelab.training.episodes import stack_infos
from drivelab.training.losses import fused_adam
from drivelab.training.nets import OffPolicyAgent
from drivelab.training.run import Run
from drivelab.training.timing import native_bf16
from drivelab.training.worker_rollouts import ActorInWorker, Exploration


@dataclass
class OffPolicyParams:
    """Hyperparameters common to DDPG, TD3 and SAC (each adds its own)."""
    buffer_size: int = 1_000_000      # replay buffer capacity (transitions)
    batch_size: int = 256             # transitions per gradient step
    learning_starts: int = 5_000      # random-action heat-up steps before any update
    utd: float = 1.0                  # update-to-data ratio: gradient steps per env step
    gamma: float = 0.99               # discount factor
    n_step: int = 1                   # rewards summed in the TD target (n-step returns; buffers.ReplayBuffer)
    tau: float = 0.005                # Polyak coefficient of the target networks
    actor_lr: float = 3e-4            # actor learning rate (Adam)
    critic_lr: float = 3e-4           # critic (and image encoder) learning rate (Adam)
    hidden: list[int] = field(default_factory=lambda: [256, 256])  # hidden layer widths
    activation: str = "relu"          # tanh | relu | elu | silu
    critic_layer_norm: bool = False   # LayerNorm in the critics' hidden layers (nets.Critics)
    compile: bool = False             # torch.compile the critic and actor forward passes
    # The learner's updates under bfloat16 autocast (update_precision), the output layers kept
    # float32 (nets.in_float32): ~1.5x faster updates where the CPU has AVX512-BF16 or AMX, and on
    # GPUs; elsewhere torch emulates bfloat16 and the updates run slower (true warns there: Run).
    # auto: bfloat16 where the hardware computes it (timing.native_bf16), float32 elsewhere.
    bf16_updates: bool | str = False
    # The env workers act with a copy of the actor and keep stepping while the learner updates
    # (subprocess envs; see ReplayCollector): faster, with a policy lag of one chunk.
    act_in_workers: bool = False
    chunk_steps: int = 32             # with act_in_workers: steps each worker plays per weight update
    chunks_in_flight: int = 2         # with act_in_workers: chunks queued in each worker (the lag bound)

    def validate(self) -> None:
        if self.batch_size < 1 or self.buffer_size < self.batch_size:
            raise DrivelabError("config fields 'batch_size' and 'buffer_size' must satisfy 1 <= batch_size <= buffer_size")
        if self.chunk_steps < 1 or self.chunks_in_flight < 1:
            raise DrivelabError("config fields 'chunk_steps' and 'chunks_in_flight' must be >= 1")
        if self.n_step < 1:
            raise DrivelabError(f"config field 'n_step' must be >= 1, got {self.n_step}")
        if self.bf16_updates not in (True, False, "auto"):
            raise DrivelabError(f"config field 'bf16_updates' must be true, false or auto, got {self.bf16_updates!r}")
        if not 0 < self.tau <= 1 or not 0 <= self.gamma <= 1 or self.utd <= 0:
            raise DrivelabError("config fields 'tau' (0, 1], 'gamma' [0, 1] and 'utd' (> 0) are out of range")

    def iteration_steps(self, num_envs: int) -> int:
        """Env steps of one iteration (one step of every env; the workers' last chunks are cut
        to end there): ``steps`` is rounded up to a multiple of it."""
        return num_envs


def updates_in_bf16(hp: OffPolicyParams, device: torch.device) -> bool:
    """Whether the learner's updates run in bfloat16: ``bf16_updates`` true, or auto on a device
    that computes bfloat16 in hardware."""
    return hp.bf16_updates is True or (hp.bf16_updates == "auto" and native_bf16(device) is True)


def update_precision(hp: OffPolicyParams, device: torch.device) -> contextlib.AbstractContextManager:
    """The context of the learner's updates: bfloat16 autocast where :func:`updates_in_bf16`, else a no-op."""
    if not updates_in_bf16(hp, device):
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)


@dataclass
class NoisyExplorationParams(OffPolicyParams):
    """Exploration by noise on a deterministic actor (DDPG, TD3), with a linear schedule."""
    noise: str = "gaussian"           # gaussian | ou (Ornstein-Uhlenbeck)
    noise_std: float = 0.1            # noise std at the start ...
    noise_std_final: float = 0.1      # ... and after noise_decay_steps
    noise_decay_steps: int = 0
    pre_tanh_l2: float = 0.0          # actor loss + this * mean(u(s)^2), u the actor's pre-tanh output

    def validate(self) -> None:
        super().validate()
        if self.pre_tanh_l2 < 0:
            raise DrivelabError(f"config field 'pre_tanh_l2' must be >= 0, got {self.pre_tanh_l2}")
        if self.noise not in ("gaussian", "ou"):
            raise DrivelabError(f"config field 'noise' must be gaussian or ou, got {self.noise!r}")


class Optimizers(NamedTuple):
    """DDPG's and TD3's optimisers (SAC adds one for its temperature); the field names are the
    optimisers' names in checkpoints."""
    critic: torch.optim.Optimizer     # the critics and the (image) encoder
    actor: torch.optim.Optimizer


def make_optimizers(agent: OffPolicyAgent, hp: OffPolicyParams) -> Optimizers:
    """Adam for the critics (which also train the image encoder) and for the actor, fused: the
    learner bounds an off-policy run on two cores, and the default Adam's many small ops were a
    fifth of its update (:func:`~drivelab.training.losses.fused_adam`)."""
    critic = fused_adam([*agent.encoder.parameters(), *agent.critic.parameters()], lr=hp.critic_lr)
    return Optimizers(critic=critic, actor=fused_adam(agent.actor.parameters(), lr=hp.actor_lr))


class ReplayCollector:
    """N envs whose every transition goes into a replay buffer.

    :meth:`collect` plays the next env steps with an :class:`Exploration` (uniform random actions
    during the heat-up, before ``learning_starts``) and stores them; ``batches`` then yields
    the gradient steps owed for them under the update-to-data ratio. It plays them one of two
    ways:

    * **in this process** (the default): one vector step per call; the envs wait while the
      learner updates. Bit-reproducible for a seed, whatever the timing.
    * **in the env workers** (``act_in_workers``, subprocess envs): each worker plays chunks of
      ``chunk_steps`` steps with a copy of the actor (:class:`~drivelab.training.worker_rollouts.ActorInWorker`)
      and keeps stepping while the learner updates on what is already stored. Each worker has
      ``chunks_in_flight`` chunks queued, so it starts the next as soon as it has sent one. A
      call stores the oldest chunk in flight and queues a new one with the learner's weights of
      the moment: the actor the workers play lags the learner's by at most
      ``chunks_in_flight`` chunks of updates (``utd * chunk_steps * N`` gradient steps each,
      logged as ``charts/policy_lag``). This gives up the exact interleaving of the default: an
      update never sees the chunks being played, and episodes in flight when a checkpoint is
      written restart on resume. A run is still reproducible for a seed (what a worker plays
      depends on its reset seed and the weights it was sent, never on timing), but it is not
      the default mode's run.

    The envs run with ``AutoresetMode.DISABLED``; this collector (or the worker) resets them,
    each from a seed drawn from ``run.rng``: the s' stored at an episode end is simply the
    step's observation, and every episode's start is reproducible. A checkpoint
    (:meth:`state`) keeps the buffer, the sampling RNG, the update counts and each env's last
    reset seed; on resume (:meth:`start`), an env that had just been reset starts again from
    that same seed, so a run checkpointed between episodes continues exactly as if it had never
    stopped. An episode in flight cannot be saved: its env starts a new one.
    """

    def __init__(self, env_cfg: EnvConfig, hp: OffPolicyParams, run: Run, seed: int,
                 worker_agent: Callable[[gym.Space, gym.Space], OffPolicyAgent] | None = None,
                 worker_exploration: Callable[[int, int, int], Exploration] | None = None):
        self.in_workers = hp.act_in_workers
        wrapper = (functools.partial(ActorInWorker, make_agent=worker_agent, make_exploration=worker_exploration)
                   if self.in_workers else None)
        self.envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED, on_restart=run.note_env_restart,
                                    wrapper=wrapper)
        self.num_envs = self.envs.num_envs
        self.obs_space, self.act_space = self.envs.single_observation_space, self.envs.single_action_space
        self.buffer = ReplayBuffer(hp.buffer_size, self.obs_space, self.act_space, run.device, gamma=hp.gamma,
                                   n_step=hp.n_step, num_envs=self.num_envs)
        self.sample_rng = np.random.default_rng([seed, 1])
        self.hp, self.run, self.step_timeout = hp, run, env_cfg.step_timeout
        self.steps = run.step                 # env steps stored (run.step after this collector's last call)
        self.obs = None
        self._updates_owed = 0.0              # fractional gradient steps carried over (utd < 1)
        self._new_steps = 0                   # env steps stored by the last collect()
        self.updates = 0                      # gradient steps taken (TD3 updates its actor every policy_delay-th)
        self.exploration: Exploration | None = None
        self._reset_seeds = np.zeros(self.num_envs, np.int64)   # each env's last reset seed
        self._fresh = np.zeros(self.num_envs, bool)             # reset, not stepped since
        self._in_flight: deque[int] = deque()                   # self.updates when each chunk in flight was sent
        self._sent_steps = self.steps                           # env steps stored or in flight

    @classmethod
    def from_config(cls, cfg: TrainConfig, run: Run,
                    build_policy: Callable[[TrainConfig, gym.Space, gym.Space], OffPolicyAgent],
                    exploration: Callable[..., Exploration]) -> ReplayCollector:
        """The collector an off-policy config asks for. With ``act_in_workers`` each env worker
        builds its actor with ``build_policy(cfg, obs_space, act_space)`` and its one-env
        exploration with ``exploration(cfg.algo_params, 1, act_dim, seed)``."""
        hp: OffPolicyParams = cfg.algo_params
        return cls(cfg.env, hp, run, seed=cfg.seed, worker_agent=functools.partial(build_policy, cfg),
                   worker_exploration=functools.partial(exploration, hp))

    def start(self, checkpoint: Checkpoint | None, exploration: Exploration) -> None:
        """Reset every env; on resume, first load the buffer, the sampling RNG, the update counts,
        the ``exploration``'s state and the seeds of episodes that had not started yet
        (``checkpoint`` as returned by ``run.start``). The exploration's state is saved with the
        collector's from then on."""
        self.exploration = exploration
        everyone = np.ones(self.num_envs, bool)
        trainer = (checkpoint.state.get("trainer") or {}) if checkpoint is not None else {}
        if "replay" not in trainer:
            # A fresh run, or one resumed from its step-0 checkpoint, which is saved before the
            # collector exists: the RNGs are as the fresh run had them, so it starts the same way.
            self._reset(everyone, self.run.reset_seeds(everyone))
            return
        self.buffer.load_state(checkpoint.tensors, trainer["replay"])
        self.buffer.cut_episodes()  # the episodes in flight start anew below
        self.sample_rng.bit_generator.state = trainer["sample_rng"]
        self.updates, self._updates_owed = int(trainer.get("updates", 0)), float(trainer.get("updates_owed", 0.0))
        if "exploration" in trainer:
            exploration.load_state(trainer["exploration"])
        fresh = np.asarray(trainer.get("fresh", [False] * self.num_envs), bool)[: self.num_envs]
        old_seeds = trainer.get("reset_seeds", [0] * self.num_envs)
        new_seeds = iter(self.run.reset_seeds(~fresh))
        seeds = [int(seed) if again else next(new_seeds) for seed, again in zip(old_seeds, fresh)]
        self._reset(everyone, seeds)

    def _reset(self, mask: np.ndarray, seeds: list[int | None]) -> None:
        with self.run.timing.env:
            obs, _ = self.envs.reset(seed=seeds, options={"reset_mask": mask})
        self.obs = obs
        self._reset_seeds[mask] = [seed for seed, m in zip(seeds, mask) if m]
        self._fresh[mask] = True

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """(tensors, JSON state) for a checkpoint: the replay buffer, the sampling RNG, the seeds."""
        tensors, meta = self.buffer.state()
        state = {"replay": meta, "sample_rng": self.sample_rng.bit_generator.state, "updates": self.updates,
                 "updates_owed": self._updates_owed, "reset_seeds": self._reset_seeds.tolist(),
                 "fresh": self._fresh.tolist(), "exploration": self.exploration.state()}
        return tensors, state

    def obs_tensor(self) -> torch.Tensor:
        return torch.as_tensor(self.obs, device=self.run.device)

    def random_actions(self) -> np.ndarray:
        """(N, A) uniform actions in [-1, 1]: the heat-up before ``learning_starts``."""
        return self.sample_rng.uniform(-1.0, 1.0, size=(self.num_envs, self.act_space.shape[0]))

    def collect(self, agent: OffPolicyAgent) -> int:
        """Play and store the next env steps with ``agent`` and the exploration; returns how many
        were stored (for ``run.end_iteration``). In this process: one vector step. In the
        workers: the oldest chunk in flight (none until ``chunks_in_flight`` are queued), and a
        new chunk is queued with the actor's weights of the moment."""
        if self.in_workers:
            last_chunks = self._sent_steps >= self.run.cfg.steps  # nothing more to send: store what is in flight
            full = len(self._in_flight) >= self.hp.chunks_in_flight
            stored = self._store_chunk() if self._in_flight and (full or last_chunks) else 0
            while len(self._in_flight) < self.hp.chunks_in_flight and self._sent_steps < self.run.cfg.steps:
                self._send_chunk(agent)
        else:
            heat_up = self.steps < self.hp.learning_starts
            action = self.random_actions() if heat_up else self.exploration(agent, self.obs_tensor(), self.steps)
            self.exploration.end_episodes(self.step(agent, action))
            stored = self.num_envs
        self._new_steps = stored
        return stored

    def step(self, agent: OffPolicyAgent, action: np.ndarray) -> np.ndarray:
        """Step every env with ``action`` (N, A) in policy units; returns ``done`` (N,)."""
        with self.run.timing.env:
            next_obs, reward, terminated, truncated, info = self.envs.step(
                agent.to_env(torch.as_tensor(action, dtype=torch.float32)))
        done = terminated | truncated
        self.buffer.add(self.obs, action, reward, next_obs, terminated, truncated)
        self.run.episodes.step(reward, done, info)
        self.obs = next_obs
        self._fresh[:] = False
        self.steps += self.num_envs
        if done.any():
            self._reset(done, self.run.reset_seeds(done))
        return done

    def _send_chunk(self, agent: OffPolicyAgent) -> None:
        """Queue ``chunk_steps`` steps in each worker with the actor's current weights; the
        chunk's steps are the ``chunk_steps * N`` after those already stored or in flight."""
        # the run's last chunks are cut so that it stores exactly `steps` (a multiple of N)
        length = min(self.hp.chunk_steps, -(-(self.run.cfg.steps - self._sent_steps) // self.num_envs))
        if length <= 0:
            return
        weights = {name: value.detach().cpu().numpy() for name, value in agent.state_dict().items()
                   if not name.startswith("critic.")}
        heat_up = self._sent_steps < self.hp.learning_starts
        self.envs.call_queue("play", weights, length, self._sent_steps, self.num_envs, heat_up, steps=length)
        self._in_flight.append(self.updates)
        self._sent_steps += length * self.num_envs
        self._fresh[:] = False  # the workers are playing: no episode can be restarted from its seed

    def _store_chunk(self) -> int:
        """Wait for the oldest chunk in flight and store it, step by step as if this process had
        stepped the envs; returns the env steps stored (0 if a worker failed: the workers
        restarted, the chunks in flight are dropped and every env starts a new episode)."""
        with self.run.timing.env:
            chunks = self.envs.call_next(timeout=self.step_timeout and self.step_timeout * self.hp.chunk_steps)
        self.run.record({"charts/policy_lag": float(self.updates - self._in_flight.popleft())})
        if chunks is None:  # the workers restarted: the chunks in flight are gone
            self._in_flight.clear()
            self._sent_steps = self.steps
            self.buffer.cut_episodes()
            everyone = np.ones(self.num_envs, bool)
            self.run.episodes.restart(everyone)
            self._reset(everyone, self.run.reset_seeds(everyone))
            return 0
        # (T, N, ...) in the order the trainer would have stepped them: row t of every env, then t + 1
        obs, actions, rewards, next_obs, terminated, truncated = (
            np.stack([getattr(chunk, name) for chunk in chunks], axis=1)
            for name in ("obs", "actions", "rewards", "next_obs", "terminated", "truncated"))
        flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731
        self.buffer.add(flat(obs), flat(actions), flat(rewards), flat(next_obs), flat(terminated), flat(truncated))
        done = terminated | truncated
        for t in range(len(rewards)):
            info = stack_infos([chunk.episode_info.get(t, {}) for chunk in chunks]) if done[t].any() else {}
            self.run.episodes.step(rewards[t], done[t], info)
        self.steps += rewards.size
        return rewards.size

    def batches(self) -> Iterator[ReplayBatch]:
        """The uniform batches for the ``utd`` gradient steps owed per env step stored by the
        last :meth:`collect` (fractional counts carry over), once ``learning_starts`` steps are stored."""
        if self.steps < self.hp.learning_starts:
            return
        self._updates_owed += self.hp.utd * self._new_steps
        while self._updates_owed >= 1:
            self._updates_owed -= 1
            self.updates += 1
            yield self.buffer.sample(self.hp.batch_size, self.sample_rng)

    def close(self) -> None:
        self.envs.close()


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
