"""drivelab's drive recipe and Stable-Baselines3's SAC or TD3, side by side on MetaDrive's protocol.
Not a test.

    pip install stable-baselines3==2.9.2        # for this benchmark only: not a drivelab dependency
                                                # (2.7 pins gymnasium < 1.3 and would downgrade drivelab's)
    python benchmarks/sb3_side_by_side.py --config configs/drive.yaml --seeds 0 1 2 --steps 150000 \\
        --runs runs/sb3 --out benchmarks/results/sb3_side_by_side.json
    python benchmarks/sb3_side_by_side.py ... --minutes 30          # the same minutes instead

Both arms train on the config's env, built by drivelab (the same MetaDrive scenarios, observation,
reward terms and action repeat), in ``env.num_envs`` subprocess envs, for the same decisions
(``--steps``) or the same wall-clock minutes (``--minutes``, evaluations included in both). SB3
gets the closest settings it offers (:func:`sb3_settings`; what it cannot match is listed in the
JSON under ``unmatched``). Both choose their checkpoint the same way, on the config's selection
scenarios (200-229) every ``eval.every`` decisions and at the end, and both choices are played
by drivelab's evaluator on the 200 unseen scenarios 0-199 (deterministic actions). Per arm and
seed: held-out success, decisions, minutes, decisions/s and the CPU gauge; then the ratios
drivelab / SB3. Every result is cached in the run directories: running it again only does what
is missing.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import inspect
import json
import sys
import time
from pathlib import Path

import numpy as np

from drivelab.api import build_config
from drivelab.config import merge_overrides, read_yaml
from drivelab.envs import make_env
from drivelab.training.collection.evaluation import play
from drivelab.training.run.periodic_evaluation import eval_env_config
from drivelab.training.outputs.statistics import mean_and_ci95
from drive_recipe import EPISODES, HELDOUT_ENV, cpu_gauge_ms, heldout, train_seed  # benchmarks/drive_recipe.py
from provenance import package_version, provenance  # benchmarks/provenance.py

ARMS = ("drivelab", "sb3")


def sb3_settings(algo: str, hp: dict, num_envs: int, sb3_init) -> tuple[dict, list[str]]:
    """SB3's keyword arguments closest to drivelab's hyperparameters ``hp`` (the config's section),
    and what SB3 has no setting for."""
    kwargs = {"buffer_size": hp["buffer_size"], "learning_starts": hp["learning_starts"], "batch_size": hp["batch_size"],
              "tau": hp.get("tau", 0.005), "gamma": hp["gamma"], "train_freq": 1,
              # drivelab: utd gradient steps per env step; SB3: gradient_steps per step of all envs
              "gradient_steps": max(1, round(hp.get("utd", 1.0) * num_envs)),
              "learning_rate": hp.get("critic_lr", 3e-4),
              "policy_kwargs": {"net_arch": list(hp["hidden"])}}
    unmatched = []
    if hp.get("actor_lr", 3e-4) != hp.get("critic_lr", 3e-4):
        unmatched.append("actor_lr != critic_lr (SB3 has one learning_rate: the critic's is used)")
    if hp.get("n_step", 1) > 1:
        if "n_steps" in inspect.signature(sb3_init).parameters:
            kwargs["n_steps"] = hp["n_step"]
        else:
            unmatched.append(f"n_step {hp['n_step']} (this SB3 has no n-step returns)")
    for field, what in (("critic_layer_norm", "LayerNorm in the critics"), ("act_in_workers", "env workers acting "
                        "while the learner updates"), ("compile", "torch.compile")):
        if hp.get(field):
            unmatched.append(what)
    if algo == "sac":
        kwargs["ent_coef"] = f"auto_{hp.get('init_alpha', 1.0)}"
        if hp.get("target_entropy") is not None:
            kwargs["target_entropy"] = hp["target_entropy"]
        if hp.get("actor_every", 1) > 1:
            unmatched.append(f"actor_every {hp['actor_every']} (SB3's SAC updates the actor with every critic step)")
    else:
        kwargs.update(policy_delay=hp.get("policy_delay", 2), target_policy_noise=hp.get("target_noise", 0.2),
                      target_noise_clip=hp.get("target_noise_clip", 0.5))
        if hp.get("noise_std_final", hp.get("noise_std", 0.1)) != hp.get("noise_std", 0.1):
            unmatched.append("a decaying exploration noise (SB3's is constant: noise_std)")
    return kwargs, unmatched


class SB3Policy:
    """An SB3 model as drivelab's evaluator plays a policy: ``act`` gives the env's action
    (SB3's ``predict`` rescales from its [-1, 1] to the env's bounds), ``to_env`` passes it on."""

    shared_generator = True   # play in this process, where the SB3 model lives (it is not sent to workers)

    def __init__(self, model):
        self.model = model

    def act(self, obs, deterministic: bool = True) -> np.ndarray:
        return self.model.predict(obs.cpu().numpy(), deterministic=deterministic)[0]

    def to_env(self, action: np.ndarray) -> np.ndarray:
        return np.asarray(action)


def train_sb3(algo: str, cfg, run_dir: Path, steps: int | None, minutes: float | None) -> dict:
    """Train SB3's ``algo`` on ``cfg``'s env with drivelab's checkpoint choice; cached in RUN/training.json."""
    record = run_dir / "training.json"
    if record.is_file():
        return json.loads(record.read_text())
    from stable_baselines3 import SAC, TD3
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.noise import NormalActionNoise
    from stable_baselines3.common.vec_env import SubprocVecEnv

    cls = {"sac": SAC, "td3": TD3}[algo]
    hp = dataclasses.asdict(cfg.algo_params)
    kwargs, unmatched = sb3_settings(algo, hp, cfg.env.num_envs, cls.__init__)
    run_dir.mkdir(parents=True, exist_ok=True)
    wall_started = time.time()
    gauge_before = cpu_gauge_ms()
    envs = SubprocVecEnv([functools.partial(make_env, cfg.env)] * cfg.env.num_envs, start_method="forkserver")
    if algo == "td3":
        act_dim = envs.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(np.zeros(act_dim), hp.get("noise_std", 0.1) * np.ones(act_dim))
    model = cls("MlpPolicy", envs, seed=cfg.seed, verbose=0, device="cpu", **kwargs)
    # the selection scenarios as drivelab's periodic evaluation plays them
    selection_env = dataclasses.replace(eval_env_config(cfg), num_envs=cfg.eval.num_envs)
    curve = {"steps": [], "minutes": [], "success": []}
    best = {"success": -1.0}
    started = time.perf_counter()
    eval_seconds = [0.0]

    def select() -> None:
        """drivelab's choice: success on the selection scenarios; the best so far is kept (ties: the later)."""
        t = time.perf_counter()
        result = play(selection_env, SB3Policy(model), cfg.eval.episodes, cfg.eval.seed)
        eval_seconds[0] += time.perf_counter() - t
        success = float(result.summary()["success_rate"])
        curve["steps"].append(int(model.num_timesteps))
        curve["minutes"].append(round((time.perf_counter() - started) / 60, 2))
        curve["success"].append(success)
        if success >= best["success"]:
            best.update(success=success, step=int(model.num_timesteps))
            model.save(run_dir / "best.zip")

    class Selection(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next_eval = cfg.eval.every

        def _on_step(self) -> bool:
            if cfg.eval.every and self.num_timesteps >= self.next_eval:
                select()
                self.next_eval += cfg.eval.every
            return minutes is None or (time.perf_counter() - started) / 60 < minutes

    model.learn(total_timesteps=steps if steps is not None else 10**9, callback=Selection())
    select()   # the policy the run ends with, as eval.final
    trained_minutes = round((time.perf_counter() - started) / 60, 2)
    envs.close()
    result = {"minutes": trained_minutes, "steps": int(model.num_timesteps), "best_step": best["step"],
              "evaluation_minutes": round(eval_seconds[0] / 60, 2), "selection": curve,
              "sb3": package_version("stable-baselines3"), "settings": {k: repr(v) for k, v in kwargs.items()},
              "unmatched": unmatched, "cpu_gauge_ms": [gauge_before, cpu_gauge_ms()], **provenance(wall_started)}
    record.write_text(json.dumps(result) + "\n")
    return result


def heldout_sb3(algo: str, cfg, run_dir: Path) -> dict:
    """The SB3 run's chosen model on the 200 held-out scenarios (cached in RUN/heldout.json)."""
    cache = run_dir / "heldout.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    from stable_baselines3 import SAC, TD3

    model = {"sac": SAC, "td3": TD3}[algo].load(run_dir / "best.zip", device="cpu")
    env_cfg = dataclasses.replace(cfg.env.on(HELDOUT_ENV), num_envs=2)   # as drivelab eval --env plays it
    summary = play(env_cfg, SB3Policy(model), EPISODES, seed=0).summary()
    row = {m: summary[m] for m in ("success_rate", "crash_rate", "out_of_road_rate", "route_completion")}
    cache.write_text(json.dumps(row) + "\n")
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/drive.yaml", help="drivelab's recipe (algo sac or td3)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    budget = parser.add_mutually_exclusive_group(required=True)
    budget.add_argument("--steps", type=int, help="the same decisions (env steps) for both")
    budget.add_argument("--minutes", type=float, help="the same wall-clock minutes for both")
    parser.add_argument("--runs", type=Path, default=Path("runs/sb3"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sb3_side_by_side.json"))
    args = parser.parse_args()
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        raise SystemExit("this benchmark needs Stable-Baselines3: pip install stable-baselines3==2.9.2 "
                         "(for the benchmark only; drivelab does not depend on it)") from None
    started = time.time()
    recipe = read_yaml(args.config)
    algo = recipe["algo"]
    if algo not in ("sac", "td3"):
        raise SystemExit(f"--config: SB3's side of this benchmark is SAC or TD3, the config trains {algo}")
    budget = ({"steps": args.steps, "max_minutes": None} if args.steps is not None
              else {"steps": 10**9, "max_minutes": args.minutes})
    label = f"{args.steps}_steps" if args.steps is not None else f"{args.minutes:g}_minutes"
    table: dict[str, dict[str, dict]] = {arm: {} for arm in ARMS}
    for seed in args.seeds:
        cfg = build_config(merge_overrides({**recipe, "seed": seed, "run_dir": str(args.runs / "unused")}, budget))
        ours = args.runs / label / f"drivelab_seed_{seed}"
        trained = train_seed(args.config, seed, ours, budget)
        table["drivelab"][str(seed)] = {**trained, **{k: v for k, v in heldout(ours).items() if k != "per_episode"}}
        theirs = args.runs / label / f"sb3_seed_{seed}"
        trained = train_sb3(algo, cfg, theirs, args.steps, args.minutes)
        table["sb3"][str(seed)] = {**trained, **heldout_sb3(algo, cfg, theirs)}
        for arm in ARMS:
            row = table[arm][str(seed)]
            row["decisions_per_s"] = round(row["steps"] / (row["minutes"] * 60), 1)
            print(json.dumps({"arm": arm, "seed": seed, **{k: row[k] for k in ("success_rate", "steps", "minutes",
                                                                             "decisions_per_s")}}), flush=True)
    summary = {}
    for arm in ARMS:
        summary[arm] = {}
        for metric in ("success_rate", "steps", "minutes", "decisions_per_s"):
            values = np.array([row[metric] for row in table[arm].values()], float)
            mean, half = mean_and_ci95(values)
            summary[arm][metric] = {"mean": float(mean), "ci95": float(half), "min": float(values.min())}
    ratios = {metric: summary["drivelab"][metric]["mean"] / max(summary["sb3"][metric]["mean"], 1e-9)
              for metric in ("success_rate", "decisions_per_s")}
    result = {"benchmark": "sb3-side-by-side", **provenance(started), "config": args.config, "recipe": recipe,
              "budget": budget, "sb3": package_version("stable-baselines3"), "seeds": table, "summary": summary,
              "ratio_drivelab_over_sb3": ratios,
              "protocol": "both arms: the config's env (drivelab), checkpoint chosen on scenarios 200-229, "
                          "reported on the 200 unseen scenarios 0-199 by drivelab's evaluator, deterministic actions"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for arm in ARMS:
        s = summary[arm]
        print(f"{arm:9s} held-out success {s['success_rate']['mean']:.3f} ± {s['success_rate']['ci95']:.3f}, "
              f"{s['steps']['mean']:,.0f} decisions in {s['minutes']['mean']:.1f} min "
              f"({s['decisions_per_s']['mean']:.0f}/s)")
    print(f"drivelab / SB3: decisions/s {ratios['decisions_per_s']:.2f}, held-out success {ratios['success_rate']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
