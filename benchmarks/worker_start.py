"""How long a vector env of subprocess workers takes to start, reset and close, per start method.

An evaluation, a video and a restarted worker each start new env workers. With ``spawn`` every
worker imports its env's modules again (``import metadrive`` is seconds of CPU); from a fork
server (``drivelab.envs.worker_start_method``, Linux) it forks from one interpreter that imported
them once. Each method is timed in a fresh Python process: the first start pays the imports
(the fork server's included), the later ones show what every further start costs. Not a test;
run it on an otherwise idle machine.

    python benchmarks/worker_start.py --out benchmarks/results/worker_start.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

from provenance import provenance  # benchmarks/provenance.py

PROBE = """
import functools, json, sys, time
from gymnasium.vector import AsyncVectorEnv
from drivelab.envs import EnvConfig, make_env, worker_start_method

def main(method, env_id, num_envs, starts):
    cfg = EnvConfig(id=env_id, num_envs=num_envs)
    context = worker_start_method(env_id) if method == "forkserver" else method
    seconds = []
    for _ in range(starts):
        begin = time.perf_counter()
        envs = AsyncVectorEnv([functools.partial(make_env, cfg) for _ in range(num_envs)], context=context)
        envs.reset(seed=0)
        envs.close()
        seconds.append(time.perf_counter() - begin)
    print(json.dumps(seconds))

if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))
"""


def time_starts(method: str, env_id: str, num_envs: int, starts: int) -> list[float]:
    """Seconds per start-reset-close of ``num_envs`` workers, ``starts`` times in one new process."""
    done = subprocess.run([sys.executable, "-c", PROBE, method, env_id, str(num_envs), str(starts)],
                          capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="MetaDrive-10env-v0")
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--starts", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/worker_start.json"))
    args = parser.parse_args()
    started = time.time()
    if args.starts < 2:
        parser.error("--starts must be 2 or more: the first start and the later ones are reported apart")
    rows = {}
    for method in ("spawn", "forkserver"):
        seconds = time_starts(method, args.env, args.num_envs, args.starts)
        rows[method] = {"first_s": round(seconds[0], 2), "later_median_s": round(statistics.median(seconds[1:]), 2),
                        "seconds": [round(s, 2) for s in seconds]}
        row = rows[method]
        print(f"{method:>10}: first start {row['first_s']} s, later starts {row['later_median_s']} s (median)")
    # provenance records the machine (CPU, cores), which these seconds depend on
    result = {**provenance(started), "env": args.env, "num_envs": args.num_envs, "starts": args.starts, "methods": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
