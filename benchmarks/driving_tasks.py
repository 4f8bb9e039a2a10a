"""Steps/s of drivelab's driving tasks with random actions, written as JSON. Not part of the tests.

Each task is measured as a single env in this process (what `drivelab reward compare` and
debugging see) and as a vector of `--num-envs` subprocess envs (what training sees):

    python benchmarks/driving_tasks.py --seconds 20 --num-envs 2 --out driving_tasks.json

Random actions end most episodes early, so these rates include many resets (each episode's
length is reported). A car that barely moves is cheap to simulate (the physics engine lets
resting bodies sleep), which is why random [steering, throttle] runs faster than steering at a
held speed. MetaDrive builds a scenario's map on its first visit (0.15-0.5 s) and then reuses it
(about 0.01 s per reset), per process: with short random episodes a short measurement is mostly
map building, in each subprocess separately, so longer `--seconds` come closer to the steady
state of a long training run. The Duckietown task is measured only where its extra is installed (`make duckietown`).
"""

from __future__ import annotations

import argparse
import sys
import time

from training import report, env_steps_per_second  # benchmarks/ is on sys.path when run as a script

from drivelab.config import EnvConfig
from drivelab.envs import make_env
from drivelab.envs.duckietown import duckietown_available

TASKS = {
    "lane-follow (state, [steering, throttle])": EnvConfig(id="drivelab/MetaDriveLaneFollow-v0"),
    "lane-follow (state, steering at 8 m/s)": EnvConfig(id="drivelab/MetaDriveLaneFollow-v0",
                                                        kwargs={"target_speed": 8.0}),
    "top-down (84x84x5 uint8 images)": EnvConfig(id="drivelab/MetaDriveTopDown-v0"),
    "top-down, resize 64x64, frame stack 4": EnvConfig(id="drivelab/MetaDriveTopDown-v0",
                                                       obs_filters=[{"resize": {"shape": [64, 64]}},
                                                                    {"frame_stack": {"n": 4}}]),
    "duckietown (60x80 camera)": EnvConfig(id="drivelab/DuckietownLaneFollow-v0"),
}


def single_env_steps_per_second(cfg: EnvConfig, seconds: float) -> tuple[float, float]:
    """(steps/s, mean episode length) of one env with random actions, resets included."""
    env = make_env(cfg.id, dict(cfg.kwargs), obs_filters=list(cfg.obs_filters))
    try:
        env.action_space.seed(0)
        env.reset(seed=0)
        steps, episodes, started = 0, 0, time.perf_counter()
        while time.perf_counter() - started < seconds:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            steps += 1
            if terminated or truncated:
                episodes += 1
                env.reset()
        return steps / (time.perf_counter() - started), steps / max(episodes, 1)
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0, help="measurement time per task and setting")
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    started = time.time()
    results = []
    for name, cfg in TASKS.items():
        if "Duckietown" in cfg.id and not duckietown_available():
            results.append({"task": name, "env": cfg.id, "skipped": "the Duckietown extra is not installed"})
            continue
        single, episode_length = single_env_steps_per_second(cfg, args.seconds)
        cfg.num_envs = args.num_envs
        vector = env_steps_per_second(cfg, args.seconds)
        results.append({"task": name, "env": cfg.id, "kwargs": cfg.kwargs, "obs_filters": cfg.obs_filters,
                        "single_env_steps_per_s": single, "random_episode_length": episode_length,
                        f"vector_{args.num_envs}_envs_steps_per_s": vector})
        print(f"{name:<42}{single:8.0f} steps/s   {args.num_envs} envs: {vector:8.0f} steps/s   "
              f"(random episodes: {episode_length:.0f} steps)", file=sys.stderr)
    report({"benchmark": "driving-tasks", "results": results}, args.out, started)


if __name__ == "__main__":
    main()
