"""What one SAC update costs at the drive recipe's shapes, per batch size, ``actor_every`` and
``bf16_updates`` (bfloat16 autocast, the output layers float32), as JSON.

``unfused Adam``: the same update with torch's default Adam instead of the fused one drivelab's
off-policy learners build since 2026-12-02 (``drivelab.training.learning.optim.fused_adam``). The files
written before then timed the default Adam: to compare a CPU with theirs, read this arm.

The learner's CPU per env step is (ms per update) x ``utd``; on two cores it is what keeps the
simulators waiting (docs/results.md, "Where the time goes"). Timed on random tensors shaped as
``configs/drive.yaml``'s (275-d observations, 2-d actions, [128, 128] layer-norm critics, one
torch thread), medians over repeats. Run it on an otherwise idle machine. Not a test.

    python benchmarks/sac_update_cost.py --out benchmarks/results/sac_update_cost_bf16.json

The numbers depend on the CPU, which the JSON records (``machine``): bfloat16 pays only where the
CPU computes it (``sac_update_cost_bf16.json``, AVX512-BF16); on an AVX2-only CPU it is several
times slower than float32 (``sac_update_cost_avx2.json``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from drivelab.algos import sac
from drivelab.api import build_config
from drivelab.training.learning.replay_buffer import ReplayBatch
from drivelab.training.learning.offpolicy_nets import make_target
from drivelab.training.learning.precision import update_precision
from provenance import provenance  # benchmarks/provenance.py

OBS_DIM, ACT_DIM, HIDDEN = 275, 2, [128, 128]


def ms_per_update(batch_size: int, actor_every: int, bf16: bool, unfused_adam: bool = False, *, updates: int) -> float:
    """Milliseconds per ``sac.update`` (the actor and temperature every ``actor_every``-th), in
    the context the trainer opens around it (``update_precision``); ``unfused_adam``: with torch's
    default Adam instead of the fused one drivelab builds, for the comparison."""
    cfg = build_config({"algo": "sac", "env": {"id": "Pendulum-v1"},
                        "sac": {"hidden": HIDDEN, "critic_layer_norm": True, "batch_size": batch_size,
                                "actor_every": actor_every, "init_alpha": 0.05, "n_step": 3,
                                "bf16_updates": bf16}})
    hp: sac.Params = cfg.algo_params
    obs_space = gym.spaces.Box(-1.0, 1.0, (OBS_DIM,), np.float32)
    act_space = gym.spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32)
    agent = sac.build_policy(cfg, obs_space, act_space)
    target = make_target(agent)
    log_alpha = torch.nn.Parameter(torch.tensor(hp.init_alpha).log())
    opt = sac.build_optimizers(agent, log_alpha, hp)
    if unfused_adam:
        opt = sac.Optimizers(*(torch.optim.Adam(o.param_groups[0]["params"], lr=o.param_groups[0]["lr"]) for o in opt))
    b = batch_size
    batch = ReplayBatch(obs=torch.randn(b, OBS_DIM), actions=torch.rand(b, ACT_DIM) * 2 - 1, rewards=torch.randn(b),
                        next_obs=torch.randn(b, OBS_DIM), terminated=torch.zeros(b),
                        discount=torch.full((b,), hp.gamma ** hp.n_step))

    def run(n: int) -> None:
        for i in range(n):
            with update_precision(hp, torch.device("cpu")):
                sac.update(agent, target, log_alpha, opt, batch, hp, -float(ACT_DIM), update_actor=i % actor_every == 0)

    run(30)  # first calls allocate
    started = time.perf_counter()
    run(updates)
    return (time.perf_counter() - started) / updates * 1e3


def arm_name(batch_size: int, actor_every: int, bf16: bool, unfused_adam: bool = False) -> str:
    """The JSON key of one arm, e.g. "batch 256, actor_every 2, bf16"."""
    return f"batch {batch_size}, actor_every {actor_every}" + (", bf16" if bf16 else "") + (
        ", unfused Adam" if unfused_adam else "")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=300, help="updates per timing")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    started = time.time()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    arms = [(128, 1, False), (256, 1, False), (256, 2, False), (256, 2, False, True), (256, 2, True), (512, 1, False),
            (512, 2, False), (512, 2, True)]
    timings: dict[str, list[float]] = {arm_name(*arm): [] for arm in arms}
    for _ in range(args.repeats):  # arms interleaved, so drift of the machine hits them alike
        for arm in arms:
            timings[arm_name(*arm)].append(ms_per_update(*arm, updates=args.updates))
    # provenance's "machine" is the CPU the numbers depend on
    result = {"benchmark": "sac-update-cost", **provenance(started),
              "shapes": {"obs": OBS_DIM, "act": ACT_DIM, "hidden": HIDDEN, "critic_layer_norm": True,
                         "torch_threads": 1},
              "ms_per_update_median": {k: round(statistics.median(v), 2) for k, v in timings.items()},
              "ms_per_update": {k: [round(x, 2) for x in v] for k, v in timings.items()}}
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
