"""Does more training cut the cost on unseen roads? Each kept checkpoint of a safe_drive.py run on
the held-out scenarios. A diagnosis, not a test.

    python benchmarks/safe_drive_steps.py --runs runs/safe --arms early_termination --seeds 0 \\
        --out benchmarks/results/archive/safe_drive_steps.json

``benchmarks/safe_drive.py`` reports one checkpoint per run, ``checkpoints/best``, chosen during
training on scenarios 200-229. This script plays every periodic checkpoint the run kept
(``step_*``, ``checkpoint_every`` apart) on the same 200 unseen scenarios with deterministic
actions, and writes per checkpoint: success, episode cost, crash and off-road rates, the share of
episodes the stuck guard ended (``stuck_rate``: the car stood still or stayed pinned in a collision,
drivelab/envs/metadrive.py) and how much of the cost those episodes made. The held-out numbers only
describe the run; they never choose a checkpoint. Each evaluation is cached in
``RUNS/ARM/seed_N/heldout_steps.json``, so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from checkpoint_selection import cached  # one JSON file of evaluations by key
from provenance import provenance  # benchmarks/provenance.py
from safe_drive import ARMS, EPISODES, HELDOUT_ENV, outcomes

from drivelab.api import evaluate_checkpoint
from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints


def heldout(checkpoint: Path, episodes: int) -> dict:
    """One checkpoint on the held-out scenarios 0..episodes-1: the means of safe_drive.py's metrics,
    the stuck guard's share of episodes and the cost of those episodes (summed over episodes)."""
    result, _, _ = evaluate_checkpoint(checkpoint, episodes, HELDOUT_ENV, num_envs=2)
    row = outcomes(result)
    costs = row.pop("per_episode")["cost"]
    stuck = [float(x) for x in result.metrics.get("stuck_rate", [0.0] * len(costs))]
    return {**row, "stuck_rate": sum(stuck) / len(stuck), "total_cost": round(sum(costs), 2),
            "stuck_cost": round(sum(c for c, s in zip(costs, stuck) if s), 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, required=True, help="safe_drive.py's --runs folder (RUNS/ARM/seed_N)")
    parser.add_argument("--arms", nargs="+", default=["early_termination"], choices=list(ARMS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--episodes", type=int, default=EPISODES, help="held-out scenarios (0..N-1)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    started = time.time()
    table: dict[str, dict] = {}
    for arm in args.arms:
        for seed in args.seeds:
            run = args.runs / arm / f"seed_{seed}"
            checkpoints = list_checkpoints(run)
            if not checkpoints:
                raise SystemExit(f"{run / 'checkpoints'}: no step_* checkpoint; run benchmarks/safe_drive.py first")
            rows = {}
            for checkpoint in checkpoints:
                row = cached(run / "heldout_steps.json", f"{checkpoint.name}_{args.episodes}",
                             lambda c=checkpoint: heldout(c, args.episodes))
                rows[str(checkpoint_step(checkpoint))] = row
                print(f"{arm} seed {seed} {checkpoint.name}: success {row['success_rate']:.3f} cost {row['cost']:.2f} "
                      f"stuck {row['stuck_rate']:.3f} ({row['stuck_cost']:.0f} of {row['total_cost']:.0f})", flush=True)
            table.setdefault(arm, {})[str(seed)] = rows
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "benchmark": "safe-drive-steps", **provenance(started), "runs": str(args.runs),
        "heldout": f"{HELDOUT_ENV}, scenarios 0-{args.episodes - 1}, deterministic actions",
        "arms": table}, indent=1) + "\n")


if __name__ == "__main__":
    main()
