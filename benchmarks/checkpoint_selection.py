"""Would a larger selection set have chosen better checkpoints? A diagnosis of ``checkpoints/best``.

    python benchmarks/checkpoint_selection.py --runs RUNS --seeds 0 1 2 3 4 --episodes 60 \\
        --out benchmarks/results/drive_selection60.json

``benchmarks/drive_recipe.py`` reports each seed's ``checkpoints/best``, chosen during training on
a few validation scenarios (``eval.episodes`` of them from ``eval.seed``: 30 from 200 in
``drive.yaml``). With 30 episodes one success is 3.3 points, so two checkpoints often tie and the
choice is noisy. This script evaluates each seed's periodic checkpoints (``step_*`` from
``--from-step`` on) on ``--episodes`` selection scenarios from the same ``eval.seed`` (none of the
reported 0-199), picks one as training does (highest success, ties to the higher mean return),
and evaluates the pick on the held-out 200 unless it is the run's own choice (whose held-out result
``drive_recipe.py`` cached in ``RUN/seed_N/heldout.json``). The held-out numbers only score the
rule; they must never choose a checkpoint. Each evaluation is cached in ``RUN/seed_N/
selection_<episodes>.json`` and ``RUN/seed_N/heldout_steps.json``, so an interrupted run resumes.
Not a test.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from drive_recipe import EPISODES as HELDOUT_EPISODES, HELDOUT_ENV  # the protocol whose `best` this scores
from drivelab.api import evaluate_checkpoint
from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints
from provenance import provenance  # benchmarks/provenance.py


def cached(path: Path, key: str, compute) -> dict:
    """``compute()`` once per ``key``, kept in the JSON file ``path``."""
    table = json.loads(path.read_text()) if path.is_file() else {}
    if key not in table:
        table[key] = compute()
        path.write_text(json.dumps(table, indent=1) + "\n")
    return table[key]


def evaluation(checkpoint: Path, episodes: int, seed: int) -> dict:
    """Success, mean return and each episode's success of ``checkpoint`` on ``episodes`` scenarios."""
    result, _, _ = evaluate_checkpoint(checkpoint, episodes, HELDOUT_ENV, num_envs=2, seed=seed)
    summary = result.summary()
    return {"success_rate": summary["success_rate"], "return_mean": summary["return_mean"],
            "per_episode_success": [float(x) for x in result.metrics["success_rate"]]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, required=True, help="drive_recipe.py's --runs folder (RUN/seed_N)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--episodes", type=int, default=60, help="selection scenarios per checkpoint")
    parser.add_argument("--selection-seed", type=int, default=200, help="the first selection scenario")
    parser.add_argument("--from-step", type=int, default=150_000, help="skip earlier periodic checkpoints")
    parser.add_argument("--out")
    args = parser.parse_args()
    started = time.time()

    table = {}
    for seed in args.seeds:
        run = args.runs / f"seed_{seed}"
        if not (run / "heldout.json").is_file():
            raise SystemExit(f"{run / 'heldout.json'}: missing; run benchmarks/drive_recipe.py on this seed first")
        own = json.loads((run / "heldout.json").read_text())
        checkpoints = [c for c in list_checkpoints(run) if checkpoint_step(c) >= args.from_step]
        if not checkpoints:
            raise SystemExit(f"{run / 'checkpoints'}: no step_* checkpoint from step {args.from_step} on")
        selection = {c.name: cached(run / f"selection_{args.episodes}.json", c.name,
                                    lambda c=c: evaluation(c, args.episodes, args.selection_seed))
                     for c in checkpoints}
        pick = max(checkpoints, key=lambda c: (selection[c.name]["success_rate"], selection[c.name]["return_mean"]))
        # The run's own best is a copy of the policy evaluated at that step, which the next periodic
        # checkpoint follows by at most one chunk of updates: the pick is "the same" when it is that checkpoint.
        same_as_own = pick == min(checkpoints, key=lambda c: abs(checkpoint_step(c) - own["step"]))
        heldout = (own["success_rate"] if same_as_own else
                   cached(run / "heldout_steps.json", pick.name,
                          lambda: evaluation(pick, HELDOUT_EPISODES, 0))["success_rate"])
        table[str(seed)] = {
            "selection": {name: {k: v for k, v in e.items() if k != "per_episode_success"}
                          for name, e in selection.items()},
            "own_best": {"step": own["step"], "heldout_success": own["success_rate"]},
            "pick": {"checkpoint": pick.name, "same_as_own": same_as_own, "heldout_success": heldout},
        }
        print(f"seed {seed}: own best at {own['step']} -> {own['success_rate']:.3f}; "
              f"{args.episodes}-scenario pick {pick.name} -> {heldout:.3f}", flush=True)

    mean = lambda xs: sum(xs) / len(xs)
    summary = {"own_best_mean": mean([r["own_best"]["heldout_success"] for r in table.values()]),
               "pick_mean": mean([r["pick"]["heldout_success"] for r in table.values()])}
    print(f"held-out mean: own best {summary['own_best_mean']:.3f}, "
          f"{args.episodes}-scenario picks {summary['pick_mean']:.3f}")
    if args.out:
        Path(args.out).write_text(json.dumps({
            "benchmark": "checkpoint-selection", **provenance(started), "runs": str(args.runs),
            "episodes": args.episodes,
            "selection_scenarios": [args.selection_seed, args.selection_seed + args.episodes - 1],
            "heldout": f"{HELDOUT_ENV}, scenarios 0-{HELDOUT_EPISODES - 1}", "seeds": table, "summary": summary,
        }, indent=1) + "\n")


if __name__ == "__main__":
    main()
