"""Single-observation inference latency of a trained policy: drivelab's Python policy
(``drivelab.load(...).act``), the TorchScript export and the ONNX export under onnxruntime.
Not a test.

    python benchmarks/inference_latency.py runs/drive/checkpoints/best [--calls 5000] [--out latency.json]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime
import torch

import drivelab
from training import report  # benchmarks/training.py


def median_us(fn, obs: np.ndarray, calls: int) -> float:
    for _ in range(100):  # warm-up
        fn(obs)
    times = np.empty(calls)
    for i in range(calls):
        started = time.perf_counter()
        fn(obs)
        times[i] = time.perf_counter() - started
    return float(np.median(times) * 1e6)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("path", help="run directory, checkpoint directory or RUN/best")
    parser.add_argument("--calls", type=int, default=5000)
    parser.add_argument("--out")
    args = parser.parse_args()
    started = time.time()
    torch.set_num_threads(1)
    policy = drivelab.load(args.path)
    obs = policy.observation_space.sample()
    with tempfile.TemporaryDirectory() as tmp:
        policy.export(Path(tmp) / "onnx", "onnx")
        policy.export(Path(tmp) / "ts", "torchscript")
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = 1
        session = onnxruntime.InferenceSession(str(Path(tmp) / "onnx" / "policy.onnx"), options)
        scripted = torch.jit.load(str(Path(tmp) / "ts" / "policy.pt"))
        batch = obs[None]
        with torch.no_grad():
            result = {
                "benchmark": "inference-latency", "checkpoint": str(policy.checkpoint), "algo": policy.config.algo,
                "obs_shape": list(obs.shape), "calls": args.calls, "threads": 1,
                "policy_act_us": median_us(policy.act, obs, args.calls),
                "torchscript_us": median_us(lambda o: scripted(torch.as_tensor(o)), batch, args.calls),
                "onnxruntime_us": median_us(lambda o: session.run(None, {"obs": o}), batch, args.calls),
            }
    report(result, args.out, started)


if __name__ == "__main__":
    main()
