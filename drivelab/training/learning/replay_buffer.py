"""Replay buffer for off-policy algorithms (DDPG, TD3, SAC).

Preallocated ring arrays, one row per transition; vector envs insert N rows per step and a batch
is sampled with one fancy-indexing gather per field (no Python loop over items). Images stay
uint8 (4x smaller than float32; the CNN scales them). ``terminated`` and ``truncated`` are kept
apart: only termination cuts the TD target's bootstrap.

With ``n_step > 1`` a sampled row carries the n-step return (Sutton & Barto 2018, eq. 7.1; as in
Rainbow and D4PG): the next n rewards of its env, discounted, summed up to the first episode end,
and the s' after the last of them. Both collectors store the N envs in lockstep (row t of every
env, then t + 1), so env i's next transition is always N rows further on: the n-step sum is one
gather per extra step, computed when the batch is drawn (so it needs no extra storage and a
checkpoint holds the one-step rows). The sum uses the rewards the behaviour policy got, without an
off-policy correction: the usual trade of a little bias for faster reward propagation.

With ``costs`` (SAC-Lagrangian) each row also keeps its step's cost, and a batch carries the n-step
cost sum, discounted by ``cost_gamma`` and cut at the same episode ends as the rewards, for the cost
critic's target.
"""

from __future__ import annotations

from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch

from drivelab.errors import DrivelabError


class ReplayBatch(NamedTuple):
    obs: torch.Tensor         # (B, *obs_shape), env dtype (uint8 images stay uint8)
    actions: torch.Tensor     # (B, act_dim) float32, in the policy's [-1, 1] units
    rewards: torch.Tensor     # (B,)
    next_obs: torch.Tensor    # (B, *obs_shape): the true next observation (the final one at an episode end)
    terminated: torch.Tensor  # (B,) float32: 1 where s' is terminal (no bootstrap)
    discount: torch.Tensor    # (B,) float32: gamma^m, the bootstrap's discount after the m rewards in ``rewards``
    costs: torch.Tensor | None = None          # (B,) float32: the m costs summed, discounted by cost_gamma (buffers with costs)
    cost_discount: torch.Tensor | None = None  # (B,) float32: cost_gamma^m


def available_memory() -> int:
    """Bytes of memory available to this process now (Linux /proc/meminfo; psutil elsewhere)."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:  # pragma: no cover - psutil comes with MetaDrive
        with open("/proc/meminfo") as f:
            fields = dict(line.split(":", 1) for line in f)
        return int(fields["MemAvailable"].split()[0]) * 1024


class ReplayBuffer:
    """A ring of ``capacity`` transitions.

    Args:
        capacity: number of transitions kept; the oldest are overwritten.
        obs_space, act_space: the env's spaces (the action space must be a Box).
        device: where sampled batches go.
        gamma: the discount of the TD target (``discount`` of a batch is gamma^m).
        n_step: rewards summed per sampled row (1: the one-step transition).
        num_envs: envs stored in lockstep, N rows per step (with ``n_step > 1`` the capacity is
            rounded down to a multiple of it, so that a row's successor stays N rows on).
        max_memory_fraction: refuse (with a clear error) a buffer needing more than this share of
            the memory available now, instead of failing hours into a run.
        costs: keep each step's cost too (SAC-Lagrangian); its n-step sums are discounted by
            ``cost_gamma`` (None: ``gamma``).
    """

    def __init__(self, capacity: int, obs_space: gym.Space, act_space: gym.Space,
                 device: torch.device | str = "cpu", gamma: float = 0.99, n_step: int = 1, num_envs: int = 1,
                 max_memory_fraction: float = 0.8, costs: bool = False, cost_gamma: float | None = None):
        if n_step > 1:
            capacity -= capacity % num_envs
        if capacity < 1:
            raise DrivelabError(f"replay buffer_size must be >= 1, got {capacity}")
        act_dim = int(np.prod(act_space.shape))
        needed = self.bytes_needed(capacity, obs_space, act_dim, costs)
        available = available_memory()
        if needed > max_memory_fraction * available:
            raise DrivelabError(
                f"replay buffer of {capacity} transitions needs {needed / 2**30:.1f} GiB but only "
                f"{available / 2**30:.1f} GiB is available; lower buffer_size"
            )
        self.capacity, self.device = capacity, torch.device(device)
        self.gamma, self.n_step, self.num_envs = gamma, n_step, num_envs
        self.obs = np.zeros((capacity, *obs_space.shape), obs_space.dtype)
        self.next_obs = np.zeros((capacity, *obs_space.shape), obs_space.dtype)
        self.actions = np.zeros((capacity, act_dim), np.float32)
        self.rewards = np.zeros(capacity, np.float32)
        self.terminated = np.zeros(capacity, bool)
        self.truncated = np.zeros(capacity, bool)
        # the step costs, only when asked for: a buffer without them checkpoints the same fields as before
        self.costs = np.zeros(capacity, np.float32) if costs else None
        self.cost_gamma = gamma if cost_gamma is None else cost_gamma
        self.fields = self._FIELDS + (("costs",) if costs else ())
        self.pos = 0      # next row to write
        self.size = 0     # rows filled

    @staticmethod
    def bytes_needed(capacity: int, obs_space: gym.Space, act_dim: int, costs: bool = False) -> int:
        obs_bytes = int(np.prod(obs_space.shape)) * np.dtype(obs_space.dtype).itemsize
        return capacity * (2 * obs_bytes + 4 * act_dim + 4 + 2 + (4 if costs else 0))

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, next_obs: np.ndarray,
            terminated: np.ndarray, truncated: np.ndarray, costs: np.ndarray | None = None) -> None:
        """Insert a batch of N transitions (leading dim N), wrapping around the ring; ``costs`` (N,)
        is required by a buffer with costs and ignored by one without."""
        n = len(rewards)
        rows = (self.pos + np.arange(n)) % self.capacity
        self.obs[rows] = obs
        self.next_obs[rows] = next_obs
        self.actions[rows] = np.asarray(actions).reshape(n, -1)
        self.rewards[rows] = rewards
        self.terminated[rows] = terminated
        self.truncated[rows] = truncated
        if self.costs is not None:
            self.costs[rows] = costs
        self.pos = int((self.pos + n) % self.capacity)
        self.size = min(self.size + n, self.capacity)

    def cut_episodes(self) -> None:
        """Mark the newest row of every env truncated: its episode was cut there (a resume, or
        the env workers restarting), so an n-step sum must not run on into the next episode. A row
        whose episode terminated is left as it is (a resume between episodes changes nothing)."""
        newest = (self.pos - 1 - np.arange(min(self.num_envs, self.size))) % self.capacity
        self.truncated[newest] |= ~self.terminated[newest]

    def sample(self, batch_size: int, rng: np.random.Generator) -> ReplayBatch:
        """A uniform batch (with replacement) as tensors on the buffer's device."""
        idx = rng.integers(0, self.size, size=batch_size)
        series = [(self.rewards, self.gamma)] + ([(self.costs, self.cost_gamma)] if self.costs is not None else [])
        if self.n_step > 1:
            sums, last, steps = self._n_step_sums(idx, series)
        else:  # the one-step transition: its own reward (and cost) and s'
            sums, last, steps = [values[idx] for values, _ in series], idx, np.ones(batch_size, np.int64)
        to = lambda x: torch.as_tensor(x, device=self.device)  # noqa: E731
        batch = ReplayBatch(to(self.obs[idx]), to(self.actions[idx]), to(sums[0]), to(self.next_obs[last]),
                            to(self.terminated[last].astype(np.float32)),
                            to((self.gamma ** steps).astype(np.float32)))
        if self.costs is None:
            return batch
        return batch._replace(costs=to(sums[1]), cost_discount=to((self.cost_gamma ** steps).astype(np.float32)))

    def _n_step_sums(self, idx: np.ndarray, series: list[tuple[np.ndarray, float]]
                     ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
        """For rows ``idx`` (B,) and each (values, discount) of ``series`` (the rewards, then the
        costs): the discounted sum of up to ``n_step`` values of each row's env, stopping after an
        episode's end or at the newest row stored (one mask for every series, so costs are cut
        where rewards are); the last row summed (whose s' and terminated the target bootstraps
        from) and how many steps were summed (m)."""
        sums = [values[idx].astype(np.float64) for values, _ in series]
        last, steps = idx.copy(), np.ones(len(idx), np.int64)
        rows_after = (self.pos - 1 - idx) % self.capacity   # rows written after each sampled one
        going = ~(self.terminated[idx] | self.truncated[idx])
        for k in range(1, self.n_step):
            going &= k * self.num_envs <= rows_after
            row = (idx + k * self.num_envs) % self.capacity
            for total, (values, gamma) in zip(sums, series):
                total += np.where(going, gamma ** k * values[row], 0.0)
            last = np.where(going, row, last)
            steps += going
            going &= ~(self.terminated[row] | self.truncated[row])
        return [total.astype(np.float32) for total in sums], last, steps

    # Checkpointing: the filled rows as tensors (safetensors) plus the ring position (JSON);
    # ``self.fields`` adds "costs" to these when the buffer keeps them.
    _FIELDS = ("obs", "next_obs", "actions", "rewards", "terminated", "truncated")

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        tensors = {f"replay/{name}": torch.from_numpy(np.ascontiguousarray(getattr(self, name)[: self.size]))
                   for name in self.fields}
        return tensors, {"pos": self.pos, "size": self.size, "capacity": self.capacity}

    def load_state(self, tensors: dict[str, torch.Tensor], meta: dict) -> None:
        if meta["capacity"] != self.capacity:
            raise DrivelabError(f"the checkpoint's replay buffer holds {meta['capacity']} transitions, "
                                f"the config asks for {self.capacity}; resume with the same buffer_size")
        size = int(meta["size"])
        for name in self.fields:
            getattr(self, name)[:size] = tensors[f"replay/{name}"].numpy()
        self.pos, self.size = int(meta["pos"]), size
