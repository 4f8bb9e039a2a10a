"""What happens in a costly episode? A policy replayed on chosen held-out scenarios of the safety
task, decision by decision around its contacts. A diagnosis, not a test.

    python benchmarks/safe_drive_contacts.py --policy drivelab-safe-driver --scenarios 21 35 47 82 178 \\
        --out benchmarks/results/archive/safe_drive_contacts.json

Plays ``--policy`` (a shipped driver's name, a run or a checkpoint) deterministically on each
scenario of SafeMetaDrive-validation-v0 (the held-out scenarios of benchmarks/safe_drive.py) and
writes per episode: how it ended (success, stuck guard, step limit), its cost, the decision of the
first contact and the car's speed there, what the car touched (MetaDrive's ``crash_vehicle``,
``crash_object``, ``crash_building``, ``crash_sidewalk`` flags), the decisions in contact, and the
mean steering and throttle (negative: brake) the policy chose while in contact, and the approach:
for the 20 decisions before the first contact, the nearest thing the car's lidar saw (m), its
speed (m/s) and the action chosen (did the car see the object, and what did it do?). MetaDrive's car has
no reverse gear by default (``enable_reverse: False``): a negative throttle only brakes.

``--escape STEERING THROTTLE DECISIONS`` (repeatable) asks what a way out would be worth: each
scenario is played again with that fixed action held for DECISIONS decisions from the policy's
first contact on (the policy drives before and after), and the same record is written per
manoeuvre. A counterfactual only where the policy reaches the same first contact again (checked:
``same_first_contact``), since MetaDrive's outcome can depend on what its engine played before.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import deque
from pathlib import Path

import numpy as np
from provenance import provenance  # benchmarks/provenance.py
from safe_drive import HELDOUT_ENV

import drivelab
from drivelab.envs import make_env
from drivelab.envs.metadrive import lidar_returns

TOUCHED = ("crash_vehicle", "crash_object", "crash_building", "crash_sidewalk")
APPROACH = 20   # decisions before the first contact kept in the record


def replay(policy, env, scenario: int, escape: tuple[float, float, int] | None = None) -> dict:
    """One deterministic episode on ``scenario``: how it ended and what the car did in contact;
    with ``escape`` = (steering, throttle, decisions), that action replaces the policy's for the
    given decisions from the first contact on."""
    obs, info = env.reset(seed=scenario)
    agent, lidar = env.unwrapped.metadrive.agent, env.unwrapped.metadrive.config["vehicle_config"]["lidar"]
    approach: deque = deque(maxlen=APPROACH)   # (seen m, speed m/s, steering, throttle) per decision
    decisions, first, cost = 0, None, 0.0
    touched: dict[str, int] = {}
    in_contact: list[np.ndarray] = []   # the actions chosen on the decisions in contact, (2,) each
    done, override = False, 0   # decisions left of the escape manoeuvre
    while not done:
        action = np.array(escape[:2], np.float32) if override else policy.act(obs)
        override = max(override - 1, 0)
        obs, _, terminated, truncated, info = env.step(action)
        decisions, cost, done = decisions + 1, cost + info["cost"], terminated or truncated
        taken = np.asarray(action, float)
        if first is None:
            approach.append([round(float(lidar_returns(obs, lidar).min()), 1), round(info["speed"], 1),
                             *taken.round(2).tolist()])
        if info["collided"]:
            if first is None:
                first = {"decision": decisions, "speed": round(info["speed"], 2)}
                override = int(escape[2]) if escape else 0
            in_contact.append(taken)
            for flag in TOUCHED:
                touched[flag] = touched.get(flag, 0) + bool(getattr(agent, flag, False))
    ended = "success" if info["success"] else "stuck" if info.get("stuck") else \
        "out_of_road" if info["out_of_road"] and terminated else "step_limit" if truncated else "terminated"
    mean_action = np.mean(in_contact, axis=0).round(2).tolist() if in_contact else None
    return {"scenario": scenario, "ended": ended, "decisions": decisions, "cost": round(cost, 2),
            "first_contact": first, "decisions_in_contact": len(in_contact), "touched": touched,
            "approach": {"columns": ["seen_m", "speed_m_s", "steering", "throttle"], "decisions": list(approach)}
            if first else None,
            "mean_action_in_contact": {"steering": mean_action[0], "throttle": mean_action[1]} if mean_action else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="drivelab-safe-driver", help="a shipped driver's name, a run or a checkpoint")
    parser.add_argument("--scenarios", type=int, nargs="+", required=True, help="held-out scenarios (0-199)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--escape", type=float, nargs=3, action="append", default=[],
                        metavar=("STEERING", "THROTTLE", "DECISIONS"), help="a fixed action held from the first contact")
    args = parser.parse_args()
    started = time.time()
    policy = drivelab.load(args.policy)
    env = make_env(policy.env_config.on(HELDOUT_ENV))
    episodes = []
    for scenario in args.scenarios:
        episodes.append(replay(policy, env, scenario))
        print(json.dumps(episodes[-1]), flush=True)
        for escape in args.escape:
            probe = replay(policy, env, scenario, tuple(escape))
            probe.update(escape=escape, same_first_contact=probe["first_contact"] == episodes[-1]["first_contact"])
            episodes.append(probe)
            print(json.dumps(probe), flush=True)
    env.close()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "safe-drive-contacts", **provenance(started), "policy": args.policy,
                                    "env": HELDOUT_ENV, "episodes": episodes}, indent=1) + "\n")


if __name__ == "__main__":
    main()
