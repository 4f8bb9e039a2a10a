"""Small statistics shared by plots, tables and model cards: rolling means and 95% confidence
intervals over seeds or episodes."""

from __future__ import annotations

import numpy as np


def rolling_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last ``window`` values at each point (fewer at the start)."""
    cumulative = np.cumsum(np.insert(np.asarray(values, np.float64), 0, 0.0))
    end = np.arange(1, len(values) + 1)
    start = np.maximum(end - window, 0)
    return (cumulative[end] - cumulative[start]) / (end - start)


def mean_and_ci95(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over axis 0 and the half-width of its 95% confidence interval (Student's t with
    n - 1 dof; 0 for a single sample)."""
    from scipy import stats

    samples = np.asarray(samples, float)
    mean = samples.mean(axis=0)
    if len(samples) < 2:
        return mean, np.zeros_like(mean)
    return mean, stats.t.ppf(0.975, len(samples) - 1) * samples.std(axis=0, ddof=1) / np.sqrt(len(samples))


def mean_and_band(curves: list[tuple[np.ndarray, np.ndarray]], points: int = 200) -> tuple[np.ndarray, ...]:
    """(x, mean, low, high) of several (x, y) curves on a common grid over their shared range;
    the band is the 95% confidence interval of the mean (:func:`mean_and_ci95`)."""
    lo, hi = max(c[0][0] for c in curves), min(c[0][-1] for c in curves)
    grid = np.linspace(lo, hi, points) if hi > lo else np.array([lo])
    mean, half = mean_and_ci95(np.stack([np.interp(grid, x, y) for x, y in curves]))
    return grid, mean, mean - half, mean + half
