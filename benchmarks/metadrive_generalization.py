"""Does the agent drive on MetaDrive scenarios it has never seen? Train on a training split, then
evaluate the run's checkpoints on held-out validation scenarios and on training scenarios, beside
MetaDrive's own PPO expert and a random policy measured with the same protocol. Not a test.

    python benchmarks/metadrive_generalization.py --config configs/ppo_metadrive_drive.yaml --run-dir runs/drive
    python benchmarks/metadrive_generalization.py --run-dir runs/drive --skip-train   # re-evaluate a finished run

Training resumes from the run's last checkpoint if it was interrupted; evaluating again into the same
JSON (same protocol) reuses the checkpoints and baselines evaluated before, so a long run can be
evaluated while it trains. The first checkpoint kept
in ``RUN/checkpoints`` at or after each multiple of ``--every`` (and the last one) is evaluated
deterministically on ``--heldout`` validation scenarios (MetaDrive-validation-v0, scenarios
0..N-1) and ``--train-episodes`` training scenarios (the run's own env, seeds 0..M-1). Writes
``RUN/generalization.json`` and ``RUN/generalization.png`` (success rate and route completion
against env steps, train vs held-out, baselines as reference lines), unless ``--out`` says where.

The run's own choice, ``RUN/checkpoints/best`` (the checkpoint that scored best in the run's
periodic evaluation, ``eval.best_metric``), is evaluated on the held-out scenarios too, as
``selected``: the number to report for a recipe that keeps its best checkpoint. It is honest only
if the run chose on scenarios disjoint from the held-out ones (``eval.env_id`` another split, or
``eval.seed`` >= ``--heldout`` on the validation split); ``selected.disjoint`` says which. ``peak``
is the curve's row with the highest held-out success: chosen on the test scenarios themselves, an
optimistic number, not one to report as the recipe's.

``--stochastic`` plays every policy with sampled actions instead, the checkpoints and MetaDrive's
expert alike (``"actions": "sampled"`` in the JSON). The default protocol takes the mode (as the
expert's reference numbers do); sampling is worth knowing about, because a PPO or SAC policy
trained with noise may drive better with it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from drivelab.api import build_config, checkpoint_config, evaluate_baseline, play, policy_from_checkpoint, train
from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints, load_checkpoint
from drivelab.config import EnvConfig, read_yaml
from provenance import provenance  # benchmarks/provenance.py

HELDOUT_ENV = "MetaDrive-validation-v0"


def train_run(config: str | None, run_dir: Path, steps: int | None) -> float:
    """Train (or resume) the run; returns the training wall time of this call in seconds."""
    checkpoints = list_checkpoints(run_dir)
    data = read_yaml(config) if config else read_yaml(run_dir / "config.yaml")
    data = {**data, "run_dir": str(run_dir), **({"steps": steps} if steps else {})}
    cfg = build_config(data)
    if checkpoints and checkpoint_step(checkpoints[-1]) >= cfg.steps:
        return 0.0
    started = time.perf_counter()
    train(cfg, resume=bool(checkpoints))
    return time.perf_counter() - started


def heldout_env_config(env: EnvConfig, num_envs: int) -> EnvConfig:
    """The validation split with the run's wrappers (action grid, filters, reward) but not its
    kwargs, which may redefine the scenario range."""
    return dataclasses.replace(env, id=HELDOUT_ENV, kwargs={}, num_envs=num_envs)


def evaluate_run(run_dir: Path, every: int, heldout: int, train_episodes: int, num_envs: int,
                 from_step: int = 0, known: dict[int, dict] | None = None, deterministic: bool = True) -> list[dict]:
    """Evaluate the chosen checkpoints; rows in ``known`` (by step, same protocol) are reused."""
    paths = [p for p in list_checkpoints(run_dir) if checkpoint_step(p) >= from_step]
    steps = [checkpoint_step(p) for p in paths]
    # the first checkpoint at or after each multiple of `every` (iterations rarely end on one), and the last
    chosen = sorted({next(p for p, s in zip(paths, steps) if s >= m) for m in range(from_step, steps[-1] + 1, every)}
                    | {paths[-1]})
    curve = []
    for path in chosen:
        if known and checkpoint_step(path) in known:
            curve.append(known[checkpoint_step(path)])
            continue
        ckpt = load_checkpoint(path)
        cfg = checkpoint_config(ckpt)
        row = {"step": ckpt.step}
        for name, env_cfg, episodes in (
                ("heldout", heldout_env_config(cfg.env, num_envs), heldout),
                ("train", dataclasses.replace(cfg.env, num_envs=num_envs), train_episodes)):
            if episodes:
                policy = policy_from_checkpoint(ckpt, cfg, env_cfg)
                row[name] = play(env_cfg, policy, episodes, deterministic=deterministic).summary()
        print(json.dumps(row), flush=True)
        curve.append(row)
    return curve


def evaluate_selected(run_dir: Path, heldout: int, num_envs: int, curve: list[dict], known: dict | None = None,
                      deterministic: bool = True) -> dict | None:
    """The run's ``checkpoints/best`` on the held-out scenarios, and whether the run chose it on
    scenarios disjoint from them; None if the run kept no best. A row of ``curve`` or ``known`` at
    the same step (the same weights) is reused."""
    best_dir = run_dir / "checkpoints" / "best"
    if not best_dir.is_dir():
        return None
    ckpt = load_checkpoint(best_dir)
    if known and known.get("step") == ckpt.step:
        return known
    cfg = checkpoint_config(ckpt)
    spec = cfg.eval
    chosen_on = spec.env_id or cfg.env.id
    # Validation scenario k is reset with seed k: the run chose on seeds [seed, seed + episodes).
    disjoint = chosen_on != HELDOUT_ENV or spec.seed >= heldout
    summary = next((row["heldout"] for row in curve if row["step"] == ckpt.step and "heldout" in row), None)
    if summary is None:
        env_cfg = heldout_env_config(cfg.env, num_envs)
        summary = play(env_cfg, policy_from_checkpoint(ckpt, cfg, env_cfg), heldout, deterministic=deterministic).summary()
    row = {"step": ckpt.step, "chosen_on": {"env_id": chosen_on, "seed": spec.seed, "episodes": spec.episodes,
                                            "metric": spec.best_metric},
           "disjoint": disjoint, "heldout": summary}
    print(json.dumps({"selected": row}), flush=True)
    return row


def plot(curve: list[dict], baselines: dict[str, dict], selected: dict | None, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    steps = [row["step"] for row in curve]
    for ax, metric, label in ((axes[0], "success_rate", "success rate"), (axes[1], "route_completion", "route completion")):
        for split, style in (("heldout", "o-"), ("train", "s--")):
            values = [row[split][metric] for row in curve if split in row]
            if values:
                ax.plot([row["step"] for row in curve if split in row], values, style,
                        label=f"{'held-out' if split == 'heldout' else 'training'} scenarios")
        if selected:
            ax.plot([selected["step"]], [selected["heldout"][metric]], "*", markersize=14, color="tab:red",
                    label=f"the run's best checkpoint, {selected['step']:,} steps (held-out"
                          + ("" if selected["disjoint"] else "; chosen on some of these scenarios") + ")")
        for (name, summary), color in zip(baselines.items(), ("tab:green", "tab:gray", "tab:purple")):
            ax.axhline(summary[metric], color=color, linestyle=":", label=f"{name} (held-out)")
        ax.set_xlabel("env steps")
        ax.set_ylabel(label)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlim(0, max(steps) * 1.02 if steps else 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help="training config (default: the run's config.yaml)")
    parser.add_argument("--run-dir", required=True)
    parser.add_argument("--steps", type=int, help="override the config's steps")
    parser.add_argument("--skip-train", action="store_true", help="only evaluate the run's checkpoints")
    parser.add_argument("--every", type=int, default=200_000, help="evaluate checkpoints at multiples of this step")
    parser.add_argument("--heldout", type=int, default=100, help="validation scenarios per evaluation")
    parser.add_argument("--train-episodes", type=int, default=50, help="training scenarios per evaluation")
    parser.add_argument("--baselines", nargs="*", default=["metadrive-expert", "random"])
    parser.add_argument("--num-envs", type=int, default=2, help="evaluation env processes")
    parser.add_argument("--from-step", type=int, default=0, help="skip checkpoints before this step (1: the initial one)")
    parser.add_argument("--stochastic", action="store_true", help="sample every policy's actions (see above)")
    parser.add_argument("--out", help="JSON path (the PNG goes beside it); default RUN/generalization.json")
    args = parser.parse_args()
    started = time.time()
    run_dir = Path(args.run_dir)
    out = Path(args.out) if args.out else run_dir / "generalization.json"
    out.parent.mkdir(parents=True, exist_ok=True)  # before hours of training and evaluation, not after
    try:
        wall = 0.0 if args.skip_train else train_run(args.config, run_dir, args.steps)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the run saved a checkpoint of this moment
        raise SystemExit(f"interrupted; the same command resumes the run in {run_dir}") from None
    eval_started = time.perf_counter()
    # A second call on the same output adds the new checkpoints (and baselines) only.
    previous = json.loads(out.read_text()) if out.exists() else {}
    actions = "sampled" if args.stochastic else "mode"
    if (previous.get("heldout_episodes"), previous.get("train_episodes"), previous.get("actions", "mode")) != (
            args.heldout, args.train_episodes, actions):
        previous = {}
    known = {row["step"]: row for row in previous.get("curve", [])}
    curve = evaluate_run(run_dir, args.every, args.heldout, args.train_episodes, args.num_envs, args.from_step, known,
                         deterministic=not args.stochastic)
    heldout_env = EnvConfig(id=HELDOUT_ENV, num_envs=args.num_envs)
    baselines = {name: previous.get("baselines", {}).get(name)
                 or evaluate_baseline(name, heldout_env, args.heldout, deterministic=not args.stochastic).summary()
                 for name in args.baselines}
    selected = evaluate_selected(run_dir, args.heldout, args.num_envs, curve, previous.get("selected"),
                                 deterministic=not args.stochastic)
    metrics = [row for row in curve if "heldout" in row]
    peak = max(metrics, key=lambda row: (row["heldout"]["success_rate"], row["heldout"]["route_completion"]), default=None)
    cfg = read_yaml(run_dir / "config.yaml")
    eval_wall = time.perf_counter() - eval_started  # before provenance(), whose git calls it must not count
    result = {"benchmark": "metadrive-generalization", **provenance(started), "run_dir": str(run_dir),
              "algo": cfg["algo"], "train_env": cfg["env"]["id"], "heldout_env": HELDOUT_ENV,
              "heldout_episodes": args.heldout, "train_episodes": args.train_episodes, "actions": actions,
              "train_wall_s_this_call": wall, "eval_wall_s": eval_wall, "curve": curve, "selected": selected,
              "peak": peak, "baselines": baselines}
    out.write_text(json.dumps(result, indent=1) + "\n")
    plot(curve, baselines, selected, out.with_suffix(".png"),
         f"{cfg['algo']} trained on {cfg['env']['id']}: {args.heldout} held-out validation scenarios"
         + (", sampled actions" if args.stochastic else ""))
    print(json.dumps({"selected": selected, "peak": peak, "baselines": baselines}, indent=1))
    print(f"wrote {out} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
