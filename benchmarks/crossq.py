"""TD3's critics with target networks (the default) against CrossQ's batch-normalised critics
without targets (``td3.crossq``), as JSON: learning on Pendulum-v1, and the cost of one update at
the drive recipe's shapes. Not a test.

    python benchmarks/crossq.py --seeds 0 1 --steps 8000 --out benchmarks/results/crossq.json

Each arm is configs/td3_pendulum.yaml's TD3 ([128, 128], lr 5e-4, one env, synchronous) with one
change, trained for ``--steps`` env steps per seed; every checkpoint (each 2,000 steps) plays 10
deterministic episodes. The arms run two at a time, one torch thread each. The JSON has, per arm
and seed, the mean return of each checkpoint, the training minutes, and the logged mean Q and
actor saturation (the share of actions within 1% of a bound), which tell a critic that has not
found the returns' scale from an actor stuck at the bounds. Then, on one thread, the median time
of one TD3 update (critic and actor step) at configs/drive.yaml's shapes: 275-d observations, 2-d
actions, [128, 128] networks, batch 256, layer-norm critics with targets against CrossQ's.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from multiprocessing import Pool
from pathlib import Path

from provenance import provenance  # benchmarks/provenance.py

ARMS = {
    "td3": {},
    "crossq": {"crossq": True},
    "crossq + pre_tanh_l2 0.1": {"crossq": True, "pre_tanh_l2": 0.1},
}


def train_arm(job: tuple[str, int, int, str]) -> dict:
    import torch

    torch.set_num_threads(1)
    from drivelab.api import build_config, evaluate_checkpoint, train
    from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints
    from drivelab.training.outputs.plots import read_metrics

    arm, seed, steps, tmp = job
    run_dir = Path(tmp) / f"{arm.replace(' ', '_')}_{seed}"
    cfg = build_config({"algo": "td3", "steps": steps, "seed": seed, "run_dir": str(run_dir),
                        "checkpoint_every": 2000, "keep_checkpoints": 100, "log_every": 500,
                        "env": {"id": "Pendulum-v1", "num_envs": 1}, "eval": {"every": 0},
                        "td3": {"learning_starts": 1000, "hidden": [128, 128], "actor_lr": 5e-4, "critic_lr": 5e-4,
                                **ARMS[arm]}})
    started = time.perf_counter()
    train(cfg, progress=False)
    minutes = (time.perf_counter() - started) / 60
    metrics = read_metrics(run_dir)
    returns = {}
    for checkpoint in list_checkpoints(run_dir):
        result, _, _ = evaluate_checkpoint(checkpoint, episodes=10)
        returns[checkpoint_step(checkpoint)] = round(result.summary()["return_mean"], 1)
    logged = {name: {"step": metrics[name][0].astype(int).tolist(), "value": [round(float(v), 3) for v in metrics[name][2]]}
              for name in ("charts/q", "charts/actor_saturation")}
    return {"arm": arm, "seed": seed, "minutes": round(minutes, 2), "return_by_step": returns, **logged}


def update_ms(crossq: bool, repeats: int = 7, updates: int = 100) -> float:
    """Median over ``repeats`` of the mean time of one update (ms) at the drive recipe's shapes."""
    import gymnasium as gym
    import numpy as np
    import torch

    from drivelab.algos import td3
    from drivelab.training.learning.replay_buffer import ReplayBatch
    from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, make_target
    from drivelab.training.learning.optim import make_optimizers

    torch.set_num_threads(1)
    torch.manual_seed(0)
    obs_space, act_space = gym.spaces.Box(-1, 1, (275,), np.float32), gym.spaces.Box(-1, 1, (2,), np.float32)
    hp = td3.Params(hidden=[128, 128], batch_size=256, critic_layer_norm=not crossq, crossq=crossq)
    agent = OffPolicyAgent(obs_space, act_space, hp.hidden, hp.activation, stochastic=False, critics=2,
                           critic_layer_norm=not crossq, critic_batch_norm=crossq)
    target, opt = None if crossq else make_target(agent), make_optimizers(agent, hp)
    size = hp.batch_size
    batch = ReplayBatch(obs=torch.rand(size, 275), actions=torch.rand(size, 2) * 2 - 1, rewards=torch.randn(size),
                        next_obs=torch.rand(size, 275), terminated=torch.zeros(size), discount=torch.full((size,), 0.99))
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        for i in range(updates):
            td3.update(agent, target, opt, batch, hp, update_actor=i % hp.policy_delay == 0)
        times.append((time.perf_counter() - started) / updates * 1000)
    return float(np.median(times))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=8000)
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crossq.json"))
    args = parser.parse_args()
    started = time.time()
    with tempfile.TemporaryDirectory() as tmp, Pool(2) as pool:
        rows = pool.map(train_arm, [(arm, seed, args.steps, tmp) for arm in args.arms for seed in args.seeds])
    for row in rows:
        print(f"{row['arm']:>26}  seed {row['seed']}  {row['minutes']:5.2f} min  returns {row['return_by_step']}")
    costs = {"td3 (layer-norm critics, targets)": update_ms(crossq=False), "crossq": update_ms(crossq=True)}
    print("one update at the drive recipe's shapes, one thread: "
          + ", ".join(f"{name} {ms:.2f} ms" for name, ms in costs.items()))
    result = {"benchmark": "crossq", **provenance(started), "env": "Pendulum-v1", "steps": args.steps,
              "seeds": args.seeds, "arms": {arm: ARMS[arm] for arm in args.arms}, "runs": rows,
              "update_ms_drive_shapes": costs}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
