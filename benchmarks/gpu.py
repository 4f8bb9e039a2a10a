"""The GPU check, as one prepared script of a few minutes (issue 38). Not part of the test suite.

1. Every algorithm trains on the device: ``drivelab train --algo X --device D --steps 3000
   --num-envs 8`` on Pendulum-v1 (vector observations), and PPO and SAC on CarRacing-v3 (images,
   the CNN path). Exit code and wall time per run. With ``--pack``, each run's directory (its
   last checkpoint and step 0 only: ``keep_checkpoints 1``) goes into one tar.gz, so the runs can
   be evaluated on a CPU-only machine: ``drivelab eval RUN --episodes 2``; every run is also
   evaluated there with CUDA hidden.
2. Gradient updates/s of TD3 and SAC with the networks and a replay batch on the device, against
   the same on the CPU: hidden [256, 256] and [1024, 1024] x batch 256 and 1024, on MetaDrive's
   observation size (259) and action size (2). Each point is timed for ``--seconds``.
3. PPO on CarRacing-v3 (CNN), 8 env processes: training env steps/s with the networks on the
   device and on the CPU (the CPU run with ``--cpu-threads`` intra-op threads for its updates).

Run it where CUDA is (and, as a dry run of the script itself, anywhere with ``--device cpu``):

    python benchmarks/gpu.py --out gpu.json --pack gpu_runs.tar.gz
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import torch

from drivelab.algos import sac, td3
from drivelab.training.learning.replay_buffer import ReplayBatch
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, make_target
from drivelab.training.learning.optim import make_optimizers
from drivelab.training.outputs.plots import last_metrics
from training import report  # benchmarks/training.py

ALGOS = ("reinforce", "a2c", "ppo", "grpo", "ddpg", "td3", "sac")
# Off-policy runs must reach their updates within the short run; the image replay stays small (a
# 96x96x3 observation is 27 KB, stored twice per transition, and the buffer goes into checkpoints).
SHORT_RUN_FIELDS = {alg: [f"--{alg}.learning_starts", "1000"] for alg in ("ddpg", "td3", "sac")}
IMAGE_FIELDS = {"ppo": ["--ppo.num_steps", "128"],
                "sac": ["--sac.learning_starts", "500", "--sac.buffer_size", "200", "--sac.batch_size", "64"]}


def train_cli(run_dir: Path, algo: str, env: str, device: str, steps: int, extra: list[str]) -> dict:
    """One ``drivelab train`` in a subprocess (as a user would type it): exit code, wall time,
    the training's own steps/s and, on failure, the last lines it printed."""
    cmd = [sys.executable, "-m", "drivelab", "train", "--algo", algo, "--env", env, "--device", device,
           "--steps", str(steps), "--num-envs", "8", "--seed", "0", "--no-progress", "--run-dir", str(run_dir),
           "--eval.every", "0", "--keep_checkpoints", "1", *extra]
    started = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    result = {"algo": algo, "env": env, "device": device, "steps": steps, "run_dir": str(run_dir),
              "exit_code": done.returncode, "wall_s": round(time.perf_counter() - started, 1)}
    if done.returncode == 0:
        result["steps_per_s"] = last_metrics(run_dir).get("perf/steps_per_s")
    else:
        result["error"] = (done.stdout + done.stderr).strip().splitlines()[-3:]
    return result


def eval_on_cpu(run_dir: Path) -> int:
    """``drivelab eval RUN --episodes 2`` with CUDA hidden: the exit code."""
    cmd = [sys.executable, "-m", "drivelab", "eval", str(run_dir), "--episodes", "2", "--json"]
    return subprocess.run(cmd, capture_output=True, env={**os.environ, "CUDA_VISIBLE_DEVICES": ""}).returncode


def short_runs(device: str, work: Path, pack: str | None) -> list[dict]:
    """The short runs, each then evaluated with CUDA hidden. The packed runs are the vector ones:
    a CNN checkpoint (weights and Adam moments) is ~50 MB, too much to carry back."""
    runs = []
    for algo in ALGOS:
        runs.append(train_cli(work / f"{algo}-pendulum", algo, "Pendulum-v1", device, 3000, SHORT_RUN_FIELDS.get(algo, [])))
    for algo, fields in IMAGE_FIELDS.items():
        runs.append(train_cli(work / f"{algo}-carracing", algo, "CarRacing-v3", device, 1000, fields))
    for run in runs:
        if run["exit_code"] == 0:
            run["cpu_eval_exit_code"] = eval_on_cpu(Path(run["run_dir"]))
        print(run, flush=True)
    if pack:
        with tarfile.open(pack, "w:gz") as tar:
            for run in runs:
                if run["exit_code"] == 0 and run["env"] == "Pendulum-v1":
                    tar.add(run["run_dir"], arcname=Path(run["run_dir"]).name)
    return runs


def updates_per_s(algo: str, device: str, hidden: list[int], batch_size: int, seconds: float) -> float:
    """Gradient updates/s of ``algo`` (critics every call, the actor every other call, as TD3's
    policy_delay 2 and a SAC with actor_every 2 do) on random batches held on ``device``."""
    dev = torch.device(device)
    obs_space, act_space = gym.spaces.Box(-1, 1, (259,)), gym.spaces.Box(-1, 1, (2,))
    agent = OffPolicyAgent(obs_space, act_space, hidden, "relu", stochastic=algo == "sac").to(dev)
    target = make_target(agent)
    batch = ReplayBatch(torch.randn(batch_size, 259, device=dev), torch.rand(batch_size, 2, device=dev) * 2 - 1,
                        torch.randn(batch_size, device=dev), torch.randn(batch_size, 259, device=dev),
                        torch.zeros(batch_size, device=dev), torch.full((batch_size,), 0.99, device=dev))
    if algo == "sac":
        hp = sac.Params(hidden=hidden, batch_size=batch_size)
        log_alpha = torch.nn.Parameter(torch.zeros((), device=dev))
        opt = sac.build_optimizers(agent, log_alpha, hp)

        def one(i: int) -> None:
            sac.update(agent, target, log_alpha, opt, batch, hp, -2.0, update_actor=i % 2 == 0)
    else:
        hp = td3.Params(hidden=hidden, batch_size=batch_size)
        opt = make_optimizers(agent, hp)

        def one(i: int) -> None:
            td3.update(agent, target, opt, batch, hp, update_actor=i % 2 == 0)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    for i in range(10):  # warm-up: kernels chosen, allocator filled
        one(i)
    sync()
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds or count < 4:
        one(count)
        count += 1
    sync()
    return count / (time.perf_counter() - started)


def update_speeds(device: str, seconds: float) -> list[dict]:
    rows = []
    for algo in ("td3", "sac"):
        for hidden in ([256, 256], [1024, 1024]):
            for batch_size in (256, 1024):
                row = {"algo": algo, "hidden": hidden, "batch_size": batch_size,
                       f"{device}_updates_per_s": round(updates_per_s(algo, device, hidden, batch_size, seconds), 1)}
                if device != "cpu":
                    row["cpu_updates_per_s"] = round(updates_per_s(algo, "cpu", hidden, batch_size, seconds), 1)
                print(row, flush=True)
                rows.append(row)
    return rows


def ppo_carracing_speed(device: str, work: Path, steps: int, cpu_threads: int) -> list[dict]:
    rows, settings = [], [("cpu", cpu_threads)] if device == "cpu" else [(device, 1), ("cpu", cpu_threads)]
    for dev, threads in settings:
        run = train_cli(work / f"ppo-carracing-speed-{dev}", "ppo", "CarRacing-v3", dev, steps,
                        ["--update_threads", str(threads)])
        run["update_threads"] = threads
        print(run, flush=True)
        rows.append(run)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--seconds", type=float, default=3.0, help="timing per updates/s point")
    parser.add_argument("--ppo-steps", type=int, default=4096, help="PPO CarRacing steps per device")
    parser.add_argument("--cpu-threads", type=int, default=os.cpu_count() // 2, help="CPU updates' intra-op threads")
    parser.add_argument("--skip", action="append", default=[], choices=("runs", "updates", "ppo"))
    parser.add_argument("--pack", help="tar.gz of the short runs (last checkpoint each), to evaluate elsewhere")
    parser.add_argument("--out")
    args = parser.parse_args()
    started = time.time()
    result = {"benchmark": "gpu", "device": args.device, "torch": torch.__version__,
              "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
              "cpu_cores": os.cpu_count(), "cpu_threads_for_updates": torch.get_num_threads()}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if "runs" not in args.skip:
            result["short_runs"] = short_runs(args.device, work, args.pack)
        if "updates" not in args.skip:
            result["updates_per_s"] = update_speeds(args.device, args.seconds)
        if "ppo" not in args.skip:
            result["ppo_carracing"] = ppo_carracing_speed(args.device, work, args.ppo_steps, args.cpu_threads)
    report(result, args.out, started)


if __name__ == "__main__":
    main()
