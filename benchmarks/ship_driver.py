"""Turn a run of the drive benchmark into a shipped driver with its model card (drivelab/tools/drivers.py).

    python benchmarks/drive_recipe.py --seeds 0 --runs runs/drive      # trains, evaluates on 0-199
    python benchmarks/ship_driver.py runs/drive/seed_0 --benchmark benchmarks/results/drive_recipe.json

A safe driver, evaluated on SafeMetaDrive's validation scenarios (its card adds the episode cost
when heldout.json has it per episode):

    python benchmarks/ship_driver.py RUN --name drivelab-safe-driver --config safe_drive \
        --env SafeMetaDrive-validation-v0 --summary "..." --benchmark benchmarks/results/safe_drive.json

``--protocol`` replaces the card's description of the evaluation (default: PROTOCOL, or
SAFE_PROTOCOL for a SafeMetaDrive env, with the run's training env filled in).

Takes ``RUN/checkpoints/best`` (chosen during training on scenarios disjoint from the reported
ones) and keeps the policy alone (``TrainedPolicy.save``: the same tensors). Its evaluation on
MetaDrive's protocol (the 200 unseen validation scenarios, start seeds 0-199, default traffic,
per episode) comes from ``RUN/heldout.json``, and MetaDrive's expert's on the same scenarios from
the benchmark's JSON, both written by benchmarks/drive_recipe.py; tests/test_drivers.py replays
the first scenarios with the shipped files. Writes ``drivelab/drivers/NAME/``: the weights,
``state.json``, ``card.json`` and ``SHA256SUMS`` (the sha256 of those three, which loading checks,
so the card cannot be edited unnoticed). Not a test.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from importlib.metadata import version
from pathlib import Path

from drivelab import api
from drivelab.tools.drivers import DRIVERS_DIR, card_metrics, write_driver
from drivelab.training.outputs.checkpoint import checkpoint_step

PROTOCOL = ("MetaDrive's generalization protocol: trained on MetaDrive-1000envs (start seed 1000, 1000 "
            "scenarios); evaluated deterministically on the 200 unseen scenarios of start seeds 0-199 "
            "(MetaDrive-validation-v0, default traffic), episode k on scenario k")
SAFE_PROTOCOL = ("MetaDrive's generalization protocol with a cost: trained on {train_env}; evaluated "
                 "deterministically on the 200 unseen scenarios of start seeds 0-199 (SafeMetaDrive-validation-v0: "
                 "default traffic, accidents on the road, a crash does not end the episode), episode k on "
                 "scenario k; cost: 1 for each step out of the road or in contact with a vehicle or an object")
# What the card keeps of each held-out episode (replayed by tests/test_drivers.py), when heldout.json has it.
PER_EPISODE = ("success_rate", "route_completion", "cost", "length")


def observation_description(env_kwargs: dict) -> str:
    """What the driver sees: MetaDrive's lidar state, with the nearest vehicles when the config adds them."""
    others = env_kwargs.get("vehicle_config", {}).get("lidar", {}).get("num_others", 0)
    nearest = f", and the relative position and velocity of the {others} nearest vehicles" if others else ""
    return f"MetaDrive's lidar state: ego state, navigation and 240 lidar beams{nearest}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--name", default="drivelab-driver")
    parser.add_argument("--config", default="drive", help="the shipped config the run used (for the card)")
    parser.add_argument("--summary", default="TD3 that drives MetaDrive roads it has never seen")
    parser.add_argument("--benchmark", type=Path, default=Path("benchmarks/results/drive_recipe.json"))
    parser.add_argument("--env", default="MetaDrive-validation-v0",
                        help="the env heldout.json was evaluated on (the card's reproduce command)")
    parser.add_argument("--protocol", help="the card's description of the evaluation (default: PROTOCOL, or "
                        "SAFE_PROTOCOL for a SafeMetaDrive env)")
    args = parser.parse_args()
    best = args.run / "checkpoints" / "best"
    heldout = json.loads((args.run / "heldout.json").read_text())
    expert = json.loads(args.benchmark.read_text())["baselines"]["metadrive-expert"]
    for what, outcomes in ((args.run / "heldout.json", heldout), (f"{args.benchmark}'s expert", expert)):
        if "per_episode" not in outcomes:   # the card's CIs and its replayed episodes need them
            raise SystemExit(f"{what} has no per-episode outcomes (written before they were kept): evaluate again")
    if heldout["step"] != checkpoint_step(best):
        raise SystemExit(f"{args.run / 'heldout.json'} is of step {heldout['step']}, checkpoints/best of {checkpoint_step(best)}")
    policy = api.load(best)
    cfg = policy.config
    protocol = args.protocol or (SAFE_PROTOCOL.format(train_env=cfg.env.id) if args.env.startswith("SafeMetaDrive")
                                 else PROTOCOL)
    with tempfile.TemporaryDirectory() as tmp:
        saved = policy.save(Path(tmp) / "policy")
        step = checkpoint_step(best)
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
        training = json.loads((args.run / "training.json").read_text())
        card = {
            "name": args.name,
            "summary": args.summary,
            "training": {
                "algo": cfg.algo, "config": f"configs/{args.config}.yaml", "seed": cfg.seed, "steps": step,
                "minutes": training["minutes"], "steps_trained": training["steps"], "machine": "2 CPU cores, no GPU",
                "drivelab_commit": commit, "metadrive_version": version("metadrive-simulator"),
                "selection": f"checkpoints/best: highest {cfg.eval.best_metric} on {cfg.eval.env_id} scenarios "
                             f"{cfg.eval.seed}-{cfg.eval.seed + cfg.eval.episodes - 1}, every {cfg.eval.every:,} steps"
                             + ("" if cfg.eval.cost_limit is None else
                                f", evaluations with a mean episode cost <= {cfg.eval.cost_limit:g} first"),
                # the config's own budget: in decisions (the same on every CPU) without a time budget,
                # else its minutes (training.json's minutes include the evaluation after it)
                "reproduce": f"drivelab train --config {args.config} --seed {cfg.seed} "
                             + (f"--max_minutes {cfg.max_minutes:g}" if cfg.max_minutes else f"--steps {cfg.steps}")
                             + f" --run-dir runs/{args.name} && "
                             f"drivelab eval runs/{args.name}/checkpoints/best --env {args.env} "
                             f"--episodes {len(heldout['per_episode']['success_rate'])} --num-envs 2 --json",
            },
            "observation": observation_description(cfg.env.kwargs),
            "observation_shape": list(policy.observation_space.shape),
            "evaluation": {
                "protocol": protocol, "episodes": len(heldout["per_episode"]["success_rate"]),
                "policies": {args.name: card_metrics(heldout["per_episode"]),
                             "metadrive-expert": card_metrics(expert["per_episode"])},
                "per_episode": {name: heldout["per_episode"][name] for name in PER_EPISODE
                                if name in heldout["per_episode"]},
            },
        }
        out = write_driver(DRIVERS_DIR / args.name, saved, card)
    print(api.model_card(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
