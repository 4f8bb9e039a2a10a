"""How fast multi-agent scenes step, and where a step's time goes. Not a test.

    python benchmarks/multiagent_speed.py --scene Intersection --out benchmarks/results/multiagent_speed.json

1. Where the time goes: one scene in this process, every car holding a fixed action (straight on,
   half throttle), ``--steps`` steps under cProfile, split into MetaDrive's observation (lidar
   and state), the cars' own after-step work (navigation, their detectors), the physics engine,
   the respawns, drivelab's slot bookkeeping, and the rest.
2. Rate against env processes: the same scene in 1 and 2 subprocesses stepped together as the
   trainer steps them (``make_vector_env``, a batch of every car's action per step), env steps/s
   and car steps/s (live cars summed). A machine with more cores runs more processes (or Ray
   actors, ``env.backend: ray``); the JSON projects the rate as linear in processes up to the cores.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np
from drive_recipe import cpu_gauge_ms
from provenance import provenance  # benchmarks/provenance.py
from gymnasium.vector import AutoresetMode

from drivelab.envs import EnvConfig, make_vector_env
from drivelab.envs.multiagent import AgentSlots

# profile bucket -> the functions (file:function) whose cumulative time it is
BUCKETS = {
    "observation (lidar, state)": ("state_obs.py:observe",),
    "cars' after-step (navigation, detectors)": ("base_vehicle.py:after_step",),
    "physics": ("engine_core.py:step_physics_world",),
    "respawns": ("multi_agent_metadrive.py:_respawn_vehicles",),
    "drivelab slots": ("multiagent.py:_seat",),
}


def profile(scene: str, num_agents: int, steps: int) -> dict:
    env = AgentSlots(scene, num_agents=num_agents)
    env.reset(seed=0)
    action = np.tile(np.array([0.0, 0.5], np.float32), (env.num_slots, 1))
    live = 0
    profiler = cProfile.Profile()
    started = time.perf_counter()
    profiler.enable()
    for _ in range(steps):
        live += int(env.step(action)[4]["acted"].sum())
    profiler.disable()
    wall = time.perf_counter() - started
    env.close()
    stats = pstats.Stats(profiler).stats
    cumulative: dict[str, float] = {}
    for (file, _, name), entry in stats.items():  # same-named functions of one file: the outer one encloses
        key = f"{Path(file).name}:{name}"
        cumulative[key] = max(cumulative.get(key, 0.0), entry[3])
    total = cumulative["multiagent.py:step"]
    shares = {bucket: sum(cumulative.get(key, 0.0) for key in keys) / total for bucket, keys in BUCKETS.items()}
    shares["other"] = 1.0 - sum(shares.values())
    return {"env_steps_per_s_profiled": steps / wall, "mean_live_cars": live / steps, "time_shares": shares}


def rate(scene: str, num_agents: int, processes: int, steps: int) -> dict:
    cfg = EnvConfig(id=f"MultiAgent{scene}-v0", num_envs=processes, kwargs={"num_agents": num_agents})
    cfg.validate()
    envs = make_vector_env(cfg, autoreset_mode=AutoresetMode.SAME_STEP)
    try:
        envs.reset(seed=list(range(processes)))
        action = np.tile(np.array([0.0, 0.5], np.float32), (processes, num_agents, 1))
        for _ in range(20):  # warm-up: every car on the road
            envs.step(action)
        live, started = 0, time.perf_counter()
        for _ in range(steps):
            info = envs.step(action)[4]
            live += int(sum(np.sum(a) for a in info["acted"]))
        wall = time.perf_counter() - started
    finally:
        envs.close()
    return {"processes": processes, "env_steps_per_s": processes * steps / wall, "car_steps_per_s": live / wall}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="Intersection")
    parser.add_argument("--num-agents", type=int, default=30)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/multiagent_speed.json"))
    args = parser.parse_args()
    started = time.time()
    gauge_before = cpu_gauge_ms()
    rates = [rate(args.scene, args.num_agents, n, args.steps) for n in (1, 2)]
    profiled = profile(args.scene, args.num_agents, args.steps)
    gauge_after = cpu_gauge_ms()  # measured before provenance(), so that its end time follows every measurement
    result = {"benchmark": "multiagent-speed", **provenance(started), "scene": args.scene,
              "num_agents": args.num_agents, "steps": args.steps, "profile": profiled, "rates": rates,
              "cores": os.cpu_count(),
              "projection": "env steps/s ~ processes x the 1-process rate while each process has a core "
                            f"({rates[0]['env_steps_per_s']:.1f} per process here)",
              "cpu_gauge_ms": [gauge_before, gauge_after]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: result[k] for k in ("profile", "rates")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
