"""The drive recipe on MetaDrive's benchmark protocol, over seeds: one table and one PNG. Not a test.

    python benchmarks/drive_recipe.py --config configs/drive.yaml --seeds 0 1 2 3 4 --runs runs/drive \\
        --out benchmarks/results/drive_recipe.json
    python benchmarks/drive_recipe.py --config configs/drive.yaml --steps 150000 ...   # a budget in decisions
    ... --set sac.prior_data=demos.safetensors       # with prior data (drivelab demos), its cost in the JSON

For each seed: train RUNS/seed_N with the config (its ``max_minutes`` bounds the training wall
clock; an interrupted run resumes, a finished one is kept), then evaluate the run's own choice,
``checkpoints/best`` (picked during training on validation scenarios 200-229), on the 200 unseen
scenarios of MetaDrive's protocol: start seeds 0-199, default traffic, deterministic actions,
episode k on scenario k. MetaDrive's PPO expert and the random policy play the same 200.

The JSON has, per seed, the held-out success, crash, out-of-road and route completion, the
training wall clock and env steps, the checkpoint's step, the CPU and how fast it was
(``cpu_gauge_ms``, before and after training: one SAC update at ``drive.yaml``'s shapes with
torch's default Adam, ``benchmarks/sac_update_cost.py``'s arm "batch 256, actor_every 2, unfused
Adam", whose cost a run's 30 minutes of decisions follow); over seeds the mean with its 95%
confidence interval (Student's t) and the minimum. The PNG plots success on the selection
scenarios (the in-training evaluations) against training wall-clock minutes per seed, with the
held-out success of the chosen checkpoints and of the baselines. Every result is cached in the
run directories and the JSON: running it again only does what is missing. The JSON keeps each
seed's row with its selection curve and the resolved config (``recipe``), so a seed whose run
directory is gone (another machine, an earlier session) stays in the table as long as the recipe
is the same.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np

from drivelab.api import baseline_env, build_config, evaluate_baseline, evaluate_checkpoint, train
from drivelab.config import merge_overrides, parse_value, read_yaml
from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints, resolve_checkpoint
from drivelab.training.outputs.statistics import mean_and_ci95
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.run.timing import UpdateSection, cpu_model
from provenance import provenance  # benchmarks/provenance.py
from sac_update_cost import ms_per_update  # benchmarks/sac_update_cost.py

HELDOUT_ENV, EPISODES = "MetaDrive-validation-v0", 200
METRICS = ("success_rate", "crash_rate", "out_of_road_rate", "route_completion")
TIMEOUT = "timeout_rate"  # recorded since 2026-11-27: seeds cached before it have none


def cpu_gauge_ms(repeats: int = 3, updates: int = 200) -> float:
    """This CPU's speed as the median milliseconds of one SAC update at the drive recipe's shapes
    with torch's default Adam on one thread (the arm "batch 256, actor_every 2, unfused Adam" of
    ``sac_update_cost.py``, comparable with every file it wrote). One CPU model name: 5-16 ms."""
    with UpdateSection(threads=1):  # sets one torch thread, restores the caller's on exit
        return round(statistics.median(ms_per_update(256, 2, False, unfused_adam=True, updates=updates)
                                       for _ in range(repeats)), 2)


def train_seed(config: str, seed: int, run_dir: Path, overrides: dict | None = None) -> dict:
    """Train (or finish) one seed; its wall clock, steps, CPU, the CPU's speed before and after
    (:func:`cpu_gauge_ms`) and its provenance (``benchmarks/provenance.py``) are kept in
    RUN/training.json (30 minutes hold ~3x fewer steps on a CPU ~3x slower: docs/results.md, "What
    these numbers promise")."""
    record = run_dir / "training.json"
    if record.is_file():
        return json.loads(record.read_text())
    cfg = build_config(merge_overrides({**read_yaml(config), "seed": seed, "run_dir": str(run_dir)}, overrides or {}))
    wall_started = time.time()  # the provenance's start: the gauge's time is part of the record
    gauge_before = cpu_gauge_ms()
    started = time.perf_counter()
    train(cfg, resume=bool(list_checkpoints(run_dir)))
    minutes = round((time.perf_counter() - started) / 60, 2)
    result = {"minutes": minutes, "steps": checkpoint_step(resolve_checkpoint(run_dir)), "cpu": cpu_model(),
              "cpu_gauge_ms": [gauge_before, cpu_gauge_ms()], **provenance(wall_started)}
    record.write_text(json.dumps(result) + "\n")
    return result


def heldout(run_dir: Path) -> dict:
    """The run's checkpoints/best on the 200 held-out scenarios (cached in RUN/heldout.json)."""
    cache = run_dir / "heldout.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    best = run_dir / "checkpoints" / "best"
    result, _, _ = evaluate_checkpoint(best, EPISODES, HELDOUT_ENV, num_envs=2)
    row = {**outcomes(result), "step": checkpoint_step(best)}
    cache.write_text(json.dumps(row) + "\n")
    return row


def outcomes(result) -> dict:
    """The means of METRICS (and TIMEOUT) and, under ``per_episode``, each episode's (for model cards)."""
    summary = result.summary()
    names = [m for m in (*METRICS, TIMEOUT) if m in summary]
    return {**{m: summary[m] for m in names},
            "per_episode": {m: [round(float(x), 4) for x in result.metrics[m]] for m in names}}


def selection_curve(run_dir: Path) -> dict[str, list[float]]:
    """Env steps (decisions), training minutes and success on the selection scenarios of the in-training evaluations."""
    steps, seconds, values = read_metrics(run_dir)["eval/success_rate"]  # seconds since the run's first log row
    return {"steps": [int(x) for x in steps], "minutes": [round(float(x), 2) for x in seconds / 60],
            "success": [float(x) for x in values]}


def prior_env_steps(run_dir: Path) -> int | None:
    """The env steps that collecting the run's prior data cost (a run with ``prior_data``), else None."""
    logged = read_metrics(run_dir).get("prior/env_steps")
    return int(logged[2][-1]) if logged is not None else None


def plot(table: dict, baselines: dict, algo: str, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Against decisions (env steps: what transfers between machines) and against minutes (what
    # this machine's CPU made of them, its gauge in the JSON).
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.8), sharey=True)
    for ax, x, end, label in ((axes[0], "steps", "steps", "decisions (env steps)"),
                              (axes[1], "minutes", "minutes", "training wall clock (minutes, 2 CPU cores)")):
        for seed, row in table.items():
            curve = row.get("selection")   # rows kept from before the curves were saved have none
            has = bool(curve) and x in curve
            name = f"seed {seed}: selection scenarios 200-229" if has else f"seed {seed} (curve not kept)"
            line, = ax.plot(curve[x] if has else [], curve["success"] if has else [], "o-", alpha=0.8, label=name)
            ax.plot([row[end]], [row["success_rate"]], "*", markersize=13, color=line.get_color())
        for (name, summary), color in zip(baselines.items(), ("tab:green", "tab:gray")):
            ax.axhline(summary["success_rate"], color=color, linestyle=":", label=f"{name} (held-out 0-199)")
        ax.plot([], [], "*", color="black", label="chosen checkpoint on held-out 0-199, at the end of training")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate")
    axes[0].set_ylim(-0.02, 1.02)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle(f"drive recipe ({algo.upper()}, env workers acting) on MetaDrive's protocol")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/drive.yaml")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--runs", type=Path, default=Path("runs/drive"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/drive_recipe.json"))
    parser.add_argument("--skip-train", action="store_true", help="only evaluate the seeds already trained")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="config overrides for an ablation arm, e.g. td3.noise_decay_steps=200000 "
                             "or sac.prior_data=demos.safetensors")
    parser.add_argument("--steps", type=int, help="a budget in decisions (env steps) instead of the config's "
                                                  "minutes: steps=N and no max_minutes")
    args = parser.parse_args()
    started = time.time()
    overrides = {key: parse_value(value) for key, _, value in (item.partition("=") for item in args.set)}
    if args.steps is not None:
        overrides.update({"steps": args.steps, "max_minutes": None})
    recipe = merge_overrides(read_yaml(args.config), overrides)
    previous = json.loads(args.out.read_text()) if args.out.is_file() else {}
    kept = previous.get("seeds", {}) if previous.get("recipe") == recipe else {}
    table = {}
    for seed in args.seeds:
        run_dir = args.runs / f"seed_{seed}"
        if not (run_dir / "training.json").is_file() and str(seed) in kept:
            table[str(seed)] = kept[str(seed)]       # trained and evaluated before, with this recipe
            continue
        if args.skip_train and not (run_dir / "training.json").is_file():
            continue
        try:
            trained = train_seed(args.config, seed, run_dir, overrides)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the run saved a checkpoint of this moment
            raise SystemExit(f"interrupted; the same command resumes seed {seed} in {run_dir}") from None
        row = {k: v for k, v in heldout(run_dir).items() if k != "per_episode"}
        table[str(seed)] = {**trained, **row, "prior_env_steps": prior_env_steps(run_dir),
                            "selection": selection_curve(run_dir)}
        print(json.dumps({"seed": seed, **{k: v for k, v in table[str(seed)].items() if k != "selection"}}), flush=True)
    baselines = previous.get("baselines") or {}
    for name in ("metadrive-expert", "random"):
        if name not in baselines:
            result = evaluate_baseline(name, baseline_env(env_id=HELDOUT_ENV), EPISODES)
            baselines[name] = outcomes(result)
    summary = {}
    for metric in (*METRICS, TIMEOUT, "minutes", "steps"):
        if not all(metric in row for row in table.values()):
            continue
        values = np.array([row[metric] for row in table.values()], float)
        mean, half = mean_and_ci95(values)
        summary[metric] = {"mean": float(mean), "ci95": float(half), "min": float(values.min()), "max": float(values.max())}
    result = {"benchmark": "drive-recipe", **provenance(started), "config": args.config, "overrides": overrides,
              "recipe": recipe, "metadrive_version": version("metadrive-simulator"),
              "protocol": "train on MetaDrive-1000envs (start seed 1000, 1000 scenarios); report checkpoints/best, "
                          "chosen on validation scenarios 200-229 during training, on the 200 unseen scenarios "
                          "0-199 (MetaDrive-validation-v0, default traffic, deterministic actions)",
              "seeds": table, "summary": summary, "baselines": baselines}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    plot(table, baselines, recipe["algo"], args.out.with_suffix(".png"))
    success = summary["success_rate"]
    print(f"held-out success over {len(table)} seeds: {success['mean']:.3f} ± {success['ci95']:.3f} "
          f"(min {success['min']:.3f}); expert {baselines['metadrive-expert']['success_rate']:.3f}, "
          f"random {baselines['random']['success_rate']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
