"""Training benchmarks, written as JSON. Not part of the test suite. `learn` works for every
algorithm's config; `speed` is for the on-policy family (A2C, PPO, GRPO).

Speed: raw vectorised env steps/s with random actions, training steps/s, and where the
trainer's wall time goes (perf/env_fraction, perf/update_fraction, perf/other_fraction: policy
inference during collection, storage, bookkeeping):

    python benchmarks/training.py speed --algo ppo --config configs/ppo_metadrive.yaml --steps 8192

Learning: train from a config, then evaluate deterministically:

    python benchmarks/training.py learn --config configs/ppo_lunarlander.yaml --steps 300000 --episodes 20
    python benchmarks/training.py learn --config configs/ppo_metadrive.yaml --minutes 20 \\
        --eval-env MetaDrive-validation-v0 --episodes 100
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.api import build_config, evaluate_checkpoint, train
from drivelab.training.outputs.checkpoint import checkpoint_step
from drivelab.config import parse_value, read_yaml, set_dotted
from drivelab.envs.groups import EnvGroups
from provenance import provenance  # benchmarks/provenance.py


def report(result: dict, out: str | None, started: float) -> None:
    """Print a benchmark's JSON result with its provenance (``started``: the time.time() its main
    began), and write it to ``out`` when given."""
    # The result's own keys win (e.g. inference_latency.py's "threads": 1): provenance adds only the keys it lacks
    text = json.dumps({**result, **{k: v for k, v in provenance(started).items() if k not in result}}, indent=1)
    print(text)
    if out:
        Path(out).write_text(text + "\n")


def load(args) -> object:
    data = read_yaml(args.config) if args.config else {}
    for key, value in (("algo", args.algo), ("env.id", args.env), ("env.num_envs", args.num_envs), ("seed", args.seed)):
        if value is not None:
            set_dotted(data, key, value)
    return build_config(data)


def apply_overrides(data: dict, items: list[str]) -> None:
    """Apply ``FIELD=VALUE`` overrides (a benchmark's ``--set``) to config data, values read as
    on drivelab's command line (:func:`drivelab.config.parse_value`)."""
    for item in items:
        field, _, value = item.partition("=")
        set_dotted(data, field, parse_value(value))


def env_steps_per_second(env_cfg, seconds: float = 20.0, policy=None, groups: int = 1) -> float:
    """Vectorised env steps/s for an `EnvConfig` without learning: random actions, or with
    ``policy`` (a trained policy, e.g. ``drivelab.api.load_policy``) its sampled actions.

    ``groups > 1`` steps the envs as that many independent groups, as ``env.step_groups`` does in
    training (:class:`drivelab.envs.groups.EnvGroups`): a group's next actions are chosen as soon
    as its step is back, while the others simulate. With 1 group it is a lockstep vector env."""
    if groups > 1 and env_cfg.resolved_backend() != "async":
        raise SystemExit(f"{groups} step groups need subprocess envs: set env.backend: async in the config")
    envs = EnvGroups(env_cfg, groups, autoreset_mode=AutoresetMode.SAME_STEP)
    try:
        spaces = [group.action_space for group in envs.envs]
        for group, space in enumerate(spaces):
            space.seed(group)
        obs = envs.reset(list(range(env_cfg.num_envs)))  # env i on seed i

        def act(group: int) -> None:
            if policy is None:
                envs.send(group, spaces[group].sample())
            else:
                group_obs = torch.as_tensor(obs[envs.slices[group]])
                envs.send(group, policy.to_env(policy.act(group_obs, deterministic=False)))

        all_groups = list(range(groups))
        sizes = [envs_of.stop - envs_of.start for envs_of in envs.slices]
        steps, started = 0, time.perf_counter()
        for group in all_groups:
            act(group)
        while time.perf_counter() - started < seconds:
            group = envs.wait_any(all_groups)
            obs[envs.slices[group]] = envs.receive(group)[0]
            steps += sizes[group]
            act(group)
        return steps / (time.perf_counter() - started)
    finally:
        envs.close()


def metric_means(run_dir: Path, names: tuple[str, ...], skip_first: int = 1) -> dict[str, float]:
    values: dict[str, list[float]] = {name: [] for name in names}
    with open(run_dir / "metrics.csv") as f:
        for row in csv.DictReader(f):
            if row["name"] in values:
                values[row["name"]].append(float(row["value"]))
    return {name: float(np.mean(v[skip_first:] or v)) if v else float("nan") for name, v in values.items()}


def speed(args) -> dict:
    cfg = load(args)
    with tempfile.TemporaryDirectory() as tmp:
        cfg.run_dir, cfg.steps = str(Path(tmp) / "run"), args.steps
        raw = env_steps_per_second(cfg.env, args.seconds)
        started = time.perf_counter()
        train(cfg, progress=False)
        wall = time.perf_counter() - started
        perf = metric_means(Path(cfg.run_dir), ("perf/other_fraction", "perf/env_fraction", "perf/update_fraction"))
        with open(Path(cfg.run_dir) / "metrics.csv") as f:
            final_step = max(int(r["step"]) for r in csv.DictReader(f))
    return {"benchmark": "onpolicy-speed", "algo": cfg.algo, "env": cfg.env.id, "num_envs": cfg.env.num_envs,
            "random_env_steps_per_s": raw, "train_steps_per_s": final_step / wall, "train_wall_s": wall,
            "other_fraction": perf["perf/other_fraction"], "env_fraction": perf["perf/env_fraction"],
            "update_fraction": perf["perf/update_fraction"]}


def learn(args) -> dict:
    cfg = load(args)
    run_dir = Path(args.run_dir or tempfile.mkdtemp(prefix="drivelab-bench-")) / "run"
    cfg.run_dir = str(run_dir)
    if args.steps:
        cfg.steps = args.steps
    if args.minutes:  # train until the time budget is spent (cfg.steps stays an upper bound)
        cfg.max_minutes = args.minutes
        cfg.steps = max(cfg.steps, 10**9) if not args.steps else cfg.steps
    started = time.perf_counter()
    train(cfg, progress=not args.no_progress)
    wall = time.perf_counter() - started
    kwargs = dict(item.split("=", 1) for item in args.eval_kwarg)
    result, env_cfg, ckpt = evaluate_checkpoint(run_dir, episodes=args.episodes, env_id=args.eval_env,
                                                env_kwargs={k: json.loads(v) for k, v in kwargs.items()})
    return {"benchmark": "learn", "algo": cfg.algo, "env": cfg.env.id, "eval_env": env_cfg.id,
            "steps": checkpoint_step(ckpt), "train_wall_s": wall, "train_steps_per_s": checkpoint_step(ckpt) / wall, "run_dir": str(run_dir), **result.summary()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("speed", "learn"):
        p = sub.add_parser(name)
        p.add_argument("--config")
        p.add_argument("--algo")
        p.add_argument("--env")
        p.add_argument("--num-envs", type=int)
        p.add_argument("--seed", type=int)
        p.add_argument("--steps", type=int, default=8192 if name == "speed" else None)
        p.add_argument("--out", help="also write the JSON here")
    sub.choices["speed"].add_argument("--seconds", type=float, default=20.0, help="random-action measurement time")
    learn_p = sub.choices["learn"]
    learn_p.add_argument("--minutes", type=float, help="train for about this long instead of --steps")
    learn_p.add_argument("--episodes", type=int, default=20)
    learn_p.add_argument("--eval-env")
    learn_p.add_argument("--eval-kwarg", action="append", default=[], metavar="KEY=JSON")
    learn_p.add_argument("--run-dir", help="keep the run here (default: a temporary directory)")
    learn_p.add_argument("--no-progress", action="store_true")
    args = parser.parse_args()
    started = time.time()
    result = speed(args) if args.command == "speed" else learn(args)
    report(result, args.out, started)


if __name__ == "__main__":
    sys.exit(main())
