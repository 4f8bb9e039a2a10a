"""Evaluation speed against training's, on MetaDrive with N env processes, as JSON. Not a test.

    python benchmarks/eval_speed.py --checkpoint drivelab-driver --num-envs 2 --episodes 20 --repeats 2 \\
        --out benchmarks/results/eval_speed.json

Decisions per second (env steps the policy chose an action for) of, in turn, per repeat:

* ``raw``: random actions on the evaluation env, through drivelab's lockstep subprocess vector
  env: the ceiling;
* ``in_process``: ``drivelab eval``'s episodes stepped from this process, the policy acting here
  (:func:`drivelab.training.collection.evaluation.run_episodes`, how ``drivelab eval`` played
  before it played inside the env workers);
* ``workers``: the same episodes as ``drivelab eval`` plays them now, inside the env workers
  (:func:`drivelab.training.collection.evaluation.play`);
* ``training``: training the checkpoint's own config (for the shipped driver: TD3 with
  ``act_in_workers``) with the same number of env processes, in its steady state after the
  heat-up (``benchmarks/throughput.py``'s measure).

An evaluation's decisions are its episodes' lengths; its time runs from building the envs to
closing them. The two evaluations must give the same episodes: the JSON records per path the
returns and lengths of the first repeat and how far they are apart (a continuous action computed
for a batch of one observation, in a worker, may differ in its last bits from one computed for a
batch of N). The CPU's speed drifts on a shared machine, so the measurements alternate, the JSON
keeps every repeat and the medians, and ``cpu_gauge_ms`` (``benchmarks/drive_recipe.py``'s gauge)
is taken before and after. Several minutes per repeat for 20 episodes (MetaDrive-validation-v0
episodes are 300-1000 decisions, at 60-200 a second), plus the training's heat-up.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.envs import make_vector_env
from drivelab.tools.drivers import resolve_policy_path
from drivelab.tools.policies import checkpoint_config, policy_from_checkpoint
from drivelab.training.collection.evaluation import play, run_episodes
from drivelab.training.outputs.checkpoint import load_checkpoint
from drive_recipe import cpu_gauge_ms  # benchmarks/drive_recipe.py
from provenance import provenance  # benchmarks/provenance.py
from throughput import drivelab_speed  # benchmarks/throughput.py
from training import apply_overrides, env_steps_per_second  # benchmarks/training.py


def timed_evaluation(env_cfg, policy, episodes: int, seed: int, in_workers: bool) -> tuple[dict, object]:
    """(decisions/s and wall seconds, the EvalResult) of one evaluation, envs built and closed included."""
    started = time.perf_counter()
    if in_workers:
        result = play(env_cfg, policy, episodes, seed)
    else:
        envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED)
        try:
            result = run_episodes(envs, policy, episodes, seed=seed)
        finally:
            envs.close()
    wall = time.perf_counter() - started
    return {"decisions_per_s": float(result.lengths.sum() / wall), "wall_s": wall,
            "decisions": int(result.lengths.sum())}, result


def agreement(a, b) -> dict:
    """How far two evaluations of the same episodes are apart: their lengths, returns, and the
    episodes whose outcome (success, crash, out of road, timeout: the ``*_rate`` metrics, 0 or 1
    per episode) differs."""
    outcomes = [name for name in a.metrics if name.endswith("_rate")]
    another = [k for k in range(len(a.returns)) if any(a.metrics[name][k] != b.metrics[name][k] for name in outcomes)]
    return {"same_lengths": a.lengths.tolist() == b.lengths.tolist(),
            "max_abs_return_difference": float(np.max(np.abs(a.returns - b.returns))),
            "episodes_with_another_outcome": another}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default="drivelab-driver", help="checkpoint, run directory or shipped driver")
    parser.add_argument("--env", default="MetaDrive-validation-v0", help="the env evaluation plays")
    parser.add_argument("--num-envs", type=int, default=2, help="env processes, for evaluation and training")
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes per measurement")
    parser.add_argument("--seed", type=int, default=0, help="episode k is reset with seed SEED+k")
    parser.add_argument("--train-steps", type=int, default=6000, help="training decisions measured after the heat-up")
    parser.add_argument("--seconds", type=float, default=20.0, help="random-action measurement time")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="overrides of the training config, e.g. td3.learning_starts=2000 (a shorter heat-up)")
    parser.add_argument("--out", default="benchmarks/results/eval_speed.json")
    args = parser.parse_args()
    started = time.time()
    gauge_before = cpu_gauge_ms()
    ckpt = load_checkpoint(resolve_policy_path(args.checkpoint))
    cfg = checkpoint_config(ckpt)
    env_cfg = cfg.env.on(args.env) if args.env != cfg.env.id else cfg.env.played()  # as drivelab eval --env
    env_cfg = dataclasses.replace(env_cfg, num_envs=args.num_envs)
    policy = policy_from_checkpoint(ckpt, cfg, env_cfg)
    train_data = copy.deepcopy(ckpt.state["config"])
    apply_overrides(train_data, args.set)
    threads = torch.get_num_threads()  # drivelab eval's; training sets its own (torch_threads)
    repeats, first = [], None
    for repeat in range(args.repeats):
        row = {"raw": env_steps_per_second(env_cfg, args.seconds)}
        for name, in_workers in (("in_process", False), ("workers", True)):
            torch.set_num_threads(threads)
            row[name], result = timed_evaluation(env_cfg, policy, args.episodes, args.seed, in_workers)
            if repeat == 0:
                first = {**(first or {}), name: result}
        row["training"] = {"decisions_per_s": drivelab_speed(train_data, args.num_envs, None, args.train_steps)}
        print(json.dumps({"repeat": repeat, **row}), flush=True)
        repeats.append(row)
    median = {name: statistics.median(row[name] if name == "raw" else row[name]["decisions_per_s"] for row in repeats)
              for name in ("raw", "in_process", "workers", "training")}
    gauge_after = cpu_gauge_ms()  # measured before provenance(), so that its end time follows every measurement
    result = {"benchmark": "eval-speed", **provenance(started), "cpu_gauge_ms": [gauge_before, gauge_after],
              "checkpoint": str(ckpt.path), "algo": cfg.algo, "train_env": cfg.env.id, "env": env_cfg.id,
              "num_envs": args.num_envs, "episodes": args.episodes, "seed": args.seed, "train_steps": args.train_steps,
              "overrides": args.set, "decisions_per_s_median": median,
              "workers_vs_in_process": median["workers"] / median["in_process"],
              "workers_vs_training": median["workers"] / median["training"],
              "same_episodes": agreement(first["in_process"], first["workers"]),
              "per_episode": {name: {"returns": r.returns.tolist(), "lengths": r.lengths.tolist()}
                              for name, r in first.items()},
              "repeats": repeats}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: result[k] for k in ("decisions_per_s_median", "workers_vs_in_process", "workers_vs_training",
                                             "same_episodes")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
