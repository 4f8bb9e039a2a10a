"""The replay collectors of DDPG, TD3 and SAC: N envs whose every transition goes into a replay
buffer, played in this process (:class:`SyncReplayCollector`) or by the env workers while the
learner updates (:class:`AsyncReplayCollector`). :meth:`ReplayCollector.from_config` picks one.
The networks are in :mod:`drivelab.training.learning.offpolicy_nets`, the buffer in
:mod:`drivelab.training.learning.replay_buffer`, the exploration in
:mod:`drivelab.training.collection.exploration`; the loops are in the algorithm files.

Actions are stored in the policy's units, [-1, 1] per dimension; the agent's ``to_env`` maps
them onto the env's Box bounds. With ``costs`` (SAC-Lagrangian) each step's ``info["cost"]`` is
stored beside its reward.
"""

from __future__ import annotations

import functools
from collections import deque
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.config import EnvConfig, TrainConfig
from drivelab.envs import make_vector_env
from drivelab.training.collection.checks import check_finite_step
from drivelab.training.collection.exploration import Exploration
from drivelab.training.collection.worker_rollouts import ActorInWorker
from drivelab.training.learning.hyperparams import OffPolicyParams
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent
from drivelab.training.learning.prior_data import PriorData, mixed_batch, prior_rows
from drivelab.training.learning.replay_buffer import ReplayBatch, ReplayBuffer
from drivelab.training.outputs.checkpoint import Checkpoint
from drivelab.training.outputs.demonstrations import load_demonstrations
from drivelab.training.outputs.episodes import stack_infos, step_costs

if TYPE_CHECKING:  # the collector calls the run's services; run/ sits above collection/
    from drivelab.training.run import Run


class ReplayCollector:
    """What both modes share: N envs, the replay buffer, each env's reset seeds, the gradient
    steps owed under the update-to-data ratio, and the checkpointed state.

    :meth:`collect` plays and stores the next env steps with an :class:`Exploration` (uniform
    random actions during the heat-up, before ``learning_starts``); :meth:`batches` then yields
    the gradient steps owed for them. The subclasses play them one of two ways (see each).

    The envs run with ``AutoresetMode.DISABLED``; the collector (or the worker) resets them,
    each from a seed drawn from ``run.rng``: the s' stored at an episode end is simply the
    step's observation, and every episode's start is reproducible. A checkpoint
    (:meth:`state`) keeps the buffer, the sampling RNG, the update counts and each env's last
    reset seed; on resume (:meth:`start`), an env that had just been reset starts again from
    that same seed, so a run checkpointed between episodes continues exactly as if it had never
    stopped. An episode in flight cannot be saved: its env starts a new one.
    """

    def __init__(self, env_cfg: EnvConfig, hp: OffPolicyParams, run: Run, seed: int,
                 wrapper: Callable[[gym.Env], gym.Env] | None = None, costs: bool = False):
        self.envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED, on_restart=run.note_env_restart,
                                    wrapper=wrapper)
        self.num_envs = self.envs.num_envs
        self.obs_space, self.act_space = self.envs.single_observation_space, self.envs.single_action_space
        self.buffer = ReplayBuffer(hp.buffer_size, self.obs_space, self.act_space, run.device, gamma=hp.gamma,
                                   n_step=hp.n_step, num_envs=self.num_envs, costs=costs,
                                   cost_gamma=getattr(hp, "cost_gamma", None))
        self.sample_rng = np.random.default_rng([seed, 1])
        self.prior: PriorData | None = None   # the demonstrations mixed into every batch (start)
        self._costs = costs
        self.hp, self.run, self.step_timeout = hp, run, env_cfg.step_timeout
        self.steps = run.step                 # env steps stored (run.step after this collector's last call)
        self.obs = None
        self._updates_owed = 0.0              # fractional gradient steps carried over (utd < 1)
        self._new_steps = 0                   # env steps stored by the last collect()
        self.updates = 0                      # gradient steps taken (TD3 updates its actor every policy_delay-th)
        self.exploration: Exploration | None = None
        self._reset_seeds = np.zeros(self.num_envs, np.int64)   # each env's last reset seed
        self._fresh = np.zeros(self.num_envs, bool)             # reset, not stepped since

    @classmethod
    def from_config(cls, cfg: TrainConfig, run: Run,
                    build_policy: Callable[[TrainConfig, gym.Space, gym.Space], OffPolicyAgent],
                    exploration: Callable[..., Exploration], costs: bool = False) -> ReplayCollector:
        """The collector an off-policy config asks for: :class:`AsyncReplayCollector` with
        ``act_in_workers``, whose env workers build their actor with ``build_policy(cfg,
        obs_space, act_space)`` and their one-env exploration with ``exploration(cfg.algo_params,
        1, act_dim, seed)``; :class:`SyncReplayCollector` otherwise. ``costs``: store each step's
        cost too (discounted by ``cfg.algo_params.cost_gamma`` in n-step sums)."""
        hp: OffPolicyParams = cfg.algo_params
        if not hp.act_in_workers:
            return SyncReplayCollector(cfg.env, hp, run, seed=cfg.seed, costs=costs)
        return AsyncReplayCollector(cfg.env, hp, run, seed=cfg.seed, worker_agent=functools.partial(build_policy, cfg),
                                    worker_exploration=functools.partial(exploration, hp), costs=costs)

    def start(self, checkpoint: Checkpoint | None, exploration: Exploration) -> None:
        """Reset every env; on resume, first load the buffer, the sampling RNG, the update counts,
        the ``exploration``'s state and the seeds of episodes that had not started yet
        (``checkpoint`` as returned by ``run.start``). The exploration's state is saved with the
        collector's from then on."""
        self.exploration = exploration
        everyone = np.ones(self.num_envs, bool)
        trainer = (checkpoint.state.get("trainer") or {}) if checkpoint is not None else {}
        self._start_prior(checkpoint, trainer)
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

    def _start_prior(self, checkpoint: Checkpoint | None, trainer: dict) -> None:
        """The prior data: the checkpoint's own copy on resume (exact, and the file may be gone),
        else the config's file, checked against the env's layout; logged once (prior/*)."""
        hp = self.hp
        if hp.prior_data is None or hp.prior_share == 0:
            return
        gammas = {"device": self.run.device, "gamma": hp.gamma, "cost_gamma": getattr(hp, "cost_gamma", None)}
        if "prior" in trainer:
            self.prior = PriorData.from_state(checkpoint.tensors, trainer["prior"], **gammas)
        else:
            rows, about = load_demonstrations(hp.prior_data, self.obs_space, self.act_space, costs=self._costs)
            self.prior = PriorData(rows, about, **gammas)
        self.run.log({"prior/transitions": float(self.prior.size),
                      "prior/env_steps": float(self.prior.about.get("env_steps", self.prior.size))})

    def _reset(self, mask: np.ndarray, seeds: list[int | None]) -> None:
        with self.run.timing.env:
            obs, _ = self.envs.reset(seed=seeds, options={"reset_mask": mask})
        self.obs = obs
        self._reset_seeds[mask] = [seed for seed, m in zip(seeds, mask) if m]
        self._fresh[mask] = True

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """(tensors, JSON state) for a checkpoint: the replay buffer, the sampling RNG, the seeds."""
        tensors, meta = self.buffer.state()
        if self.prior is not None:
            prior_tensors, prior_meta = self.prior.state()
            tensors = {**tensors, **prior_tensors}
        state = {"replay": meta, "sample_rng": self.sample_rng.bit_generator.state, "updates": self.updates,
                 "updates_owed": self._updates_owed, "reset_seeds": self._reset_seeds.tolist(),
                 "fresh": self._fresh.tolist(), "exploration": self.exploration.state()}
        if self.prior is not None:
            state["prior"] = prior_meta
        return tensors, state

    def obs_tensor(self) -> torch.Tensor:
        return torch.as_tensor(self.obs, device=self.run.device)

    def random_actions(self) -> np.ndarray:
        """(N, A) uniform actions in [-1, 1]: the heat-up before ``learning_starts``."""
        return self.sample_rng.uniform(-1.0, 1.0, size=(self.num_envs, self.act_space.shape[0]))

    def collect(self, agent: OffPolicyAgent) -> int:
        """Play and store the next env steps with ``agent`` and the exploration; returns how many
        were stored (for ``run.end_iteration``)."""
        self._new_steps = self._play_and_store(agent)
        return self._new_steps

    def _play_and_store(self, agent: OffPolicyAgent) -> int:
        raise NotImplementedError

    def batches(self) -> Iterator[ReplayBatch]:
        """The uniform batches for the ``utd`` gradient steps owed per env step stored by the
        last :meth:`collect` (fractional counts carry over), once ``learning_starts`` steps are
        stored. With prior data, ``prior_share`` of each batch's rows are prior transitions (the
        last rows), the rest replay."""
        if self.steps < self.hp.learning_starts:
            return
        self._updates_owed += self.hp.utd * self._new_steps
        k = prior_rows(self.hp.batch_size, self.hp.prior_share) if self.prior is not None else 0
        while self._updates_owed >= 1:
            self._updates_owed -= 1
            self.updates += 1
            batch = self.buffer.sample(self.hp.batch_size - k, self.sample_rng)
            yield mixed_batch(batch, self.prior.sample(k, self.sample_rng)) if k else batch

    def close(self) -> None:
        self.envs.close()


class SyncReplayCollector(ReplayCollector):
    """The default mode: one vector step per :meth:`collect`, in this process; the envs wait
    while the learner updates. Bit-reproducible for a seed, whatever the timing."""

    def _play_and_store(self, agent: OffPolicyAgent) -> int:
        heat_up = self.steps < self.hp.learning_starts
        action = self.random_actions() if heat_up else self.exploration(agent, self.obs_tensor(), self.steps)
        self.exploration.end_episodes(self.step(agent, action))
        return self.num_envs

    def step(self, agent: OffPolicyAgent, action: np.ndarray) -> np.ndarray:
        """Step every env with ``action`` (N, A) in policy units; returns ``done`` (N,)."""
        with self.run.timing.env:
            next_obs, reward, terminated, truncated, info = self.envs.step(
                agent.to_env(torch.as_tensor(action, dtype=torch.float32)))
        check_finite_step(next_obs, reward, self.steps)
        done = terminated | truncated
        # with DISABLED autoreset the info is the step's own, an episode's last step included
        costs = step_costs(info, done) if self.buffer.costs is not None else None
        self.buffer.add(self.obs, action, reward, next_obs, terminated, truncated, costs)
        self.run.episodes.step(reward, done, info)
        self.obs = next_obs
        self._fresh[:] = False
        self.steps += self.num_envs
        if done.any():
            self._reset(done, self.run.reset_seeds(done))
        return done


class AsyncReplayCollector(ReplayCollector):
    """``act_in_workers`` (subprocess envs): each worker plays chunks of ``chunk_steps`` steps
    with a copy of the actor (:class:`~drivelab.training.collection.worker_rollouts.ActorInWorker`)
    and keeps stepping while the learner updates on what is already stored.

    Each worker has ``chunks_in_flight`` chunks queued, so it starts the next as soon as it has
    sent one. A :meth:`collect` stores the oldest chunk in flight (none until
    ``chunks_in_flight`` are queued) and queues a new one with the learner's weights of the
    moment: the actor the workers play lags the learner's by at most ``chunks_in_flight``
    chunks of updates (``utd * chunk_steps * N`` gradient steps each, logged as
    ``charts/policy_lag``). This gives up the exact interleaving of the synchronous mode: an
    update never sees the chunks being played, and episodes in flight when a checkpoint is
    written restart on resume. A run is still reproducible for a seed (what a worker plays
    depends on its reset seed and the weights it was sent, never on timing), but it is not the
    synchronous mode's run.
    """

    def __init__(self, env_cfg: EnvConfig, hp: OffPolicyParams, run: Run, seed: int,
                 worker_agent: Callable[[gym.Space, gym.Space], OffPolicyAgent],
                 worker_exploration: Callable[[int, int, int], Exploration], costs: bool = False):
        wrapper = functools.partial(ActorInWorker, make_agent=worker_agent, make_exploration=worker_exploration)
        super().__init__(env_cfg, hp, run, seed, wrapper=wrapper, costs=costs)
        self._in_flight: deque[int] = deque()   # self.updates when each chunk in flight was sent
        self._sent_steps = self.steps           # env steps stored or in flight

    def _play_and_store(self, agent: OffPolicyAgent) -> int:
        last_chunks = self._sent_steps >= self.run.cfg.steps  # nothing more to send: store what is in flight
        full = len(self._in_flight) >= self.hp.chunks_in_flight
        stored = self._store_chunk() if self._in_flight and (full or last_chunks) else 0
        while len(self._in_flight) < self.hp.chunks_in_flight and self._sent_steps < self.run.cfg.steps:
            self._send_chunk(agent)
        return stored

    def _send_chunk(self, agent: OffPolicyAgent) -> None:
        """Queue ``chunk_steps`` steps in each worker with the actor's current weights; the
        chunk's steps are the ``chunk_steps * N`` after those already stored or in flight."""
        # the run's last chunks are cut so that it stores exactly `steps` (a multiple of N)
        length = min(self.hp.chunk_steps, -(-(self.run.cfg.steps - self._sent_steps) // self.num_envs))
        if length <= 0:
            return
        # the workers only act: the critics (and a cost critic) stay here
        weights = {name: value.detach().cpu().numpy() for name, value in agent.state_dict().items()
                   if not name.startswith(("critic.", "cost_critic."))}
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
        for env in range(self.num_envs):
            check_finite_step(next_obs[:, env][None], rewards[:, env][None], self.steps, first_env=env)
        flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731
        costs = flat(np.stack([chunk.costs for chunk in chunks], axis=1)) if self.buffer.costs is not None else None
        self.buffer.add(flat(obs), flat(actions), flat(rewards), flat(next_obs), flat(terminated), flat(truncated), costs)
        done = terminated | truncated
        for t in range(len(rewards)):
            info = stack_infos([chunk.episode_info.get(t, {}) for chunk in chunks]) if done[t].any() else {}
            self.run.episodes.step(rewards[t], done[t], info)
        self.steps += rewards.size
        return rewards.size
