"""What one env worker of a MetaDrive config pays per decision and per reset, as JSON.

MetaDrive builds a scenario's road network (blocks, lanes, their physics bodies) the first time a
process resets to it, and keeps it (``store_map``): a reset to a scenario this process has not seen
costs far more than a reset to one it has. On ``MetaDrive-1000envs`` a 30-minute run plays ~1,000
episodes, so most resets build a new map. Timed in one process on the config's training env
(wrappers included): ``new_map_reset_ms`` (the first reset to each of ``--scenarios`` scenarios),
``stored_map_reset_ms`` (the same scenarios again) and ``step_ms`` (a decision: steering 0,
throttle 0.3, the env reset to a stored scenario when an episode ends), medians. Not a test; run
it on an otherwise idle machine (docs/results.md, "Where the time goes").

    python benchmarks/metadrive_reset_cost.py --out benchmarks/results/metadrive_reset_cost.json
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from drivelab.api import build_config
from drivelab.config import read_yaml
from drivelab.envs import make_env
from drivelab.training.run.timing import machine
from training import report  # benchmarks/training.py


def milliseconds(action) -> float:
    """Wall-clock milliseconds of ``action()``."""
    started = time.perf_counter()
    action()
    return (time.perf_counter() - started) * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/drive.yaml")
    parser.add_argument("--scenarios", type=int, default=20, help="new scenarios to reset to")
    parser.add_argument("--steps", type=int, default=500, help="decisions to time")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    started = time.time()
    cfg = build_config(read_yaml(args.config))
    env = make_env(cfg.env)
    first = env.unwrapped.start_seed
    env.reset(options={"scenario": first})  # builds the engine
    scenarios = range(first + 1, first + 1 + args.scenarios)
    new_map = [milliseconds(lambda s=s: env.reset(options={"scenario": s})) for s in scenarios]
    stored_map = [milliseconds(lambda s=s: env.reset(options={"scenario": s})) for s in scenarios]
    action = np.array([0.0, 0.3], np.float32)
    step, episodes = [], 0
    env.reset(options={"scenario": first})
    for _ in range(args.steps):
        began = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        step.append((time.perf_counter() - began) * 1e3)
        if terminated or truncated:
            episodes += 1
            env.reset(options={"scenario": first})
    env.close()
    medians = {"new_map_reset_ms": statistics.median(new_map), "stored_map_reset_ms": statistics.median(stored_map),
               "step_ms": statistics.median(step)}
    result = {"benchmark": "metadrive-reset-cost", "config": args.config, "env": cfg.env.id,
              "action_repeat": cfg.env.action_repeat, "simulator_repeat": cfg.env.simulator_repeat,
              "machine": machine(), **{k: round(v, 2) for k, v in medians.items()},
              "new_map_in_decisions": round(medians["new_map_reset_ms"] / medians["step_ms"], 1),
              "episodes_in_step_timing": episodes,
              "new_map_reset_ms_each": [round(x, 1) for x in new_map],
              "stored_map_reset_ms_each": [round(x, 1) for x in stored_map]}
    report(result, args.out, started)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
