"""Multi-agent MetaDrive with IPPO or MAPPO, over scenes and seeds: one table and one PNG. Not a test.

    python benchmarks/multiagent.py --config ma_intersection --scenes Intersection Roundabout Tollgate Bottleneck \\
        --seeds 0 1 2 --steps 250000 --runs runs/ma        # writes benchmarks/results/ma_intersection.json + .png

For each scene and seed: train ``--config`` (``ma_intersection``: IPPO, or ``ma_intersection_mappo``)
on the scene (RUNS/CONFIG/SCENE/seed_N; an interrupted run resumes, a finished one is kept) for
``--steps`` env steps, then report

* CoPO's measure: the best training success rate (``episode/success_rate``, a mean over the last
  ``stats_window`` cars' episodes, at its best log point; CoPO reports the best of its training);
* deterministic evaluation of the final policy on ``--episodes`` scene episodes (seeds 0..N-1):
  success, crash, out-of-road, crashes per scene episode, efficiency, cars on the road;
* the same episodes with sampled actions, as the cars act in training (``sampled``): the gap
  between the two is what taking every car's mode instead of a sample changes;
* the generalisation twist: the same policy on ``--other-scene`` (a scene it never drove);
* env steps, minutes, env steps/s, and the CPU gauge beside them.

Over seeds: mean, 95% confidence interval and minimum. CoPO's published IPPO and CoPO success
(MetaDrive 0.2.5, 1M env steps, best training success over 8 seeds) are put beside them. The PNG
plots training success against env steps and against minutes. Results are cached in the run
directories, so running it again does what is missing.
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

from drivelab.api import evaluate_checkpoint
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.outputs.statistics import mean_and_ci95

CONFIGS = Path(__file__).resolve().parent.parent / "drivelab" / "configs"
# decisionforce/CoPO, benchmarks/MetaDrive-0.2.5/README.md: best training success, 1M env steps
COPO_PUBLISHED = {"IPPO": {"Intersection": 0.719, "Roundabout": 0.664, "Bottleneck": 0.240, "Tollgate": 0.044,
                           "ParkingLot": 0.170, "PGMap": 0.818},
                  "CoPO": {"Intersection": 0.795, "Roundabout": 0.728, "Bottleneck": 0.474, "Tollgate": 0.272,
                           "ParkingLot": 0.195, "PGMap": 0.834}}
EVAL_KEYS = ("success_rate", "crash_rate", "out_of_road_rate", "crashes_per_episode", "efficiency", "live_agents",
             "agent_episodes")


def scene_id(scene: str) -> str:
    return f"MultiAgent{scene}-v0"


def evaluation(run_dir: Path, scene: str, episodes: int, name: str, deterministic: bool = True) -> dict:
    """Scene episodes of the run's final policy on ``scene``, its actions the mode or sampled
    (cached in RUN/NAME.json)."""
    cache = run_dir / f"{name}.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    result, _, _ = evaluate_checkpoint(run_dir, episodes, scene_id(scene), num_envs=2, deterministic=deterministic)
    row = {key: value for key, value in result.summary().items() if key in EVAL_KEYS}
    cache.write_text(json.dumps(row) + "\n")
    return row


def training_curve(run_dir: Path) -> dict:
    """Training success against env steps and wall minutes, and its best point."""
    steps, seconds, values = read_metrics(run_dir).get("episode/success_rate", ([], [], []))
    steps, values = [int(x) for x in steps], [float(x) for x in values]
    minutes = [float(x) / 60 for x in seconds]  # wall clock since the run's first log
    best = int(np.argmax(values)) if values else None
    return {"steps": steps, "success": values, "minutes": minutes,
            "best_training_success": values[best] if best is not None else float("nan"),
            "best_at_step": steps[best] if best is not None else None}


def summarise(rows: list[dict], keys: tuple[str, ...]) -> dict:
    out = {}
    for key in keys:
        values = [row[key] for row in rows if key in row]
        if values:
            mean, ci = mean_and_ci95(values)
            out[key] = {"mean": float(mean), "ci95": float(ci), "min": float(np.min(values))}
    return out


def plot(scenes: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for scene, data in scenes.items():
        for i, (seed, row) in enumerate(data["seeds"].items()):
            curve = row["curve"]
            label = scene if i == 0 else None
            color = f"C{list(scenes).index(scene)}"
            axes[0].plot(curve["steps"], curve["success"], color=color, alpha=0.7, label=label)
            axes[1].plot(curve["minutes"], curve["success"], color=color, alpha=0.7, label=label)
        for name, published in COPO_PUBLISHED.items():
            if scene in published:
                axes[0].axhline(published[scene], color=f"C{list(scenes).index(scene)}",
                                ls="--" if name == "CoPO" else ":", lw=0.8)
    axes[0].set_xlabel("env steps")
    axes[1].set_xlabel("minutes of training")
    for ax in axes:
        ax.set_ylabel("training success (cars' episodes)")
        ax.set_ylim(0, 1)
        ax.legend()
    axes[0].set_title("dotted: CoPO's IPPO, dashed: CoPO (1M steps)")
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="ma_intersection", help="ma_intersection (IPPO) or ma_intersection_mappo")
    parser.add_argument("--scenes", nargs="+", default=["Intersection", "Roundabout", "Tollgate", "Bottleneck"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=250_000, help="env steps of training per run")
    parser.add_argument("--episodes", type=int, default=10, help="scene episodes of each evaluation")
    parser.add_argument("--other-scene", default="Roundabout", help="a scene the Intersection runs never drove")
    parser.add_argument("--runs", type=Path, default=Path("runs/ma"))
    parser.add_argument("--out", type=Path, default=None, help="default: benchmarks/results/CONFIG.json")
    args = parser.parse_args()
    started = time.time()
    config = CONFIGS / f"{args.config}.yaml"
    args.out = args.out or Path("benchmarks/results") / f"{args.config}.json"
    gauge_before = cpu_gauge_ms()
    scenes = {}
    for scene in args.scenes:
        seeds = {}
        for seed in args.seeds:
            run_dir = args.runs / args.config / scene / f"seed_{seed}"
            try:
                trained = train_seed(str(config), seed, run_dir, {"env.id": scene_id(scene), "steps": args.steps})
            except KeyboardInterrupt:
                raise SystemExit(f"interrupted; the same command resumes {scene} seed {seed} in {run_dir}") from None
            row = {**trained, "steps_per_s": trained["steps"] / (60 * trained["minutes"]),
                   "curve": training_curve(run_dir), **evaluation(run_dir, scene, args.episodes, "evaluation"),
                   "sampled": evaluation(run_dir, scene, args.episodes, "evaluation_sampled", deterministic=False)}
            if scene == "Intersection" and args.other_scene != scene:
                row["other_scene"] = {"scene": args.other_scene,
                                      **evaluation(run_dir, args.other_scene, args.episodes, "other_scene")}
            row["best_training_success"] = row["curve"]["best_training_success"]
            seeds[str(seed)] = row
            print(json.dumps({"scene": scene, "seed": seed, **{k: v for k, v in row.items() if k != "curve"}}),
                  flush=True)
        scenes[scene] = {"seeds": seeds, "summary": summarise(list(seeds.values()),
                                                              ("best_training_success", *EVAL_KEYS, "steps_per_s")),
                         "sampled": summarise([row["sampled"] for row in seeds.values()], EVAL_KEYS),
                         "copo_published": {name: table.get(scene) for name, table in COPO_PUBLISHED.items()}}
    gauge_after = cpu_gauge_ms()  # measured before provenance(), so that its end time follows every measurement
    result = {"benchmark": f"multiagent-{args.config}", **provenance(started),
              "cpu_gauge_ms": [gauge_before, gauge_after],
              "config": str(config.relative_to(CONFIGS.parent.parent)), "steps": args.steps,
              "protocol": "best training success over the cars' episodes (CoPO's measure), and deterministic "
                          f"evaluation of the final policy on {args.episodes} scene episodes (seeds 0..N-1), "
                          "and the same episodes with sampled actions (sampled)",
              "scenes": scenes}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    plot(scenes, args.out.with_suffix(".png"))
    for scene, data in scenes.items():
        s = data["summary"]["best_training_success"]
        print(f"{scene:13s} best training success {s['mean']:.3f} ± {s['ci95']:.3f} (min {s['min']:.3f}); "
              f"CoPO's IPPO {data['copo_published']['IPPO']}, CoPO {data['copo_published']['CoPO']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
