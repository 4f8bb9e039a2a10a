"""The Ray backend against the subprocess backend, written as JSON. Not part of the test suite.

    python benchmarks/ray_backend.py --out benchmarks/results/ray_backend.json [--address auto]

1. The cost of the Ray path per step: vector steps/s of CartPole (an env that costs ~20 us) with
   random actions, in-process (sync), in subprocesses (async) and in Ray actors, 1 and 2 workers.
   1 / rate is the transport's cost per vector step (one message to each worker and back).
2. MetaDrive: raw env steps/s (random actions) and PPO training steps/s with the subprocess and
   the Ray backend at 1 and 2 workers (parallel efficiency: 2-worker rate / (2 x 1-worker rate)).
3. A projection to 16 and 64 workers from the measured per-step costs (printed and in the JSON).

Without --address a local Ray instance is started (all of this machine's CPUs).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from gymnasium.vector import AutoresetMode

from drivelab import api
from drivelab.config import EnvConfig
from drivelab.envs import make_vector_env
from drivelab.envs.ray_backend import connect
from provenance import provenance  # benchmarks/provenance.py


def vector_steps_per_s(env_cfg: EnvConfig, seconds: float) -> float:
    """Vector steps/s with random actions (each vector step is num_envs env steps)."""
    envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.SAME_STEP)
    try:
        envs.action_space.seed(0)
        envs.reset(seed=0)
        for _ in range(20):  # warm up: maps built, caches filled
            envs.step(envs.action_space.sample())
        steps, started = 0, time.perf_counter()
        while time.perf_counter() - started < seconds:
            envs.step(envs.action_space.sample())
            steps += 1
        return steps / (time.perf_counter() - started)
    finally:
        envs.close()


def ppo_steps_per_s(backend: str, workers: int, steps: int) -> float:
    """Steady-state PPO training steps/s on MetaDrive (the drive recipe, shorter batches), the
    trainer stepping the envs with every backend (``act_in_workers`` needs subprocess envs)."""
    with tempfile.TemporaryDirectory() as tmp:
        result = api.train("ppo", {"id": "MetaDrive-1000envs-v0", "num_envs": workers, "backend": backend},
                           config="ppo_metadrive_drive", steps=steps, run_dir=Path(tmp) / "run", progress=False,
                           eval={"every": 0}, log_every=1024, ppo={"num_steps": 1024, "num_minibatches": 8, "act_in_workers": False})
        return result.metrics["perf/steps_per_s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--address", help="Ray cluster address (default: start a local instance)")
    parser.add_argument("--seconds", type=float, default=10.0, help="per raw-throughput measurement")
    parser.add_argument("--ppo-steps", type=int, default=16384, help="per PPO measurement")
    parser.add_argument("--out", default="benchmarks/results/ray_backend.json")
    args = parser.parse_args()
    started = time.time()
    connect(args.address)
    out: dict = {"cpus": os.cpu_count(), "transport": {}, "metadrive_raw": {}, "metadrive_ppo": {}}

    for backend in ("sync", "async", "ray"):
        for workers in (1, 2):
            rate = vector_steps_per_s(EnvConfig(id="CartPole-v1", num_envs=workers, backend=backend, actor_cpus=0.5),
                                      args.seconds)
            out["transport"][f"{backend}_{workers}"] = {"vector_steps_per_s": rate, "us_per_vector_step": 1e6 / rate}
            print(f"CartPole {backend:5s} x{workers}: {rate:8.0f} vector steps/s ({1e6 / rate:7.0f} us each)", flush=True)

    for backend in ("async", "ray"):
        for workers in (1, 2):
            cfg = EnvConfig(id="MetaDrive-1000envs-v0", num_envs=workers, backend=backend)
            rate = workers * vector_steps_per_s(cfg, args.seconds * 2)
            out["metadrive_raw"][f"{backend}_{workers}"] = rate
            print(f"MetaDrive raw {backend:5s} x{workers}: {rate:6.0f} env steps/s", flush=True)
    for backend in ("async", "ray"):
        for workers in (1, 2):
            rate = ppo_steps_per_s(backend, workers, args.ppo_steps)
            out["metadrive_ppo"][f"{backend}_{workers}"] = rate
            print(f"MetaDrive PPO {backend:5s} x{workers}: {rate:6.0f} steps/s", flush=True)
    for kind in ("metadrive_raw", "metadrive_ppo"):
        for backend in ("async", "ray"):
            one, two = out[kind][f"{backend}_1"], out[kind][f"{backend}_2"]
            out[kind][f"{backend}_parallel_efficiency"] = two / (2 * one)

    # Projection. Per env step, a worker spends t_env in the simulator (MetaDrive, measured with
    # one worker over the subprocess backend, minus that backend's transport cost); the trainer
    # spends t_trainer (inference + update + bookkeeping, from the 1-worker PPO run) and, per vector
    # step, the Ray transport cost t_ray (CartPole over Ray, 2 workers). With W workers stepping
    # one env each, a vector step gives W env steps and costs max(t_env + t_ray, trainer's share)
    # when stepping overlaps inference, at best: rate(W) = W / (t_env + t_ray + W * t_trainer).
    t_async = 1 / out["transport"]["async_1"]["vector_steps_per_s"]
    t_ray = 1 / out["transport"]["ray_2"]["vector_steps_per_s"]
    t_env = 1 / out["metadrive_raw"]["async_1"] - t_async
    t_trainer = max(1 / out["metadrive_ppo"]["async_1"] - 1 / out["metadrive_raw"]["async_1"], 0.0)
    projection = {}
    for workers in (16, 64):
        projection[workers] = workers / (t_env + t_ray + workers * t_trainer)
    out["projection"] = {"t_env_s": t_env, "t_ray_transport_s": t_ray, "t_trainer_per_step_s": t_trainer,
                         "steps_per_s": projection,
                         "limit": "the single trainer: inference and the PPO update cost t_trainer per env step, "
                                  "so rate(W) tends to 1/t_trainer however many workers step the envs"}
    print(f"per step: env {t_env * 1e3:.2f} ms, Ray transport {t_ray * 1e3:.2f} ms per vector step, trainer "
          f"{t_trainer * 1e3:.2f} ms per env step -> projected {projection[16]:.0f} steps/s at 16 workers, "
          f"{projection[64]:.0f} at 64 (ceiling 1/t_trainer = {1 / max(t_trainer, 1e-9):.0f})")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({**out, **provenance(started)}, indent=1))
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
