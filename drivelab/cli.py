"""The ``drivelab`` command.

    drivelab train --algo reinforce --env CartPole-v1 --steps 20000 --seed 0 --run-dir runs/cartpole
    drivelab train --config configs/reinforce_metadrive.yaml --reinforce.lr 0.001 --env.kwargs.num_scenarios 10
    drivelab train --resume runs/cartpole --steps 40000
    drivelab eval runs/cartpole --episodes 10 [--env MetaDrive-validation-v0] [--json]
    drivelab train --config ppo_metadrive_drive --env.backend ray --ppo.act_in_workers false --ray-address auto
    drivelab sweep configs/ppo_cartpole.yaml --grid ppo.lr=1e-4,3e-4 --seeds 0-4 --out runs/sweep-lr

Any config field can be set with a dotted flag (``--env.num_envs 4``, ``--reinforce.gamma 0.95``);
values are read as YAML scalars (``3x3`` stays text, ``[64, 64]`` is a list, ``null`` is None).
Bad input ends with one line on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import shlex
import signal
import sys
import traceback
from pathlib import Path
from typing import Any

# Nothing imported here loads torch (the algorithms are imported when their entry in ALGORITHMS is
# read): the commands import drivelab.api when they run, so that `drivelab --help`, `--version`
# and `drivelab train --help` answer at once.
from drivelab.algos import ALGORITHMS
from drivelab.config import parse_value
from drivelab.envs.supervised import error_line
from drivelab.errors import DrivelabError, Terminated, TrainingCrashed, raise_interrupt
from drivelab.tools.baselines import BASELINES
from drivelab.tools.tables import format_evaluation, format_evaluations
from drivelab.version import __version__


def parse_overrides(tokens: list[str]) -> dict[str, Any]:
    """['--a.b', '1', '--c=x'] -> {'a.b': 1, 'c': 'x'}."""
    overrides: dict[str, Any] = {}
    i = 0
    while i < len(tokens):
        token = tokens[i]
        if not token.startswith("--") or len(token) == 2:
            raise DrivelabError(f"unexpected argument {token!r}")
        key, eq, value = token[2:].partition("=")
        if not eq:
            if i + 1 >= len(tokens) or tokens[i + 1].startswith("--"):
                raise DrivelabError(f"option --{key} needs a value")
            value = tokens[i + 1]
            i += 1
        key = ".".join(part if part == "kwargs" else part.replace("-", "_") for part in key.split("."))
        overrides[key] = parse_value(value)
        i += 1
    return overrides


def _train_parser(sub, epilog: str | None = None) -> None:
    p = sub.add_parser("train", help="train an agent", epilog=epilog or "drivelab train --algo ALGO --help lists ALGO's hyperparameters",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Train an agent. Any config field can be set with --section.field VALUE.")
    p.add_argument("--config", help="YAML config file, or the name of a shipped config (drivelab configs)")
    p.add_argument("--resume", metavar="RUN_DIR", help="continue the run in RUN_DIR (or mlflow:RUN_ID, fetched into "
                                                       "--run-dir or runs/mlflow-RUN_ID) from its latest checkpoint")
    p.add_argument("--resume-if-exists", action="store_true",
                   help="with --run-dir: start the run if the directory holds none yet, else continue it (the one "
                        "command to requeue on a preemptible cluster; the config must describe the same run)")
    p.add_argument("--algo", help=f"algorithm: {', '.join(ALGORITHMS)}")
    p.add_argument("--env", help="Gymnasium env id, e.g. CartPole-v1 or MetaDrive-10env-v0")
    p.add_argument("--steps", type=int, help="total env steps to train for")
    p.add_argument("--seed", type=int)
    p.add_argument("--run-dir", help="where to write logs and checkpoints (default runs/<algo>-<env>-s<seed>-<time>)")
    p.add_argument("--num-envs", type=int, help="parallel environments")
    p.add_argument("--actions", metavar="NxM", help="discretise [steering, throttle] into N x M actions (env.action_grid)")
    p.add_argument("--mlflow", action="store_true", help="also track with MLflow")
    p.add_argument("--wandb", action="store_true", help="also track with Weights & Biases (offline without an API key; "
                                                       "pip install 'drivelab[wandb]')")
    p.add_argument("--wandb-project", help="W&B project (default: drivelab)")
    p.add_argument("--mlflow-uri", help="MLflow tracking URI (default: sqlite:///<run dir's parent>/mlflow.db, "
                                        "e.g. runs/mlflow.db, shared by the runs beside it)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--ray-address", help="Ray cluster for --env.backend ray / --eval.backend ray: auto (the cluster "
                                         "on this machine), ray://HOST:10001, HOST:6379 (default: a local Ray instance)")


def _sweep_parser(sub) -> None:
    p = sub.add_parser("sweep", help="run a grid of configs x seeds in parallel on Ray Tune, then tabulate",
                       description="Every combination of --grid values and --seeds is a normal, resumable drivelab run "
                                   "in OUT/<setting>-s<seed>; running the sweep again resumes the unfinished ones. "
                                   "Ends with a table (mean and 95%% CI over seeds of the final metrics) and plots.")
    p.add_argument("config", help="YAML config file or shipped config name; its optional `sweep:` section holds a grid and seeds")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2", help="a config field and its values (repeatable)")
    p.add_argument("--seeds", help="e.g. 0-4 or 0,1,2 (default: the config's sweep.seeds, else 0)")
    p.add_argument("--space", action="append", default=[], metavar="KEY=DIST:A,B",
                   help="search instead of a grid: a config field and its distribution, loguniform|uniform|int:LOW,HIGH "
                        "or choice:V1,V2 (repeatable); Optuna picks the values")
    p.add_argument("--trials", type=int, help="search: how many runs Optuna samples (default 8)")
    p.add_argument("--metric", help="search: the logged metric that ranks the trials (default eval/return_mean)")
    p.add_argument("--mode", choices=["max", "min"], help="search: maximise or minimise --metric (default max)")
    p.add_argument("--asha", action="store_true", default=None,
                   help="search: stop the trials that trail at an evaluation (ASHA early stopping)")
    p.add_argument("--steps", type=int, help="env steps per run (overrides the config)")
    p.add_argument("--env", help="env id for every run (overrides the config), e.g. my_env:MyEnv; its module must be "
                                 "importable where the runs train (installed, or on PYTHONPATH on every Ray node)")
    p.add_argument("--out", help="sweep directory (default runs/sweep-<config name>)")
    p.add_argument("--ray-address", help="Ray cluster to run on (default: a local Ray instance)")
    p.add_argument("--cpus-per-trial", type=float, default=1.0, help="CPUs Ray reserves for each run")
    p.add_argument("--max-concurrent", type=int, help="at most this many runs at once (default: as the CPUs allow)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (trials done)")


def _eval_parser(sub) -> None:
    p = sub.add_parser("eval", help="evaluate checkpoints, runs' latest checkpoints, or baseline policies",
                       description="Evaluate deterministically; several paths and --policy values give one table, "
                                   "all on the same env and seeds.")
    p.add_argument("path", nargs="*", help="run directory, checkpoint directory (e.g. RUN/checkpoints/best) or "
                                           "a shipped driver's name (drivelab models)")
    p.add_argument("--card", action="store_true", help="show the model card of each driver given, do not evaluate")
    p.add_argument("--policy", action="append", default=[], choices=BASELINES,
                   help="also evaluate a reference policy (repeatable); on --env, else the checkpoints' env, "
                        "else MetaDrive-validation-v0")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--env", help="evaluate on another env id (the training env's kwargs are then dropped)")
    p.add_argument("--env-kwarg", action="append", default=[], metavar="KEY=VALUE", help="env keyword override (repeatable)")
    p.add_argument("--num-envs", type=int, help="parallel environments (default: as in training)")
    p.add_argument("--seed", type=int, default=0, help="episode k is reset with seed SEED+k")
    p.add_argument("--stochastic", action="store_true",
                   help="sample actions instead of taking the mode (checkpoints and the expert)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--video", metavar="FILE", help="record the episodes into one video (.mp4, or .gif); plays on one env")
    p.add_argument("--video-dir", metavar="DIR", help="record one video per episode into DIR (episode_<k>.mp4)")
    p.add_argument("--no-overlay", action="store_true", help="videos without the text overlay")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (episodes done per policy, on stderr)")
    p.add_argument("--mlflow-uri", help="where mlflow:RUN_ID paths live (default: $MLFLOW_TRACKING_URI, else runs/mlflow.db)")


def build_parser(train_epilog: str | None = None) -> argparse.ArgumentParser:
    parser = OneLineErrors(prog="drivelab", description="Reinforcement learning for driving simulators.")
    parser.add_argument("--version", action="version", version=f"drivelab {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an unexpected error "
                                                            "(also: DRIVELAB_DEBUG=1)")
    sub = parser.add_subparsers(dest="command", required=True)
    _train_parser(sub, train_epilog)
    _eval_parser(sub)
    sub.add_parser("envs", help="list drivelab's MetaDrive env ids")
    sub.add_parser("configs", help="list the shipped configs (drivelab train --config NAME)")
    sub.add_parser("models", help="list the trained drivers that ship with drivelab (drivelab eval NAME --card)")
    report = sub.add_parser("report", help="one self-contained HTML report of runs: curves, evaluation, video")
    report.add_argument("runs", nargs="+", metavar="RUN")
    report.add_argument("--out", help="HTML file (default: RUN/report.html for one run, report.html otherwise)")
    report.add_argument("--episodes", type=int, default=10, help="evaluation episodes per policy")
    report.add_argument("--no-baselines", action="store_true", help="skip the reference policies")
    report.add_argument("--no-progress", action="store_true", help="no progress bar")
    plot = sub.add_parser("plot", help="training curves of runs (seeds of one config: mean and 95%% CI band)")
    plot.add_argument("runs", nargs="+", metavar="RUN")
    plot.add_argument("--metric", action="append", help="a metric to draw, e.g. eval/success_rate (repeatable; "
                                                        "default: return, entropy, losses, driving metrics)")
    plot.add_argument("--out", help="PNG file (default: RUN/curves.png for one run, curves.png otherwise)")
    plot.add_argument("--window", type=int, default=10, help="rolling mean over this many logged points")
    plot.add_argument("--x", choices=("steps", "time"), default="steps", help="env steps or wall time")
    export = sub.add_parser("export", help="export a trained policy to ONNX or TorchScript (runs without drivelab)")
    export.add_argument("path", help="run directory, checkpoint directory, or RUN/best")
    export.add_argument("--format", default="onnx", choices=("onnx", "torchscript"))
    export.add_argument("--out", required=True, help="output directory (policy.onnx or policy.pt, and policy.json)")
    demos = sub.add_parser("demos", help="record a trained policy's transitions as prior data for an off-policy "
                                         "learner (its prior_data)")
    demos.add_argument("policy", help="run directory, checkpoint directory, RUN/best or a shipped driver")
    demos.add_argument("--config", help="the learner's config, whose env the policy plays (default: the policy's own env)")
    demos.add_argument("--steps", type=int, required=True, help="env steps to record")
    demos.add_argument("--out", required=True, help="the demonstration file (.safetensors)")
    demos.add_argument("--seed", type=int, default=0, help="seeds the envs' resets")
    demos.add_argument("--stochastic", action="store_true", help="sampled actions instead of the deterministic ones")
    demos.add_argument("--no-progress", action="store_true")
    _reward_parser(sub)
    _sweep_parser(sub)
    return parser


def _reward_parser(sub) -> None:
    reward = sub.add_parser("reward", help="plot a reward function, or compare reward functions on the same episodes")
    tools = reward.add_subparsers(dest="tool", required=True)
    plot = tools.add_parser("plot", help="reward against cross-track error and heading error, to a PNG")
    plot.add_argument("--reward", required=True, metavar="FILE.yaml", help="reward terms (e.g. configs/rewards/cte.yaml)")
    plot.add_argument("--out", default="reward.png")
    plot.add_argument("--max-cte", type=float, default=3.0)
    plot.add_argument("--speed", type=float, default=10.0, help="speed (m/s) for speed-dependent terms")
    compare = tools.add_parser("compare", help="score the same episodes under several reward configs")
    compare.add_argument("--rewards", nargs="+", required=True, metavar="FILE.yaml")
    compare.add_argument("--env", default="drivelab/MetaDriveLaneFollow-v0")
    compare.add_argument("--policy", default="lane-keeping", help="random, lane-keeping, or a run/checkpoint directory")
    compare.add_argument("--episodes", type=int, default=3)
    compare.add_argument("--seed", type=int, default=0)
    compare.add_argument("--env-kwarg", action="append", default=[], metavar="KEY=VALUE")
    compare.add_argument("--max-steps", type=int, default=1000)
    compare.add_argument("--out", default="reward_compare.png")
    compare.add_argument("--json", action="store_true")


# The config field that each of `drivelab train`'s named flags sets: --num-envs (dest num_envs)
# sets env.num_envs. (--mlflow and --wandb switch track.mlflow and track.wandb on.)
TRAIN_FLAGS = {"algo": "algo", "env": "env.id", "steps": "steps", "seed": "seed", "run_dir": "run_dir",
               "num_envs": "env.num_envs", "actions": "env.action_grid", "mlflow_uri": "track.mlflow_uri",
               "wandb_project": "track.wandb_project", "ray_address": "ray_address"}


def _train_overrides(args: argparse.Namespace, extra: dict[str, Any]) -> dict[str, Any]:
    """The config fields that ``drivelab train``'s flags set (dotted keys), the --section.field flags last."""
    flags = {field: getattr(args, dest) for dest, field in TRAIN_FLAGS.items()}
    flags |= {"track.mlflow": True if args.mlflow else None, "track.wandb": True if args.wandb else None}
    return {k: v for k, v in flags.items() if v is not None} | extra


def check_flag_names(extra: dict[str, Any]) -> None:
    """A --section.field flag that names no config field stops here, with the flag that was
    probably meant: ``--num_envs`` -> did you mean --num-envs (or --env.num_envs)? (The config's
    own check names fields, which in a YAML file is right; on the command line a flag is.)"""
    from drivelab.config import RETIRED_FIELDS, TrainConfig, closest_field, is_field

    for key in extra:
        section, _, rest = key.partition(".")
        if rest in RETIRED_FIELDS.get(section, {}):
            continue  # a removed option: the config says so, and what to do
        if section in ALGORITHMS:  # --ppo.gamma: a field of that algorithm's hyperparameters
            if not rest:
                continue  # a whole section (--ppo '{lr: 0.001}'): the config checks its value
            cls, path, prefix = ALGORITHMS[section].params, rest, f"{section}."
        else:
            cls, path, prefix = TrainConfig, key, ""
        if is_field(path, cls):
            continue
        meant = closest_field(path, cls)
        if meant is None:
            listed = f"--algo {section} --help lists its hyperparameters" if prefix else "--help lists the config fields"
            raise DrivelabError(f"unknown option --{key}; drivelab train {listed}")
        # the dotted flag of that field, after the named flag that sets it, if one does (--num-envs
        # sets env.num_envs; --run-dir is run_dir's own)
        named = next((dest for dest, field in TRAIN_FLAGS.items() if field == prefix + meant), None)
        flags = [f"--{prefix}{meant}"] if named != prefix + meant else []
        flags = ([f"--{named.replace('_', '-')}"] if named else []) + flags
        raise DrivelabError(f"unknown option --{key} (did you mean {' or '.join(flags)}?)")


def cmd_train(args: argparse.Namespace, extra: dict[str, Any]) -> int:
    from drivelab import api

    if args.resume:
        args.resume = _local_run(args.resume, args.mlflow_uri, args.run_dir)
    if args.resume and args.resume_if_exists:
        raise DrivelabError("give --resume RUN_DIR or --resume-if-exists (with --run-dir), not both")
    check_flag_names(extra)
    cfg = api.train_config(_train_overrides(args, extra), args.config, resume=args.resume,
                           if_exists=args.resume_if_exists)
    resume = "auto" if args.resume_if_exists else bool(args.resume)
    run_dir, metrics = api.train(cfg, resume=resume, progress=not args.no_progress)
    shown = [(k, v) for k, v in metrics.items() if k.startswith(("episode/", "eval/")) and "reward/" not in k]
    if shown:
        print("last logged: " + ", ".join(f"{k} {v:.3g}" for k, v in shown))
    print(f"run saved in {run_dir} (config.yaml, metrics.csv, tb/, checkpoints/)")
    # the next commands, shell-quoted: a run directory with spaces pastes as one argument
    evaluate = shlex.join(["drivelab", "eval", str(run_dir), "--episodes", "10"])
    print(f"  evaluate: {evaluate}    watch: {shlex.join(['tensorboard', '--logdir', str(Path(run_dir) / 'tb')])}")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from drivelab import api
    from drivelab.tools.sweep import format_search, format_summary, load_search, load_sweep, run_search, run_sweep

    out = Path(args.out or Path("runs") / f"sweep-{Path(args.config).stem}")
    searched = load_search(args.config, args.space, args.seeds, args.steps, trials=args.trials, metric=args.metric,
                           mode=args.mode, asha=args.asha, env=args.env)
    if searched is not None:
        if args.grid:
            raise DrivelabError("give --grid or --space (a search), not both")
        base, search, seed = searched
        summary = run_search(base, search, seed, out, train=api.train, ray_address=args.ray_address,
                             cpus_per_trial=args.cpus_per_trial, max_concurrent=args.max_concurrent,
                             progress=not args.no_progress)
        print(format_search(summary))
        if "best" in summary:
            best = summary["best"]
            print(f"best: {best['run']} ({search.metric} {best['metric']:.4g}); search saved in {out} "
                  "(sweep.json, sweep.md, curves.png, one run directory per trial)")
        return 0 if "best" in summary else 1
    base, grid, seeds = load_sweep(args.config, args.grid, args.seeds, args.steps, env=args.env)
    summary = run_sweep(base, grid, seeds, out, train=api.train, ray_address=args.ray_address,
                        cpus_per_trial=args.cpus_per_trial, max_concurrent=args.max_concurrent,
                        progress=not args.no_progress)
    print(format_summary(summary))
    print(f"sweep saved in {out} (sweep.json, sweep.md, curves.png{', final.png' if (out / 'final.png').is_file() else ''}, "
          "one run directory per setting and seed)")
    if summary.get("failed"):
        print("failed runs (rerun the same command to resume them):\n  " + "\n  ".join(summary["failed"]), file=sys.stderr)
        return 1
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from drivelab import api

    if not args.path and not args.policy:
        raise DrivelabError("drivelab eval needs a run or checkpoint directory, or --policy NAME for a baseline")
    kwargs = _env_kwargs(args.env_kwarg)
    args.path = [_local_run(path, args.mlflow_uri) for path in args.path]
    if args.card:
        print("\n\n".join(api.model_card(path) for path in args.path))
        return 0
    if (args.video or args.video_dir) and len(args.path) + len(args.policy) != 1:
        raise DrivelabError("--video and --video-dir record one policy: give one path or one --policy")
    rows: list[dict[str, Any]] = []
    env_cfg = None
    for path in args.path:
        result, env_cfg, ckpt = api.evaluate_checkpoint(path, args.episodes, args.env, kwargs, args.num_envs,
                                                        args.seed, deterministic=not args.stochastic,
                                                        recorder=_recorder(args), progress=not args.no_progress)
        rows.append(api.evaluation_row(result, env_cfg.id, ckpt))  # the dict drivelab.evaluate returns
    if args.policy:
        base = api.baseline_env(env_cfg, args.env, kwargs, num_envs=args.num_envs or 2)
        for name in args.policy:
            rows.append({**api.evaluate_baseline(name, base, args.episodes, args.seed, _recorder(args),
                                                 deterministic=not args.stochastic,
                                                 progress=not args.no_progress).summary(),
                         "env": base.id, "policy": name})
    nonfinite = [f"{k}={v}" for row in rows for k, v in row.items() if isinstance(v, float) and not math.isfinite(v)]
    if args.json:  # always valid JSON: a non-finite number is null
        clean = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()} for row in rows]
        print(json.dumps(clean[0] if len(clean) == 1 else clean, allow_nan=False))
    elif len(rows) == 1:
        row = rows[0]
        what = f"{row['checkpoint']} (step {row['step']})" if "checkpoint" in row else f"the {row['policy']} baseline"
        print(format_evaluation(row, row["env"], what))
    else:
        print(format_evaluations(rows, args.episodes, args.seed, sampled=args.stochastic))
    if nonfinite:
        raise DrivelabError(f"evaluation gave non-finite results ({', '.join(nonfinite[:3])}): the policy or env diverged")
    return 0


def _local_run(path: str, tracking_uri: str | None, into: str | None = None) -> str:
    """``mlflow:RUN_ID`` -> a local run directory fetched from the run's artifacts; other paths as they are."""
    if not path.startswith("mlflow:"):
        return path
    from drivelab.training.outputs.tracking import fetch_mlflow_run

    return str(fetch_mlflow_run(path, tracking_uri, Path(into or Path("runs") / f"mlflow-{path.split(':', 1)[1]}")))


def _recorder(args: argparse.Namespace):
    """The video recorder that --video / --video-dir ask for, or None."""
    from drivelab.training.outputs.video import Recorder

    if args.video and args.video_dir:
        raise DrivelabError("give --video or --video-dir, not both")
    if args.video:
        return Recorder(args.video, with_overlay=not args.no_overlay)
    if args.video_dir:
        return Recorder(args.video_dir, per_episode=True, with_overlay=not args.no_overlay)
    return None


def _env_kwargs(items: list[str]) -> dict[str, Any]:
    kwargs = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise DrivelabError(f"--env-kwarg expects KEY=VALUE, got {item!r}")
        kwargs[key] = parse_value(value)
    return kwargs


def cmd_reward(args: argparse.Namespace) -> int:
    from drivelab.tools import reward_tools

    if args.tool == "plot":
        path = reward_tools.plot_reward(reward_tools.load_reward_config(args.reward), args.out, args.max_cte, args.speed)
        print(f"wrote {path}")
        return 0
    configs = {Path(f).stem: reward_tools.load_reward_config(f) for f in args.rewards}
    trajectories = reward_tools.record_episodes(args.env, args.policy, args.episodes, args.seed,
                                                _env_kwargs(args.env_kwarg), args.max_steps)
    table = reward_tools.compare_rewards(trajectories, configs)
    reward_tools.plot_comparison(trajectories, configs, args.out)
    if args.json:
        print(json.dumps({"env": args.env, "policy": args.policy, "episodes": args.episodes, "table": table}))
    else:
        print(f"{args.episodes} episodes of {args.env} with policy '{args.policy}', scored under each reward config:")
        print(reward_tools.format_comparison(table))
        print(f"wrote {args.out}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from drivelab.tools.report import write_report

    path = write_report(args.runs, args.out, args.episodes, baselines=not args.no_baselines,
                        progress=not args.no_progress)
    print(f"wrote {path}")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from drivelab.training.outputs.plots import plot_runs

    out = args.out or (Path(args.runs[0]) / "curves.png" if len(args.runs) == 1 else "curves.png")
    print(f"wrote {plot_runs(args.runs, out, args.metric, args.window, args.x)}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from drivelab import api

    path = api.load(args.path).export(args.out, args.format)
    print(f"wrote {path} and {Path(args.out) / 'policy.json'}")
    return 0


def cmd_demos(args: argparse.Namespace) -> int:
    from drivelab import api
    from drivelab.tools.demonstrations import record_demonstrations

    policy = api.load(args.policy)
    env_cfg = api.train_config({}, config=args.config).env if args.config else policy.config.env
    path = record_demonstrations(policy, env_cfg, args.steps, args.out, seed=args.seed,
                                 deterministic=not args.stochastic, progress=not args.no_progress)
    print(f"wrote {path}: {args.steps:,}+ transitions of {args.policy} on {env_cfg.id}; "
          f"use it with --<algo>.prior_data {path}")
    return 0


def cmd_configs() -> int:
    from drivelab.config import read_yaml, shipped_configs

    for name, path in shipped_configs().items():
        data = read_yaml(path)
        env = data.get("env", {}).get("id", "") if isinstance(data.get("env"), dict) else ""
        kind = "  (a sweep: drivelab sweep NAME)" if "sweep" in data else ""
        print(f"{name:<28}{data.get('algo', '?'):<10}{env:<34}{data.get('steps', '')}{kind}")
    print("(drivelab train --config NAME; the files are in drivelab/configs/)")
    return 0


def cmd_models() -> int:
    from drivelab.tools.drivers import CARD_METRICS, DRIVERS_DIR, read_card, shipped_drivers

    for name in shipped_drivers():
        card = read_card(DRIVERS_DIR / name)
        mine = card.get("evaluation", {}).get("policies", {}).get(name, {})
        # success and route completion, and the episode cost of a driver evaluated with one
        numbers = ", ".join(f"{m} {mine[m]['mean']:.2f}" for m in (*CARD_METRICS[:1], *CARD_METRICS[-1:], "cost")
                            if m in mine)
        print(f"{name:<22}{card.get('training', {}).get('algo', '?'):<6}{card.get('summary', '')} ({numbers})")
    print("(drivelab eval NAME --card shows a model card; drivelab.load(NAME) loads one)")
    return 0


def cmd_envs() -> int:
    from drivelab.envs.registration import MULTIAGENT_SCENES, TASKS, metadrive_ids

    print("\n".join([*metadrive_ids(), *TASKS]))
    print("multi-agent scenes (algo ippo or mappo):\n" + "\n".join(MULTIAGENT_SCENES))
    print("(and any Gymnasium id: CartPole-v1, LunarLander-v3, CarRacing-v3, ...)")
    return 0


class OneLineErrors(argparse.ArgumentParser):
    """argparse, but a usage error is one line (``drivelab: error: ...``, exit 2) like every other
    bad input; ``--help`` still shows the usage."""

    def error(self, message: str) -> None:
        print(f"drivelab: error: {self.prog.removeprefix('drivelab ')}: {message}".replace(": drivelab:", ":"),
              file=sys.stderr)
        sys.exit(2)


def algo_help(name: str) -> str:
    """The hyperparameters of one algorithm: field, type, default, meaning."""
    from drivelab.config import field_docs

    spec = ALGORITHMS[name]
    lines = [f"{name}: {spec.summary}", f"hyperparameters (--{name}.FIELD VALUE, or the '{name}:' section of a config):"]
    lines += [_field_line(*row) for row in field_docs(spec.params)]
    return "\n".join(lines)


def config_help() -> str:
    """Every field of a run's config but the hyperparameters, one line each: name, type, default,
    meaning. Made from the dataclasses (drivelab/config.py, drivelab/envs/config.py) and the
    comments beside their fields, so the help lists exactly the fields the config has."""
    from drivelab.config import TrainConfig, field_docs

    top, sections = [], []
    for name, kind, default, meaning in field_docs(TrainConfig):
        if dataclasses.is_dataclass(default):  # a section (env, eval, track): its fields, dotted
            sections += [_field_line(f"{name}.{field}", *rest) for field, *rest in field_docs(type(default))]
        elif name != "algo_params":  # the hyperparameters: --algo ALGO --help
            top.append(_field_line(name, kind, default, meaning))
    title = "config fields (--FIELD VALUE or --SECTION.FIELD VALUE; - or _ alike; or the same in a --config file):"
    return "\n".join([title, *top, *sections])


def train_help(algo: str | None) -> str:
    """The epilog of ``drivelab train --help``: the config fields, then ALGO's hyperparameters
    (with ``--algo ALGO``) or how to list them."""
    algo_part = algo_help(algo) if algo in ALGORITHMS else "drivelab train --algo ALGO --help lists ALGO's hyperparameters"
    return config_help() + "\n\n" + algo_part


def _field_line(field: str, kind: str, default: Any, meaning: str) -> str:
    """One field in a help text: name, type, default and the first sentence of its meaning,
    shortened when long (its parentheses left out, then what follows a semicolon, then cut)."""
    meaning = re.split(r"(?<!e\.g)(?<!i\.e)\. ", meaning)[0].rstrip(".")  # "e.g. " ends no sentence
    if len(meaning) > 70:
        meaning = re.sub(r" \([^()]*\)", "", meaning)
    if len(meaning) > 80:
        meaning = meaning.split("; ")[0]
    if len(meaning) > 80:
        meaning = meaning[:meaning.rfind(" ", 0, 76)] + " ..."
    return f"  {field:<22} {kind:<14} {default!s:<12} {meaning}"


def _train_epilog(argv: list[str]) -> str | None:
    """For ``drivelab train [--algo ALGO] --help``: the config fields (and ALGO's
    hyperparameters); None otherwise, so that no other command pays for reading them."""
    if argv[:1] != ["train"] or not ("-h" in argv or "--help" in argv):
        return None
    algo = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--algo"), None) or \
        next((a.split("=", 1)[1] for a in argv if a.startswith("--algo=")), None)
    return train_help(algo)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    # --debug may stand anywhere (after `train`, its other flags are config fields)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    parser = build_parser(train_epilog=_train_epilog(argv))
    # Every command stops on SIGTERM as on Ctrl-C (a run with a checkpoint, see api.stop_signals),
    # and hears Ctrl-C even when started from a shell that ignores SIGINT for background jobs.
    signal.signal(signal.SIGTERM, raise_interrupt)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    args, unknown = parser.parse_known_args(argv)
    args.debug = debug
    run_dir = getattr(args, "resume", None) or getattr(args, "run_dir", None)
    try:
        if args.command == "train":
            code = cmd_train(args, parse_overrides(unknown))
        else:
            if unknown:
                parser.error(f"unrecognized arguments: {' '.join(unknown)}")
            code = {"eval": cmd_eval, "reward": cmd_reward, "export": cmd_export, "demos": cmd_demos, "plot": cmd_plot, "report": cmd_report, "sweep": cmd_sweep, "configs": lambda a: cmd_configs(), "models": lambda a: cmd_models()}.get(
                args.command, lambda a: cmd_envs())(args)
    except TrainingCrashed as exc:  # the traceback is in RUN/error.log
        _print_error(exc, exc.__cause__, args.debug)
        sys.exit(1)
    except DrivelabError as exc:
        print(f"drivelab: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        sys.exit(0)
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (raised as Terminated, a KeyboardInterrupt)
        hint = f"; continue with: {shlex.join(['drivelab', 'train', '--resume', str(run_dir)])}" if run_dir else ""
        print(f"\ndrivelab: {'terminated' if isinstance(exc, Terminated) else 'interrupted'}{hint}", file=sys.stderr)
        # as a shell reports a process killed by the signal: 128 + its number
        sys.exit(128 + (signal.SIGTERM if isinstance(exc, Terminated) else signal.SIGINT))
    except Exception as exc:  # noqa: BLE001 - outside training (loading, evaluating): still one line
        _print_error(f"{error_line(exc)} (drivelab --debug ... shows the traceback)", exc, args.debug)
        sys.exit(1)
    sys.exit(code)


def run(*args: str | os.PathLike) -> None:
    """Run a drivelab command in this process: ``run("eval", RUN, "--episodes", "1")`` does what
    ``drivelab eval RUN --episodes 1`` does in a terminal, for notebooks and scripts that have
    Python, torch and the simulator loaded already. A command that fails (its message is on
    stderr) raises RuntimeError instead of exiting."""
    argv = [str(a) for a in args]
    try:
        main(argv)
    except SystemExit as stop:
        if stop.code:
            raise RuntimeError(f"{shlex.join(['drivelab', *argv])} failed (exit status {stop.code})") from None


def _print_error(message: object, exc: BaseException | None, debug: bool) -> None:
    """One line on stderr; with ``--debug`` (or DRIVELAB_DEBUG=1), the traceback above it."""
    if exc is not None and (debug or os.environ.get("DRIVELAB_DEBUG") == "1"):
        traceback.print_exception(exc, file=sys.stderr)
    print(f"drivelab: error: {message}", file=sys.stderr)
