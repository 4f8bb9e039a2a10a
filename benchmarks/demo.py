"""``make demo`` as a measurement: the same training and the same table, written to a results file. Not a test.

    python benchmarks/demo.py --runs runs/demo_bench                       # 10 minutes, as make demo
    python benchmarks/demo.py --runs runs/demo_bench --steps 90000         # a budget in decisions

``make demo`` trains the drive recipe on TD3 (``configs/drive_td3.yaml``, no evaluation during
training) for 10 minutes of wall clock, then plays 50 validation scenarios (start seeds 0-49, which
no training scenario and no checkpoint choice has seen) with the demo's agent before training (its
step-0 checkpoint) and after, the shipped ``drivelab-driver``, MetaDrive's expert and a random
policy, deterministic actions. This script does exactly that and keeps, in
``benchmarks/results/demo.json``: each policy's success, route completion, crash, off-road and
timeout rates (success with its 95% confidence interval), the decisions the training made and its
minutes, with the CPU gauge (``drive_recipe.cpu_gauge_ms``) before and after, and the provenance.
``--steps`` states the budget in decisions instead (the minutes are then what it took). The run
directory is kept: a finished training is not repeated, an interrupted one resumes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from drive_recipe import outcomes, train_seed  # benchmarks/drive_recipe.py
from provenance import provenance  # benchmarks/provenance.py

from drivelab.api import baseline_env, evaluate_baseline, evaluate_checkpoint
from drivelab.training.outputs.statistics import mean_and_ci95

CONFIG = Path(__file__).resolve().parent.parent / "drivelab" / "configs" / "drive_td3.yaml"
ENV = "MetaDrive-validation-v0"  # scenarios 0-49 (--episodes 50), the Makefile's table


def row(result) -> dict:
    """One policy's line of the table: the means, success's 95% CI half-width over the episodes
    (Student's t, as every drivelab table), and no per-episode lists."""
    means = {key: value for key, value in outcomes(result).items() if key != "per_episode"}
    _, ci = mean_and_ci95(result.metrics["success_rate"])
    return {**means, "success_ci95": float(ci), "episodes": len(result.metrics["success_rate"])}


def table(run_dir: Path, episodes: int) -> dict:
    """The Makefile's table: step 0 and the trained agent, the shipped driver, the expert, random."""
    rows, played = {}, None
    step_0 = run_dir / "checkpoints" / "step_000000000000"  # kept through rotation, as make demo reads it
    for name, path in (("step 0", step_0), ("trained", run_dir), ("drivelab-driver", "drivelab-driver")):
        result, env_cfg, _ = evaluate_checkpoint(path, episodes, ENV, num_envs=2)
        rows[name] = row(result)
        played = played or env_cfg
    for name in ("metadrive-expert", "random"):  # as drivelab eval: on the env the checkpoints played
        rows[name] = row(evaluate_baseline(name, baseline_env(played), episodes))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, default=Path("runs/demo_bench"), help="the demo's run directory")
    parser.add_argument("--minutes", type=float, default=10.0, help="training wall clock, as make demo")
    parser.add_argument("--steps", type=int, default=None, help="a budget in decisions instead of minutes")
    parser.add_argument("--episodes", type=int, default=50, help="validation scenarios 0..N-1, as make demo")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/demo.json"))
    args = parser.parse_args()
    started = time.time()
    budget = {"eval.every": 0}
    budget.update({"steps": args.steps, "max_minutes": None} if args.steps else {"max_minutes": args.minutes})
    trained = train_seed(str(CONFIG), args.seed, args.runs, budget)
    rows = table(args.runs, args.episodes)
    result = {"benchmark": "demo", **provenance(started), "config": "drivelab/configs/drive_td3.yaml",
              "budget": {"steps": args.steps} if args.steps else {"minutes": args.minutes}, "seed": args.seed,
              "training": {key: trained[key] for key in ("minutes", "steps", "cpu", "cpu_gauge_ms", "commit")},
              "decisions_per_s": round(trained["steps"] / (60 * trained["minutes"]), 1),
              "protocol": f"{ENV}, start seeds 0-{args.episodes - 1}, deterministic actions", "policies": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"trained {trained['steps']} decisions in {trained['minutes']} minutes "
          f"(CPU gauge {trained['cpu_gauge_ms']} ms)")
    for name, line in rows.items():
        print(f"{name:17s} success {line['success_rate']:.0%} ± {line['success_ci95']:.0%}  "
              f"route {line['route_completion']:.0%}  crash {line['crash_rate']:.0%}  "
              f"off road {line['out_of_road_rate']:.0%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
