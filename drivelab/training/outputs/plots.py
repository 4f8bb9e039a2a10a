"""Training curves of one or more runs (``drivelab plot``), headless with matplotlib.

By default four panels (episode return, entropy, value/critic loss, policy/actor loss), the
ones that tell whether a policy-gradient run learns, plus success rate and route completion for driving envs and the periodic
evaluation's return when there is one. Each curve is a rolling mean over ``window`` logged
points. Runs whose configs are equal but for the seed (and run directory) form a group, drawn
as the mean over seeds with a 95% confidence band (t-distribution over the seeds' curves,
interpolated onto common steps).
"""

from __future__ import annotations

import csv
from collections import defaultdict
from pathlib import Path

import numpy as np
import yaml

from drivelab.errors import DrivelabError
from drivelab.training.outputs.statistics import mean_and_band, rolling_mean

# panel title -> metric names, the first one a run logged is drawn (a panel no run logged is left out:
# the cost panels appear for envs with a cost, the multiplier for the constrained algorithms)
DEFAULT_PANELS = {
    "episode return": ("episode/return",),
    "entropy": ("loss/entropy", "charts/entropy"),
    "value / critic loss": ("loss/value", "loss/critic"),
    "policy / actor loss": ("loss/policy", "loss/actor"),
    "success rate": ("episode/success_rate",),
    "route completion": ("episode/route_completion",),
    "episode cost": ("episode/cost",),
    "Lagrange multiplier": ("charts/lagrange_multiplier",),
    "evaluation return": ("eval/return_mean",),
    "evaluation cost": ("eval/cost",),
}


def read_metrics(run_dir: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """metric -> (steps, wall seconds since the first log, values) from ``RUN/metrics.csv``."""
    path = Path(run_dir) / "metrics.csv"
    if not path.is_file():
        raise DrivelabError(f"not a drivelab run directory (no metrics.csv): {run_dir}")
    rows: dict[str, list[tuple[int, float, float]]] = defaultdict(list)
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            try:
                rows[row["name"]].append((int(row["step"]), float(row["time"]), float(row["value"])))
            except (KeyError, TypeError, ValueError):
                continue  # a half-written last line of a killed run
    start = min((r[0][1] for r in rows.values() if r), default=0.0)
    return {name: (np.array([r[0] for r in rs]), np.array([r[1] for r in rs]) - start, np.array([r[2] for r in rs]))
            for name, rs in rows.items()}


def group_runs(run_dirs: list[Path]) -> dict[str, list[Path]]:
    """Runs with the same config but for seed and run directory, keyed by a short label: "algo on
    env", and where several groups share that, every one of them with the fields that set it apart
    (``ppo on CartPole-v1 (lr=0.001)``)."""
    configs: dict[str, dict] = {}
    groups: dict[str, list[Path]] = defaultdict(list)
    for run in run_dirs:
        config_file = run / "config.yaml"
        config = yaml.safe_load(config_file.read_text()) if config_file.is_file() else {}
        config = {k: v for k, v in (config if isinstance(config, dict) else {}).items() if k not in ("seed", "run_dir")}
        key = yaml.safe_dump(config, sort_keys=True)
        configs[key] = config
        groups[key].append(run)
    base = {key: f"{c.get('algo', '?')} on {(c.get('env') or {}).get('id', '?')}" for key, c in configs.items()}
    flat = {key: _flat(c) for key, c in configs.items()}
    labels = {}
    for key, label in base.items():
        twins = [other for other in base if base[other] == label]
        if len(twins) > 1:
            differing = [name for name in flat[key] if len({repr(flat[t].get(name)) for t in twins}) > 1]
            shown = ", ".join(f"{name.split('.')[-1]}={_short(flat[key].get(name))}" for name in differing[:3])
            label = f"{label} ({shown or groups[key][0].name})"
        labels[key] = label
    return {labels[key]: members for key, members in groups.items()}


def _short(value: object) -> object:
    return float(f"{value:.3g}") if isinstance(value, float) else value


def _flat(data: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def default_panels(logged: list[dict[str, object]]) -> dict[str, tuple[str, ...]]:
    """The :data:`DEFAULT_PANELS` that some run logged a metric of (``logged``: each run's metrics
    by name, as :func:`read_metrics` returns them)."""
    return {title: names for title, names in DEFAULT_PANELS.items() if any(n in run for run in logged for n in names)}


def last_metrics(run_dir: str | Path) -> dict[str, float]:
    """The last logged value of each metric in ``RUN/metrics.csv`` (a run's final metrics)."""
    return {name: float(values[-1]) for name, (_, _, values) in read_metrics(run_dir).items()}


def plot_runs(run_dirs: list[str | Path], out: str | Path, metrics: list[str] | None = None, window: int = 10,
              x_axis: str = "steps") -> Path:
    """Draw the runs' curves into ``out`` (PNG): one panel per metric (or per default panel)."""
    if window < 1:
        raise DrivelabError(f"--window (the rolling mean's length) must be >= 1, got {window}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [Path(r) for r in run_dirs]
    data = {run: read_metrics(run) for run in runs}
    if metrics:
        panels = {name: (name,) for name in metrics}
    else:
        panels = default_panels([data[run] for run in runs])
    if not panels:
        raise DrivelabError(f"none of the metrics to plot were logged by {', '.join(map(str, runs))}")
    cols = min(3, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.6 * rows), squeeze=False)
    for ax, (title, names) in zip(axes.flat, panels.items()):
        for label, members in group_runs(runs).items():
            curves = []
            for run in members:
                name = next((n for n in names if n in data[run]), None)
                if name is not None:
                    steps, seconds, values = data[run][name]
                    curves.append((steps if x_axis == "steps" else seconds, rolling_mean(values, window)))
            if not curves:
                continue
            x, mean, low, high = mean_and_band(curves) if len(curves) > 1 else (*curves[0], None, None)
            line, = ax.plot(x, mean, marker="o" if len(x) < 3 else None,  # a point or two: visible as markers
                            label=label + (f" ({len(curves)} seeds)" if len(curves) > 1 else ""))
            if low is not None:
                ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2)
        ax.set_title(title)
        ax.set_xlabel("env steps" if x_axis == "steps" else "wall time (s)")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=min(3, len(handles)), fontsize=9)
    fig.tight_layout(rect=(0, 0.06 if handles else 0, 1, 1))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
