"""Off-policy speed: env steps/s and gradient updates/s of DDPG, TD3 and SAC, as JSON.

Measured on LunarLander-v3 with continuous actions, [400, 300] networks and batch 256 (the
issue's setting): the update rate is timed on a filled buffer, the env rate is the training
loop's rate during heat-up (random actions into the replay buffer, no updates). A short warm-up
run first keeps import and first-call costs out of the first algorithm's numbers. Not part of
the test suite.

    python benchmarks/offpolicy_speed.py --out offpolicy_speed.json [--updates 500] [--compile]
"""

from __future__ import annotations

import argparse
import csv
import tempfile
import time
from pathlib import Path

from drivelab.api import build_config, train
from training import report  # benchmarks/training.py


def measure(algo: str, updates: int, steps: int, compile_: bool) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        # phase 1: env steps of the loop in heat-up (no updates: learning_starts > steps)
        cfg = build_config({"algo": algo, "steps": steps, "seed": 0, "run_dir": f"{tmp}/env",
                            "env": {"id": "LunarLander-v3", "num_envs": 1, "kwargs": {"continuous": True}},
                            algo: {"hidden": [400, 300], "batch_size": 256, "buffer_size": 100_000,
                                   "learning_starts": steps + 1, "compile": compile_}})
        started = time.perf_counter()
        train(cfg, progress=False)
        env_rate = steps / (time.perf_counter() - started)
        # phase 2: updates: heat-up of 1000 steps, then `updates` gradient steps (utd 1)
        # (one log, at the end: perf/update_fraction covers the whole run)
        cfg = build_config({"algo": algo, "steps": 1000 + updates, "seed": 0, "run_dir": f"{tmp}/upd", "log_every": 10**9,
                            "env": {"id": "LunarLander-v3", "num_envs": 1, "kwargs": {"continuous": True}},
                            algo: {"hidden": [400, 300], "batch_size": 256, "buffer_size": 100_000,
                                   "learning_starts": 1000, "compile": compile_}})
        started = time.perf_counter()
        train(cfg, progress=False)
        wall = time.perf_counter() - started
        with open(Path(cfg.run_dir) / "metrics.csv") as f:
            rows = {r["name"]: float(r["value"]) for r in csv.DictReader(f)}
    return {"algo": algo, "env_steps_per_s": env_rate, "updates_per_s": updates / (wall * rows["perf/update_fraction"]),
            "updates": updates}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=3000, help="env steps for the env-rate phase")
    parser.add_argument("--compile", action="store_true", help="torch.compile the networks")
    parser.add_argument("--out")
    args = parser.parse_args()
    started = time.time()
    measure("ddpg", updates=10, steps=500, compile_=args.compile)   # warm-up, discarded
    results = {"benchmark": "offpolicy-speed", "env": "LunarLander-v3 (continuous)", "hidden": [400, 300],
               "batch_size": 256, "compile": args.compile,
               "algos": [measure(a, args.updates, args.steps, args.compile) for a in ("ddpg", "td3", "sac")]}
    report(results, args.out, started)


if __name__ == "__main__":
    main()
