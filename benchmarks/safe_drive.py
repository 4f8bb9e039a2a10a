"""Safe driving on MetaDrive's safety task, over methods and seeds: one table and one PNG. Not a test.

    python benchmarks/safe_drive.py --seeds 0 1 2 3 4 --runs runs/safe \\
        --out benchmarks/results/safe_drive.json

Methods (``--arms``, each a config of ``drivelab/configs``):

* ``unconstrained``: the drive recipe (SAC) on SafeMetaDrive, cost ignored (``safe_drive_unconstrained``);
* ``shaping``: the same with the cost as a fixed reward penalty (``safe_drive_shaping``);
* ``sac_lag``: the constrained recipe, SAC-Lagrangian with a PID multiplier (``safe_drive``);
* ``ppo_lag``: PPO-Lagrangian, the baseline the field reproduces (``ppo_lag_safe_metadrive``).

For each method and seed: train RUNS/ARM/seed_N (the config's ``max_minutes`` bounds the wall
clock; an interrupted run resumes, a finished one is kept), then evaluate the run's own choice,
``checkpoints/best`` (picked during training on scenarios 200-229), on the 200 unseen scenarios
0-199 of SafeMetaDrive-validation-v0 with deterministic actions. MetaDrive's expert and the random
policy play the same 200. Per method the JSON holds each seed's test success, episode cost, cost
rate, crash, out-of-road and route completion, its cumulative training cost (the cost of every
training episode: how much harm happened while learning), minutes and decisions; over seeds the
mean with its 95% confidence interval and the minimum; and the issue's goals checked against the
unconstrained method. The PNG plots success and cost on the selection scenarios against training
minutes. Every result is cached in the run directories, so running it again does what is missing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from drive_recipe import cpu_gauge_ms, train_seed
from provenance import provenance  # benchmarks/provenance.py

from drivelab.api import baseline_env, evaluate_baseline, evaluate_checkpoint
from drivelab.config import parse_value, read_yaml
from drivelab.training.outputs.checkpoint import checkpoint_step
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.outputs.statistics import mean_and_ci95

CONFIGS = Path(__file__).resolve().parent.parent / "drivelab" / "configs"
ARMS = {"unconstrained": "safe_drive_unconstrained", "shaping": "safe_drive_shaping", "sac_lag": "safe_drive",
        "ppo_lag": "ppo_lag_safe_metadrive"}
HELDOUT_ENV, EPISODES = "SafeMetaDrive-validation-v0", 200
METRICS = ("success_rate", "cost", "cost_rate", "crash_rate", "out_of_road_rate", "route_completion")
CONSTRAINED = "sac_lag"


def heldout(run_dir: Path, episodes: int) -> dict:
    """The run's checkpoints/best on the held-out scenarios (cached in RUN/heldout.json)."""
    cache = run_dir / "heldout.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    best = run_dir / "checkpoints" / "best"
    result, _, _ = evaluate_checkpoint(best, episodes, HELDOUT_ENV, num_envs=2)
    row = {**outcomes(result), "step": checkpoint_step(best)}
    cache.write_text(json.dumps(row) + "\n")
    return row


def outcomes(result) -> dict:
    summary = result.summary()
    return {m: summary[m] for m in METRICS if m in summary}


def training_record(run_dir: Path) -> dict:
    """The cumulative training cost and the curves of the in-training evaluations (selection scenarios)."""
    metrics = read_metrics(run_dir)
    out = {}
    if "charts/cumulative_cost" in metrics:
        out["training_cost"] = float(metrics["charts/cumulative_cost"][2][-1])
    for name, key in (("success", "eval/success_rate"), ("cost", "eval/cost")):
        if key in metrics:
            _, seconds, values = metrics[key]
            out.setdefault("selection", {})["minutes"] = [round(float(x), 2) for x in seconds / 60]
            out["selection"][name] = [float(x) for x in values]
    return out


def summarise(rows: list[dict]) -> dict:
    summary = {}
    for metric in (*METRICS, "training_cost", "minutes", "steps"):
        values = np.array([row[metric] for row in rows if metric in row], float)
        if len(values):
            mean, half = mean_and_ci95(values)
            summary[metric] = {"mean": float(mean), "ci95": float(half), "min": float(values.min()),
                               "max": float(values.max()), "seeds": len(values)}
    return summary


def goals(arms: dict, cost_limit: float | None) -> dict:
    """The issue's goals for the constrained method against the unconstrained one."""
    if CONSTRAINED not in arms or "unconstrained" not in arms:
        return {}
    safe, free = arms[CONSTRAINED]["summary"], arms["unconstrained"]["summary"]
    seeds = arms[CONSTRAINED]["seeds"].values()
    out = {"test_cost_at_most_a_third": safe["cost"]["mean"] <= free["cost"]["mean"] / 3,
           "success_within_3_points": safe["success_rate"]["mean"] >= free["success_rate"]["mean"] - 0.03}
    if "training_cost" in safe and "training_cost" in free:
        out["training_cost_at_most_half"] = safe["training_cost"]["mean"] <= free["training_cost"]["mean"] / 2
    if cost_limit is not None:
        out["every_seed_within_cost_limit"] = all(row["cost"] <= cost_limit for row in seeds)
    return out


def plot(arms: dict, cost_limit: float | None, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    colors = dict(zip(arms, ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:red")))
    for arm, data in arms.items():
        for seed, row in data["seeds"].items():
            curve = row.get("selection", {})
            for ax, name in zip(axes, ("success", "cost")):
                if name in curve:
                    ax.plot(curve["minutes"], curve[name], "-", color=colors[arm], alpha=0.6,
                            label=arm if seed == next(iter(data["seeds"])) else None)
    if cost_limit is not None:
        axes[1].axhline(cost_limit, color="black", linestyle="--", label=f"cost_limit {cost_limit}")
    for ax, label in zip(axes, ("success rate (scenarios 200-229)", "episode cost (scenarios 200-229)")):
        ax.set_xlabel("training wall clock (minutes, 2 CPU cores)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("safe driving on SafeMetaDrive: success and cost while training")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--runs", type=Path, default=Path("runs/safe"))
    parser.add_argument("--episodes", type=int, default=EPISODES, help="held-out scenarios (0..N-1)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/safe_drive.json"))
    parser.add_argument("--baselines", nargs="*", default=["metadrive-expert", "random"],
                        help="reference policies on the same scenarios (none: --baselines)")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="overrides for every arm, e.g. max_minutes=5 for a smoke run")
    args = parser.parse_args()
    started = time.time()
    overrides = {key: parse_value(value) for key, _, value in (item.partition("=") for item in args.set)}
    gauge_before = cpu_gauge_ms()
    arms = {}
    for arm in args.arms:
        config = CONFIGS / f"{ARMS[arm]}.yaml"
        seeds = {}
        for seed in args.seeds:
            run_dir = args.runs / arm / f"seed_{seed}"
            try:
                trained = train_seed(str(config), seed, run_dir, overrides)
            except KeyboardInterrupt:
                raise SystemExit(f"interrupted; the same command resumes {arm} seed {seed} in {run_dir}") from None
            seeds[str(seed)] = {**trained, **heldout(run_dir, args.episodes), **training_record(run_dir)}
            print(json.dumps({"arm": arm, "seed": seed, **{k: v for k, v in seeds[str(seed)].items()
                                                            if k != "selection"}}), flush=True)
        arms[arm] = {"config": str(config.relative_to(CONFIGS.parent.parent)), "seeds": seeds,
                     "summary": summarise(list(seeds.values()))}
    baselines = {name: outcomes(evaluate_baseline(name, baseline_env(env_id=HELDOUT_ENV), args.episodes))
                 for name in args.baselines}
    limit = read_yaml(CONFIGS / f"{ARMS[CONSTRAINED]}.yaml").get("sac_lag", {}).get("cost_limit")
    gauge_after = cpu_gauge_ms()  # measured before provenance(), so that its end time follows every measurement
    result = {"benchmark": "safe-drive", **provenance(started), "cpu_gauge_ms": [gauge_before, gauge_after],
              "overrides": overrides, "cost_limit": limit,
              "protocol": f"train on each config's SafeMetaDrive split; report checkpoints/best, chosen on scenarios "
                          f"200-229 during training, on the unseen scenarios 0-{args.episodes - 1} of "
                          f"{HELDOUT_ENV} (deterministic actions)",
              "arms": arms, "baselines": baselines, "goals": goals(arms, limit)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    plot(arms, limit, args.out.with_suffix(".png"))
    for arm, data in arms.items():
        s = data["summary"]
        print(f"{arm:14s} success {s['success_rate']['mean']:.3f} ± {s['success_rate']['ci95']:.3f}  "
              f"cost {s['cost']['mean']:.2f} ± {s['cost']['ci95']:.2f}" if "cost" in s else arm)
    print(json.dumps(result["goals"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
