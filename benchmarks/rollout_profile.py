"""Where a PPO iteration's wall time goes, call by call: timers around the parts of the rollout
loop and the update, as milliseconds per env step, as JSON. Not a test.

    python benchmarks/rollout_profile.py --num-envs 1                 # lockstep, the drive recipe
    python benchmarks/rollout_profile.py --num-envs 4 --set env.step_groups=4

Timed (cumulative wall time, each divided by the steps trained; the parts nest, so they do not
add up): ``collect`` (a whole rollout), ``wait_for_envs`` (the trainer blocked until the workers'
results are there: the env's own time plus the pipe), ``receive`` (that wait plus reading and
unpickling the results), ``rollout_step`` (inference, sending the actions, storing the row),
``send`` (pickling and writing the actions), ``episodes`` (episode bookkeeping) and ``update``
(PPO's epochs). Run it with nothing else on the machine; ``benchmarks/throughput.py`` gives the steps/s.
"""

from __future__ import annotations

import argparse
import collections
import functools
import tempfile
import time
from pathlib import Path

import torch
from gymnasium.vector import AsyncVectorEnv

import drivelab.algos.ppo as ppo
from drivelab.api import build_config, train
from drivelab.config import read_yaml, set_dotted
from drivelab.envs.groups import EnvGroups
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.collection.rollout import RolloutCollector
from training import apply_overrides, report  # benchmarks/training.py

SECONDS: dict[str, float] = collections.defaultdict(float)
CALLS: collections.Counter = collections.Counter()


def timed(owner, attribute: str, name: str) -> None:
    """Replace ``owner.attribute`` by a wrapper that adds its wall time to ``SECONDS[name]``."""
    inner = getattr(owner, attribute)

    @functools.wraps(inner)
    def wrapper(*args, **kwargs):
        started = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            SECONDS[name] += time.perf_counter() - started
            CALLS[name] += 1

    setattr(owner, attribute, wrapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/ppo_metadrive_drive.yaml")
    parser.add_argument("--num-envs", type=int, default=1)
    parser.add_argument("--steps", type=int, default=8192)
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="config overrides")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    started = time.time()
    torch.set_num_threads(1)  # as drivelab's trainer (cfg.torch_threads)
    data = read_yaml(args.config)
    # The trainer steps the envs (the parts timed here), lockstep, unless --set env.step_groups=N
    # (or --set ppo.act_in_workers=true: then collect is the wait for the workers' rollouts).
    set_dotted(data, "env.step_groups", None)
    set_dotted(data, "ppo.act_in_workers", False)
    apply_overrides(data, args.set)
    for field, value in {"env.num_envs": args.num_envs, "steps": args.steps, "eval.every": 0,
                         "checkpoint_every": 10**9}.items():
        set_dotted(data, field, value)
    # The gymnasium worker's wait is timed in the parent only: spawned workers import this module
    # as __mp_main__, which does not run main().
    timed(AsyncVectorEnv, "_poll_pipe_envs", "wait_for_envs")
    timed(EnvGroups, "receive", "receive")
    timed(EnvGroups, "send", "send")
    timed(RolloutCollector, "_act", "rollout_step")
    timed(RolloutCollector, "collect", "collect")
    timed(EpisodeTracker, "step", "episodes")
    timed(ppo, "update", "update")
    with tempfile.TemporaryDirectory() as tmp:
        set_dotted(data, "run_dir", str(Path(tmp) / "run"))
        cfg = build_config(data)
        began = time.perf_counter()
        train(cfg, progress=False)
        total = time.perf_counter() - began
    result = {"benchmark": "rollout-profile", "config": args.config, "num_envs": args.num_envs, "steps": cfg.steps,
              "overrides": args.set, "total_s": total,
              "ms_per_env_step": {name: 1e3 * SECONDS[name] / cfg.steps for name in sorted(SECONDS, key=SECONDS.get,
                                                                                          reverse=True)},
              "calls": dict(CALLS)}
    report(result, args.out, started)


if __name__ == "__main__":
    main()
