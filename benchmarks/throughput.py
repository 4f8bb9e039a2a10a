"""On-policy training throughput against the env alone and against Stable-Baselines3, as JSON.

For each number of env processes N (default 1, 2 and 4), on the env of a PPO config:

* ``raw``: random actions through drivelab's lockstep subprocess vector env: the ceiling;
* ``drivelab``: drivelab's PPO as configured by default: all envs step together (lockstep);
* ``drivelab_groups``: drivelab's PPO with ``env.step_groups: N``, one step group per env
  (drivelab.envs.groups: each group steps while the trainer chooses the others' actions);
* ``sb3``: Stable-Baselines3's PPO (``pip install stable-baselines3``) on the same env factory in a
  ``SubprocVecEnv``, with the config's rollout length, minibatch, epochs, network, Gaussian std
  and normalisation (``VecNormalize``).

Both sides use one torch thread on the CPU and the config's activation. Training speeds are steady state: env steps per second from the end of the first rollout to the
end of the run (process start-up and the first rollout excluded), updates included. Run it with
nothing else on the machine:

    python benchmarks/throughput.py --config configs/ppo_metadrive_drive.yaml --steps 12288 --out throughput.json
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

from drivelab.api import build_config, train
from drivelab.config import read_yaml, set_dotted
from drivelab.envs import make_env
from drivelab.nets import activation
from training import random_steps_per_second  # benchmarks/training.py


def steady_steps_per_second(rows: list[tuple[int, float]]) -> float:
    """Steps/s between the first and the last (step, time) mark."""
    if len(rows) < 2:
        raise SystemExit("too few rollouts to measure a steady speed: raise --steps (at least 3 rollouts)")
    (step0, time0), (step1, time1) = rows[0], rows[-1]
    return (step1 - step0) / (time1 - time0)


def drivelab_speed(data: dict, num_envs: int, groups: int | None, steps: int) -> float:
    data = json.loads(json.dumps(data))
    set_dotted(data, "env.num_envs", num_envs)
    set_dotted(data, "env.step_groups", groups)
    with tempfile.TemporaryDirectory() as tmp:
        set_dotted(data, "run_dir", str(Path(tmp) / "run"))
        set_dotted(data, "steps", steps)
        set_dotted(data, "eval.every", 0)
        set_dotted(data, "checkpoint_every", 10**9)
        cfg = build_config(data)
        cfg.log_every = cfg.algo_params.num_steps * num_envs   # one row per iteration
        train(cfg, progress=False)
        with open(Path(cfg.run_dir) / "metrics.csv") as f:
            rows = [(int(r["step"]), float(r["time"])) for r in csv.DictReader(f) if r["name"] == "perf/steps_per_s"]
    return steady_steps_per_second(rows)


def sb3_speed(data: dict, num_envs: int, steps: int) -> float:
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
    model = PPO("MlpPolicy", envs, learning_rate=hp.lr, n_steps=hp.num_steps,
                batch_size=hp.num_steps * num_envs // hp.num_minibatches, n_epochs=hp.update_epochs, gamma=hp.gamma,
                gae_lambda=hp.gae_lambda, clip_range=hp.clip_coef, ent_coef=hp.ent_coef, vf_coef=hp.vf_coef,
                max_grad_norm=hp.max_grad_norm, seed=cfg.seed, device="cpu",
                policy_kwargs={"net_arch": {"pi": list(hp.hidden), "vf": list(hp.hidden)},
                               "activation_fn": activation(hp.activation), "log_std_init": hp.log_std_init})
    try:
        model.learn(total_timesteps=steps, callback=marks)
    finally:
        envs.close()
    # from the start of the second rollout (after the first update), as drivelab's first log row
    return steady_steps_per_second(marks.rows[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/ppo_metadrive_drive.yaml")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--steps", type=int, default=12288, help="training steps per measurement")
    parser.add_argument("--seconds", type=float, default=40.0, help="random-action measurement time")
    parser.add_argument("--num-steps", type=int, help="override ppo.num_steps (rollout length per env)")
    parser.add_argument("--skip", nargs="*", default=[], choices=["raw", "drivelab", "drivelab_groups", "sb3"])
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    torch.set_num_threads(1)  # as drivelab's trainer (cfg.torch_threads): the env processes need the cores
    data = read_yaml(args.config)
    if args.num_steps:
        set_dotted(data, "ppo.num_steps", args.num_steps)
    results = []
    for n in args.num_envs:
        row: dict[str, float | int] = {"num_envs": n}
        if "raw" not in args.skip:
            row["raw"] = random_steps_per_second(build_config({**data, "env": {**data["env"], "num_envs": n}}).env,
                                                 args.seconds)
        if "drivelab" not in args.skip:
            row["drivelab"] = drivelab_speed(data, n, None, args.steps)
        if "drivelab_groups" not in args.skip and n > 1:
            row["drivelab_groups"] = drivelab_speed(data, n, n, args.steps)
        if "sb3" not in args.skip:
            row["sb3"] = sb3_speed(data, n, args.steps)
        for name in ("drivelab", "drivelab_groups", "sb3"):
            if name in row and "raw" in row:
                row[f"{name}_vs_raw"] = row[name] / row["raw"]
        print(json.dumps(row), flush=True)
        results.append(row)
    text = json.dumps({"benchmark": "onpolicy-throughput", "config": args.config, "steps": args.steps,
                       "results": results}, indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    sys.exit(main())
