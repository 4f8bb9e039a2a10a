"""Per-episode bookkeeping shared by training and evaluation.

Driving envs report, in ``info`` at every step, whether the episode has so far ended in success,
crashed or left the road, and how much of the route is done (see
:mod:`drivelab.envs.metadrive`). Any env that reports these keys gets driving metrics; others
get return and length only. No trainer needs to know which env it runs.
"""

from __future__ import annotations

from collections import deque

import numpy as np

# info key at the last step of an episode -> metric name (a mean over episodes)
DRIVING_METRICS = {
    "success": "success_rate",
    "crash": "crash_rate",
    "out_of_road": "out_of_road_rate",
    "route_completion": "route_completion",
    "mean_abs_cte": "mean_abs_cte",          # metres from the lane centre, averaged over the episode
}


def episode_info(info: dict, index: int) -> dict[str, float]:
    """Driving metrics of sub-env ``index`` from a vector env's batched ``info``, and the episode
    sums of shaped reward terms (``reward/<term>``, see :mod:`drivelab.envs.rewards`)."""
    out = {}
    for key in info:
        metric = DRIVING_METRICS.get(key) or (key if key.startswith("reward/") else None)
        if metric and info.get(f"_{key}", np.ones(index + 1, bool))[index]:
            out[metric] = float(info[key][index])
    return out


class EpisodeStats:
    """The last ``window`` finished episodes: return, length and driving metrics."""

    def __init__(self, window: int = 20):
        self.returns: deque[float] = deque(maxlen=window)
        self.lengths: deque[int] = deque(maxlen=window)
        self.extra: dict[str, deque[float]] = {}
        self.window = window
        self.total_episodes = 0

    def add(self, episode_return: float, length: int, metrics: dict[str, float]) -> None:
        self.returns.append(float(episode_return))
        self.lengths.append(int(length))
        for name, value in metrics.items():
            self.extra.setdefault(name, deque(maxlen=self.window)).append(value)
        self.total_episodes += 1

    def means(self, prefix: str = "episode/") -> dict[str, float]:
        if not self.returns:
            return {}
        out = {f"{prefix}return": float(np.mean(self.returns)), f"{prefix}length": float(np.mean(self.lengths))}
        out.update({f"{prefix}{name}": float(np.mean(values)) for name, values in self.extra.items()})
        return out
