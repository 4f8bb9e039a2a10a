"""Safe driving on MetaDrive's safety task, over methods and seeds: one table and one PNG. Not a test.

    python benchmarks/safe_drive.py --seeds 0 1 2 3 4 --runs runs/safe \\
        --out benchmarks/results/safe_drive.json

Methods (``--arms``, each a config of ``drivelab/configs``):

* ``unconstrained``: the drive recipe (SAC) on SafeMetaDrive, cost ignored (``safe_drive_unconstrained``);
* ``shaping``: the same with the cost as a fixed reward penalty (``safe_drive_shaping``);
* ``sac_lag``: the constrained recipe, SAC-Lagrangian with a PID multiplier (``safe_drive``);
* ``early_termination``: SAC on the early-terminated MDP, where a training episode ends at its
  first cost (``safe_drive_early_termination``; Sun et al. 2021);
* ``ppo_lag``: PPO-Lagrangian, the baseline the field reproduces (``ppo_lag_safe_metadrive``);
* ``ppo``: the same PPO with the cost ignored, PPO-Lagrangian's own reference (``ppo_safe_metadrive``).

For each method and seed: train RUNS/ARM/seed_N for its config's ``steps`` (decisions, env steps:
a budget that means the same on every CPU, ``--steps`` to change it; the minutes it took are
recorded with the CPU gauge beside them; an interrupted run resumes, a finished one is kept), then
evaluate the run's own choice,
``checkpoints/best`` (picked during training on scenarios 200-229), on the 200 unseen scenarios
0-199 of SafeMetaDrive-validation-v0 with deterministic actions. MetaDrive's expert and the random
policy play the same 200. Per method the JSON holds each seed's test success, episode cost, cost
rate, crash, out-of-road and route completion, its cumulative training cost (the cost of every
training episode: how much harm happened while learning), minutes and decisions; over seeds the
mean with its 95% confidence interval and the minimum; and the issue's goals checked against the
unconstrained method. The PNG plots success and cost on the selection scenarios against training
minutes and against decisions, and the cumulative training cost against decisions.

Each finished method and seed is kept as a record, ``RECORDS/ARM_seedN.json`` (its provenance:
command, commit, versions, CPU and gauge), and the expert's and random's episodes as
``RECORDS/baselines.json``. The table is made from every record in RECORDS, so a 5-seed table
can be filled over several sittings (one method and seed takes about 40 minutes on two cores):
running the command again trains only what has no record. A record made with another config file
or budget is refused, not mixed in.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
from drive_recipe import train_seed
from provenance import provenance  # benchmarks/provenance.py

from drivelab.api import baseline_env, evaluate_baseline, evaluate_checkpoint
from drivelab.config import parse_value, read_yaml
from drivelab.training.outputs.checkpoint import checkpoint_step
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.outputs.statistics import mean_and_ci95

CONFIGS = Path(__file__).resolve().parent.parent / "drivelab" / "configs"
ARMS = {"unconstrained": "safe_drive_unconstrained", "shaping": "safe_drive_shaping", "sac_lag": "safe_drive",
        "early_termination": "safe_drive_early_termination", "ppo_lag": "ppo_lag_safe_metadrive",
        "cost_budget": "safe_drive_cost_budget", "ppo": "ppo_safe_metadrive"}
HELDOUT_ENV, EPISODES = "SafeMetaDrive-validation-v0", 200
METRICS = ("success_rate", "cost", "cost_rate", "crash_rate", "out_of_road_rate", "route_completion")
CONSTRAINED = "sac_lag"   # whose cost_limit is the table's
SAFE_ARMS = ("sac_lag", "early_termination", "cost_budget", "shaping", "ppo_lag")   # the goals are checked for each
RECORDS = Path(__file__).resolve().parent / "results" / "safe_drive_runs"


def heldout(run_dir: Path, episodes: int) -> dict:
    """The run's checkpoints/best on the held-out scenarios (cached in RUN/heldout.json, with each
    episode's outcomes: played again for a cache without them)."""
    cache = run_dir / "heldout.json"
    if cache.is_file() and "per_episode" in (kept := json.loads(cache.read_text())):
        return kept
    best = run_dir / "checkpoints" / "best"
    result, _, _ = evaluate_checkpoint(best, episodes, HELDOUT_ENV, num_envs=2)
    row = {**outcomes(result), "step": checkpoint_step(best)}
    cache.write_text(json.dumps(row) + "\n")
    return row


def outcomes(result) -> dict:
    """The means of METRICS and, under ``per_episode``, each episode's outcomes and length (for a
    model card, benchmarks/ship_driver.py; the cost rate is the total cost over the total length)."""
    summary = result.summary()
    per_episode = {m: [round(float(x), 4) for x in result.metrics[m]] for m in METRICS if m in result.metrics}
    return {**{m: summary[m] for m in METRICS if m in summary},
            "per_episode": {**per_episode, "length": [int(n) for n in result.lengths]}}


def training_record(run_dir: Path) -> dict:
    """The cumulative training cost (its final value and its curve against decisions) and the
    curves of the in-training evaluations on the selection scenarios (against decisions and minutes)."""
    metrics = read_metrics(run_dir)
    out = {}
    if "charts/cumulative_cost" in metrics:
        steps, _, values = metrics["charts/cumulative_cost"]
        out["training_cost"] = float(values[-1])
        out["training_cost_curve"] = {"steps": [int(x) for x in steps], "cost": [round(float(x), 2) for x in values]}
    for name, key in (("success", "eval/success_rate"), ("cost", "eval/cost")):
        if key in metrics:
            steps, seconds, values = metrics[key]
            selection = out.setdefault("selection", {})
            selection.update(steps=[int(x) for x in steps], minutes=[round(float(x), 2) for x in seconds / 60])
            selection[name] = [float(x) for x in values]
    return out


def config_sha256(config: Path) -> str:
    return hashlib.sha256(config.read_bytes()).hexdigest()


def check_record(record: dict, path: Path, config: Path, overrides: dict) -> dict:
    """``record`` (read from ``path``); one line (SystemExit) when it was made with another config
    file or other overrides: its numbers would not be this method's at this budget."""
    if record.get("config_sha256") != config_sha256(config) or record.get("overrides") != overrides:
        raise SystemExit(f"{path}: made with another version of {config.name} or other overrides "
                         f"({record.get('overrides')}); move it out of {path.parent} to measure again")
    return record


def read_record(path: Path, config: Path, overrides: dict) -> dict | None:
    """The record at ``path`` if there is one (:func:`check_record`)."""
    return check_record(json.loads(path.read_text()), path, config, overrides) if path.is_file() else None


def records_in(folder: Path) -> dict[str, dict[str, dict]]:
    """Every record in ``folder``: arm -> seed -> record, in ARMS' order and by seed."""
    found: dict[str, dict[str, dict]] = {}
    for path in sorted(folder.glob("*_seed*.json")):
        record = json.loads(path.read_text())
        found.setdefault(record["arm"], {})[str(record["seed"])] = record
    return {arm: dict(sorted(found[arm].items(), key=lambda kv: int(kv[0]))) for arm in ARMS if arm in found}


def baseline_outcomes(folder: Path, names: list[str], episodes: int) -> dict:
    """The reference policies on the held-out scenarios, kept in FOLDER/baselines.json (with its
    provenance) and played again only for a policy, an episode count or the per-episode outcomes it lacks."""
    path = folder / "baselines.json"
    kept = json.loads(path.read_text()) if path.is_file() else {}
    if kept.get("episodes") != episodes:
        kept = {"episodes": episodes, "policies": {}}
    missing = [name for name in names if "per_episode" not in kept["policies"].get(name, {})]
    if missing:
        started = time.time()
        for name in missing:
            kept["policies"][name] = outcomes(evaluate_baseline(name, baseline_env(env_id=HELDOUT_ENV), episodes))
        kept["provenance"] = provenance(started)
        path.write_text(json.dumps(kept, indent=1) + "\n")
    return {name: kept["policies"][name] for name in names}


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
    """The issue's goals for each safe method (every arm but the unconstrained one) against the
    unconstrained one: arm -> goal -> met."""
    if "unconstrained" not in arms:
        return {}
    free = arms["unconstrained"]["summary"]
    checked = {}
    for arm in (name for name in SAFE_ARMS if name in arms):
        safe, seeds = arms[arm]["summary"], arms[arm]["seeds"].values()
        out = {"test_cost_at_most_a_third": safe["cost"]["mean"] <= free["cost"]["mean"] / 3,
               "success_within_3_points": safe["success_rate"]["mean"] >= free["success_rate"]["mean"] - 0.03}
        if "training_cost" in safe and "training_cost" in free:
            out["training_cost_at_most_half"] = safe["training_cost"]["mean"] <= free["training_cost"]["mean"] / 2
        if cost_limit is not None:
            out["every_seed_within_cost_limit"] = all(row["cost"] <= cost_limit for row in seeds)
        checked[arm] = out
    return checked


def plot(arms: dict, cost_limit: float | None, out: Path) -> None:
    """Top: success and episode cost on the selection scenarios against training minutes and the
    cumulative training cost against decisions; bottom: the same two curves against decisions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(2, 3, figsize=(16, 8.4))
    colors = {arm: f"C{i}" for i, arm in enumerate(ARMS)}   # one colour of the default cycle per method
    for arm, data in arms.items():
        for i, (seed, row) in enumerate(data["seeds"].items()):
            label = arm if i == 0 else None
            curve = row.get("selection", {})
            for column, name in enumerate(("success", "cost")):
                if name in curve:
                    axes[0, column].plot(curve["minutes"], curve[name], "-o", ms=3, color=colors[arm], alpha=0.6, label=label)
                    axes[1, column].plot(curve["steps"], curve[name], "-o", ms=3, color=colors[arm], alpha=0.6, label=label)
            if "training_cost_curve" in row:
                spent = row["training_cost_curve"]
                axes[0, 2].plot(spent["steps"], spent["cost"], "-", color=colors[arm], alpha=0.6, label=label)
    if cost_limit is not None:
        for ax in axes[:, 1]:
            ax.axhline(cost_limit, color="black", linestyle="--", label=f"cost_limit {cost_limit}")
    for row, xlabel in enumerate(("training wall clock (minutes, 2 CPU cores)", "decisions (env steps)")):
        for column, label in enumerate(("success rate (scenarios 200-229)", "episode cost (scenarios 200-229)")):
            axes[row, column].set_xlabel(xlabel)
            axes[row, column].set_ylabel(label)
    for ax in (*axes[1, :2], axes[0, 2]):  # decisions in thousands: 200000 would run into its neighbours
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda x, _: f"{x / 1000:g}k"))
    axes[0, 2].set_xlabel("decisions (env steps)")
    axes[0, 2].set_ylabel("cumulative training cost")
    axes[1, 2].axis("off")
    for ax in axes.flat[:5]:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("safe driving on SafeMetaDrive: success and cost while training, and the cost of learning")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--steps", type=int, help="decisions (env steps) per run for every arm (default: each config's)")
    parser.add_argument("--runs", type=Path, default=Path("runs/safe"))
    parser.add_argument("--records", type=Path, default=RECORDS,
                        help="one JSON per method and seed; the table is made from all of them")
    parser.add_argument("--episodes", type=int, default=EPISODES, help="held-out scenarios (0..N-1)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/safe_drive.json"))
    parser.add_argument("--baselines", nargs="*", default=["metadrive-expert", "random"],
                        help="reference policies on the same scenarios (none: --baselines)")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="overrides for every arm, e.g. eval.episodes=10 for a smoke run")
    args = parser.parse_args()
    started = time.time()
    overrides = {key: parse_value(value) for key, _, value in (item.partition("=") for item in args.set)}
    if args.steps is not None:  # a budget in decisions: a slow CPU takes longer instead of learning less
        overrides.update(steps=args.steps, max_minutes=None)
    args.records.mkdir(parents=True, exist_ok=True)
    for arm in args.arms:
        config = CONFIGS / f"{ARMS[arm]}.yaml"
        for seed in args.seeds:
            path = args.records / f"{arm}_seed{seed}.json"
            if read_record(path, config, overrides) is not None:
                continue
            run_dir = args.runs / arm / f"seed_{seed}"
            try:
                trained = train_seed(str(config), seed, run_dir, overrides)
            except KeyboardInterrupt:
                raise SystemExit(f"interrupted; the same command resumes {arm} seed {seed} in {run_dir}") from None
            record = {"arm": arm, "seed": seed, "config": str(config.relative_to(CONFIGS.parent.parent)),
                      "config_sha256": config_sha256(config), "overrides": overrides, "episodes": args.episodes,
                      **trained, **{k: v for k, v in heldout(run_dir, args.episodes).items() if k != "per_episode"},
                      **training_record(run_dir)}
            path.write_text(json.dumps(record, indent=1) + "\n")
            print(json.dumps({k: v for k, v in record.items() if k not in ("selection", "training_cost_curve")}),
                  flush=True)
    arms = {}
    for arm, seeds in records_in(args.records).items():
        config = CONFIGS / f"{ARMS[arm]}.yaml"
        for seed, record in seeds.items():  # every record in the table is this config's at this budget
            check_record(record, args.records / f"{arm}_seed{seed}.json", config, overrides)
        arms[arm] = {"config": seeds[next(iter(seeds))]["config"], "seeds": seeds,
                     "summary": summarise(list(seeds.values()))}
    baselines = baseline_outcomes(args.records, args.baselines, args.episodes)
    limit = read_yaml(CONFIGS / f"{ARMS[CONSTRAINED]}.yaml").get("sac_lag", {}).get("cost_limit")
    result = {"benchmark": "safe-drive", **provenance(started), "overrides": overrides, "cost_limit": limit,
              "records": str(args.records),
              "protocol": f"train on each config's SafeMetaDrive split for its steps (decisions); report "
                          f"checkpoints/best, chosen on scenarios 200-229 during training, on the unseen scenarios "
                          f"0-{args.episodes - 1} of {HELDOUT_ENV} (deterministic actions); each seed's record "
                          f"holds its own commit, minutes and CPU gauge",
              "arms": arms, "baselines": baselines, "goals": goals(arms, limit)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    plot(arms, limit, args.out.with_suffix(".png"))
    for arm, data in arms.items():
        s = data["summary"]
        print(f"{arm:14s} {s['success_rate']['seeds']} seeds  success {s['success_rate']['mean']:.3f} ± "
              f"{s['success_rate']['ci95']:.3f}  cost {s['cost']['mean']:.2f} ± {s['cost']['ci95']:.2f}  "
              f"training cost {s.get('training_cost', {}).get('mean', float('nan')):.0f}")
    print(json.dumps(result["goals"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
