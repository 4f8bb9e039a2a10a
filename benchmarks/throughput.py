"""Training throughput against the env alone (and, for PPO, against Stable-Baselines3), as JSON.

For an off-policy config (DDPG, TD3, SAC; e.g. configs/drive.yaml) the contenders are
``drivelab`` (the config as it is: with ``act_in_workers`` the env workers step while the learner
updates) and ``drivelab_sync`` (the same config with the trainer stepping the envs and updating in
turn), each against ``raw`` measured just before it; their steady speed is measured after the
heat-up (``learning_starts``), and the learner's gradient steps/s (``*_updates_per_s``) are
the stored env steps/s times ``utd``:

    python benchmarks/throughput.py --config configs/drive.yaml --num-envs 1 2 --steps 40000 --repeats 1 --out throughput.json

For PPO:

For each number of env processes N (default 1, 2 and 4), on the env of a PPO config:

* ``raw``: random actions through drivelab's lockstep subprocess vector env: the ceiling (for
  ``drivelab_groups`` also ``raw_groups``: random actions with the envs stepping as N groups);
* ``drivelab``: drivelab's PPO as the config sets it up, with ``env.step_groups`` unset (the drive
  recipe sets ``ppo.act_in_workers``: each env process plays the rollout with a copy of the
  policy, drivelab/training/collection/worker_rollouts.py; without it the trainer steps the envs together);
* ``drivelab_groups``: drivelab's PPO with the trainer stepping the envs (``act_in_workers`` off)
  as ``env.step_groups: N``, one step group per env (drivelab.envs.groups: each group steps
  while the trainer chooses the others' actions);
* ``sb3``: Stable-Baselines3's PPO (``pip install stable-baselines3``) on the same env factory in a
  ``SubprocVecEnv``, with the config's rollout length, minibatch, epochs, network, Gaussian std
  and normalisation (``VecNormalize``), and its ``target_kl`` (SB3 stops at the first minibatch
  beyond 1.5x of it, drivelab at the end of the epoch beyond it).

Both sides use one torch thread on the CPU while collecting and the config's activation;
drivelab's update runs with the config's ``update_threads`` (``--update-threads N`` adds
``drivelab_update_threads``, the same config with N update threads: the env workers wait during
updates), SB3's with one thread (``--sb3-threads``). Training speeds are steady state: env steps
per second from the end of the first rollout to the end of the run (process start-up and the
first rollout excluded), updates included.

This machine's speed drifts by 20% and more within an hour (shared cores), so each training
measurement is paired with a raw measurement taken just before it, and the ratio to raw is taken
per pair; ``--repeats`` pairs per contender, the JSON keeps every pair and the medians. Run it
with nothing else on the machine:

    python benchmarks/throughput.py --config configs/ppo_metadrive_drive.yaml --steps 12288 --repeats 2 --out throughput.json

A fresh policy is the most expensive to train: with ``target_kl`` the update of a trained policy
stops after a few of its epochs (the drive recipe runs 3-5 of its 10 between 100k and 500k steps,
~9 in its last 100k, where the decayed learning rate moves the policy less). ``--from-checkpoint
RUN/checkpoints/step_N`` measures drivelab's contenders continuing a run of the config from that
checkpoint instead (weights, optimiser, normalisation statistics and schedules as they were there),
which is the speed such a run trains at in its steady state. A trained car also loads the env
differently from a random one, so each of those pairs gets a third measurement, ``acting``: the
checkpoint's policy sampling actions in the same envs, stepped the same way (lockstep, or N
groups for ``drivelab_groups``), without learning (``*_vs_acting``). ``--set FIELD=VALUE``
changes the config of every drivelab contender and the env of the ceilings, e.g. ``--set
update_threads=2``. Steps are the trainer's env steps: with ``env.action_repeat: N`` (recorded
per row) each is a decision held for N simulator steps, on both sides of every ratio.
"""

from __future__ import annotations

import argparse
import copy
import csv
import functools
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from drivelab.api import build_config, load_policy, train
from drivelab.training.outputs.checkpoint import checkpoint_step, resolve_checkpoint
from drivelab.config import read_yaml, set_dotted
from drivelab.envs import make_env
from drivelab.training.learning.layers import activation
from training import apply_overrides, env_steps_per_second, report  # benchmarks/training.py


def steady_steps_per_second(rows: list[tuple[int, float]]) -> float:
    """Steps/s between the first and the last (step, time) mark."""
    if len(rows) < 2:
        raise SystemExit("too few rollouts to measure a steady speed: raise --steps (at least 3 rollouts)")
    (step0, time0), (step1, time1) = rows[0], rows[-1]
    return (step1 - step0) / (time1 - time0)


def is_offpolicy(data: dict) -> bool:
    return hasattr(build_config(data).algo_params, "learning_starts")


def drivelab_speed(data: dict, num_envs: int, groups: int | None, steps: int,
                   checkpoint: Path | None = None) -> float:
    """Steady steps/s of drivelab's training with this config (after the heat-up for an off-policy
    one); from ``checkpoint`` (a checkpoint directory of a run of this config) it continues that
    run for ``steps`` steps instead of starting afresh."""
    data = copy.deepcopy(data)
    set_dotted(data, "env.num_envs", num_envs)
    set_dotted(data, "env.step_groups", groups)
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        set_dotted(data, "run_dir", str(run_dir))
        set_dotted(data, "steps", steps + (checkpoint_step(checkpoint) if checkpoint else 0))
        set_dotted(data, "eval.every", 0)
        set_dotted(data, "checkpoint_every", 10**9)
        cfg = build_config(data)
        hp = cfg.algo_params
        heat_up = getattr(hp, "learning_starts", 0)
        cfg.steps += heat_up
        # one row per iteration (per chunk of the env workers, or 64 vector steps off-policy)
        cfg.log_every = num_envs * (hp.num_steps if not heat_up else hp.chunk_steps if hp.act_in_workers else 64)
        if checkpoint:
            shutil.copytree(checkpoint, run_dir / "checkpoints" / checkpoint.name)
        train(cfg, progress=False, resume=checkpoint is not None)
        with open(Path(cfg.run_dir) / "metrics.csv") as f:
            rows = [(int(r["step"]), float(r["time"])) for r in csv.DictReader(f)
                    if r["name"] == "perf/steps_per_s" and int(r["step"]) >= heat_up]
    return steady_steps_per_second(rows)


def sb3_speed(data: dict, num_envs: int, steps: int, threads: int = 1) -> float:
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecNormalize

    cfg = build_config(json.loads(json.dumps({**data, "env": {**data["env"], "num_envs": num_envs}})))
    hp = cfg.algo_params
    envs = SubprocVecEnv([functools.partial(make_env, cfg.env) for _ in range(num_envs)], start_method="spawn")
    envs = VecNormalize(envs, norm_obs=hp.normalize_obs, norm_reward=hp.normalize_reward, gamma=hp.gamma)

    class Marks(BaseCallback):
        def __init__(self):
            super().__init__()
            self.rows: list[tuple[int, float]] = []

        def _on_rollout_start(self) -> None:
            self.rows.append((self.num_timesteps, time.perf_counter()))

        def _on_training_end(self) -> None:
            self.rows.append((self.num_timesteps, time.perf_counter()))

        def _on_step(self) -> bool:
            return True

    marks = Marks()
    torch.set_num_threads(threads)
    model = PPO("MlpPolicy", envs, learning_rate=hp.lr, n_steps=hp.num_steps,
                batch_size=hp.num_steps * num_envs // hp.num_minibatches, n_epochs=hp.update_epochs, gamma=hp.gamma,
                gae_lambda=hp.gae_lambda, clip_range=hp.clip_coef, ent_coef=hp.ent_coef, vf_coef=hp.vf_coef,
                max_grad_norm=hp.max_grad_norm, target_kl=hp.target_kl, seed=cfg.seed, device="cpu",
                policy_kwargs={"net_arch": {"pi": list(hp.hidden), "vf": list(hp.hidden)},
                               "activation_fn": activation(hp.activation), "log_std_init": hp.log_std_init})
    try:
        model.learn(total_timesteps=steps, callback=marks)
    finally:
        envs.close()
        torch.set_num_threads(1)
    # from the start of the second rollout (after the first update), as drivelab's first log row
    return steady_steps_per_second(marks.rows[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/ppo_metadrive_drive.yaml")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--steps", type=int, default=12288, help="training steps per measurement")
    parser.add_argument("--seconds", type=float, default=25.0, help="random-action measurement time")
    parser.add_argument("--repeats", type=int, default=2, help="(raw, training) pairs per contender")
    parser.add_argument("--num-steps", type=int, help="override ppo.num_steps (rollout length per env)")
    parser.add_argument("--sb3-threads", type=int, default=1, help="torch threads for SB3 (collection and update)")
    parser.add_argument("--update-threads", type=int, help="also measure drivelab with this update_threads "
                        "(drivelab_update_threads)")
    parser.add_argument("--skip", nargs="*", default=[], choices=["drivelab", "drivelab_groups", "drivelab_sync", "sb3",
                                                                   "drivelab_update_threads"])
    parser.add_argument("--from-checkpoint", metavar="CKPT",
                        help="drivelab's contenders continue this checkpoint (or run directory) of a run of --config "
                             "instead of starting afresh: the steady state of a trained policy, e.g. with target_kl "
                             "ending its updates early (SB3 still starts afresh)")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="config overrides for drivelab's contenders (SB3 reads the config as given)")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    started = time.time()
    checkpoint = resolve_checkpoint(args.from_checkpoint) if args.from_checkpoint else None
    # `acting`: the checkpoint's policy sampling actions without learning, the ceiling for continuing
    # its run (a trained car ends episodes, and rebuilds maps, at other rates than a random one)
    acting_policy = load_policy(checkpoint)[0] if checkpoint else None
    torch.set_num_threads(1)  # as drivelab's trainer (cfg.torch_threads): the env processes need the cores
    data = read_yaml(args.config)
    if args.num_steps:
        set_dotted(data, "ppo.num_steps", args.num_steps)
    tuned = copy.deepcopy(data)  # drivelab's contenders: the config with --set applied
    apply_overrides(tuned, args.set)
    trainer_steps = copy.deepcopy(tuned)  # step groups are the trainer's way of stepping the envs
    set_dotted(trainer_steps, f"{data.get('algo', 'ppo')}.act_in_workers", False)
    contenders = {
        "drivelab": lambda n: drivelab_speed(tuned, n, None, args.steps, checkpoint=checkpoint),
        "drivelab_groups": lambda n: drivelab_speed(trainer_steps, n, n, args.steps, checkpoint=checkpoint),
        "sb3": lambda n: sb3_speed(data, n, args.steps, args.sb3_threads),
    }
    offpolicy = is_offpolicy(data)
    if offpolicy:  # the learner beside the env workers, and in turn with them
        algo = data["algo"]
        synchronous = copy.deepcopy(tuned)
        set_dotted(synchronous, f"{algo}.act_in_workers", False)
        contenders = {"drivelab": contenders["drivelab"],
                      "drivelab_sync": lambda n: drivelab_speed(synchronous, n, None, args.steps)}
    if args.update_threads:
        contenders["drivelab_update_threads"] = lambda n: drivelab_speed({**tuned, "update_threads": args.update_threads},
                                                                         n, None, args.steps, checkpoint=checkpoint)
    results = []
    for n in args.num_envs:
        # the ceilings step the env drivelab's contenders train on (--set env.* included)
        env_cfg = build_config({**tuned, "env": {**tuned["env"], "num_envs": n, "step_groups": None}}).env
        row: dict = {"num_envs": n, "action_repeat": env_cfg.action_repeat, "pairs": {}}
        for name, measure in contenders.items():
            if name in args.skip or (name == "drivelab_groups" and n == 1):
                continue
            groups = n if name == "drivelab_groups" else 1  # how the contender's envs step
            pairs = []
            for _ in range(args.repeats):
                pair = {"raw": env_steps_per_second(env_cfg, args.seconds)}
                if groups > 1:
                    pair["raw_groups"] = env_steps_per_second(env_cfg, args.seconds, groups=groups)
                if acting_policy is not None and name != "sb3":
                    pair["acting"] = env_steps_per_second(env_cfg, args.seconds, acting_policy, groups)
                pair["trained"] = measure(n)
                pairs.append(pair)
            row["pairs"][name] = pairs
            row[name] = statistics.median(p["trained"] for p in pairs)
            if offpolicy:
                row[f"{name}_updates_per_s"] = row[name] * build_config(tuned).algo_params.utd
            for ceiling in ("raw", "raw_groups", "acting"):
                if ceiling in pairs[0]:
                    row[f"{name}_vs_{ceiling}"] = statistics.median(p["trained"] / p[ceiling] for p in pairs)
        row["raw"] = statistics.median(p["raw"] for pairs in row["pairs"].values() for p in pairs)
        print(json.dumps({k: v for k, v in row.items() if k != "pairs"}), flush=True)
        results.append(row)
    report({"benchmark": "offpolicy-throughput" if offpolicy else "onpolicy-throughput", "config": args.config, "steps": args.steps,
            "from_checkpoint": str(checkpoint) if checkpoint else None, "overrides": args.set,
            "repeats": args.repeats, "sb3_threads": args.sb3_threads, "results": results}, args.out, started)


if __name__ == "__main__":
    sys.exit(main())
