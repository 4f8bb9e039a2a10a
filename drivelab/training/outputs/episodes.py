"""Episode bookkeeping, one tracker for every algorithm and for evaluation.

Driving envs report, in ``info`` at every step, whether the episode has so far ended in success,
crashed or left the road, and how much of the route is done (see
:mod:`drivelab.envs.metadrive`). Any env that reports these keys gets driving metrics; others
get return and length only. No trainer needs to know which env it runs.

The tracker reads a vector env's batched ``info`` in both autoreset modes that drivelab uses:
with ``SAME_STEP`` the ended episode's info is under ``info["final_info"]`` (the top level
already belongs to the next episode); with ``DISABLED`` it is the top level itself.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np

# info key at the last step of an episode -> metric name (a mean over episodes)
DRIVING_METRICS = {
    "success": "success_rate",
    "crash": "crash_rate",
    "out_of_road": "out_of_road_rate",
    "timeout": "timeout_rate",               # the step limit ended the episode before the destination
    "route_completion": "route_completion",
    "mean_abs_cte": "mean_abs_cte",          # metres from the lane centre, averaged over the episode
    "replayed": "replay_rate",               # the episode replayed a failed scenario (envs.wrappers.ScenarioReplay)
    "episode_cost": "cost",                  # the episode's summed cost (envs.costs.CostSignal)
    "stuck": "stuck_rate",                   # ended: the car stood still, or stayed pinned in a collision (envs.metadrive)
    "rolled_over": "rollover_rate",          # ended because the car lay on its side or roof (envs.metadrive)
}


def is_episode_metric(key: str) -> bool:
    """Whether the tracker keeps this ``info`` key: a driving metric, or the episode sum of a
    shaped reward term (``reward/<term>``, see :mod:`drivelab.envs.rewards`) or of a cost term
    (``cost/<term>``, see :mod:`drivelab.envs.costs`)."""
    return key in DRIVING_METRICS or key.startswith(("reward/", "cost/"))


def step_costs(info: dict, done: np.ndarray) -> np.ndarray:
    """(n,) the cost of each env's last step, from a vector env's batched ``info`` (``info["cost"]``,
    which :class:`drivelab.envs.costs.CostSignal` puts there): for an env whose episode ended
    under ``SAME_STEP`` autoreset, from ``final_info`` (the top level is the next episode's reset).
    Envs without a cost (missing key) cost 0."""
    n = len(done)
    costs = np.zeros(n)
    if "cost" in info:
        costs[:] = np.where(info.get("_cost", np.ones(n, bool)), info["cost"], 0.0)
    final = info.get("final_info")
    if final and "cost" in final:
        ended = done & final.get("_cost", np.ones(n, bool))
        costs[ended] = np.asarray(final["cost"])[ended]
    return costs


def episode_info(info: dict, index: int) -> dict[str, float]:
    """The episode metrics (:func:`is_episode_metric`) of sub-env ``index`` from a vector env's
    batched ``info``, under their logged names."""
    out = {}
    for key in info:
        if is_episode_metric(key) and info.get(f"_{key}", np.ones(index + 1, bool))[index]:
            out[DRIVING_METRICS.get(key, key)] = float(info[key][index])
    return out


class Episode(NamedTuple):
    env: int                      # index of the sub-env that played it
    ret: float                    # undiscounted return
    length: int
    metrics: dict[str, float]     # driving metrics and reward-term sums, where the env reports them


class EpisodeTracker:
    """Running return and length of each of ``num_envs`` envs, and the last ``window`` finished
    episodes (their means are what training logs as ``episode/*``)."""

    def __init__(self, num_envs: int, window: int = 20):
        self.running_return = np.zeros(num_envs)
        self.running_length = np.zeros(num_envs, np.int64)
        self.returns: deque[float] = deque(maxlen=window)
        self.lengths: deque[int] = deque(maxlen=window)
        self.extra: dict[str, deque[float]] = {}
        self.window = window
        self.total_episodes = 0
        # Every counted episode's cost, summed since the run began (the safe-exploration measure,
        # and what the Lagrange multiplier reads), and the episodes that reported one.
        self.cost_total, self.cost_episodes = 0.0, 0

    def step(self, rewards: np.ndarray, done: np.ndarray, info: dict,
             counted: np.ndarray | None = None, first_env: int = 0) -> list[Episode]:
        """Add one vector step (rewards, done = terminated | truncated, both (n,)) of the envs
        ``first_env .. first_env + n - 1`` (all N by default; a group of them when groups of envs
        step on their own, see :class:`drivelab.envs.groups.EnvGroups`). Returns the episodes
        that ended at this step; those where ``counted`` (default: all) also enter the window
        (REINFORCE and GRPO do not count the episodes of envs that idle, masked)."""
        envs = slice(first_env, first_env + len(rewards))
        self.running_return[envs] += rewards
        self.running_length[envs] += 1
        if not done.any():
            return []
        source = info.get("final_info", info)
        ended = []
        for i in np.flatnonzero(done):
            env = first_env + int(i)
            episode = Episode(env, float(self.running_return[env]), int(self.running_length[env]), episode_info(source, i))
            ended.append(episode)
            if counted is None or counted[i]:
                self.add(episode)
            self.running_return[env] = 0.0
            self.running_length[env] = 0
        return ended

    def restart(self, mask: np.ndarray) -> None:
        """Zero the running sums of the envs in ``mask`` (reset by the trainer mid-episode)."""
        self.running_return[mask] = 0.0
        self.running_length[mask] = 0

    def add(self, episode: Episode) -> None:
        """Count a finished episode (for the multi-agent collector, which tracks each car itself)."""
        self.returns.append(episode.ret)
        self.lengths.append(episode.length)
        for name, value in episode.metrics.items():
            self.extra.setdefault(name, deque(maxlen=self.window)).append(value)
        self.total_episodes += 1
        if "cost" in episode.metrics:
            self.cost_total += episode.metrics["cost"]
            self.cost_episodes += 1

    def state(self) -> dict:
        """The window of finished episodes, JSON-able (checkpointed, so a resumed run logs the
        same means as an uninterrupted one)."""
        return {"returns": list(self.returns), "lengths": list(self.lengths),
                "extra": {name: list(values) for name, values in self.extra.items()}, "total": self.total_episodes,
                "cost_total": self.cost_total, "cost_episodes": self.cost_episodes}

    def load_state(self, state: dict) -> None:
        self.returns.extend(state["returns"])
        self.lengths.extend(state["lengths"])
        for name, values in state["extra"].items():
            self.extra.setdefault(name, deque(maxlen=self.window)).extend(values)
        self.total_episodes = int(state["total"])
        self.cost_total = float(state.get("cost_total", 0.0))  # absent in checkpoints written before costs
        self.cost_episodes = int(state.get("cost_episodes", 0))

    def means(self, prefix: str = "episode/") -> dict[str, float]:
        if not self.returns:
            return {}
        out = {f"{prefix}return": float(np.mean(self.returns)), f"{prefix}length": float(np.mean(self.lengths))}
        out.update({f"{prefix}{name}": float(np.mean(values)) for name, values in self.extra.items()})
        return out


def stack_infos(infos: list[dict[str, float]]) -> dict[str, np.ndarray]:
    """One info dict per env -> a vector env's batched ``info`` (``key`` and its mask ``_key``)."""
    stacked = {}
    for key in dict.fromkeys(key for info in infos for key in info):  # first-seen order, not a set's
        stacked[key] = np.array([info.get(key, 0.0) for info in infos])
        stacked[f"_{key}"] = np.array([key in info for info in infos])
    return stacked
