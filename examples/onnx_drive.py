"""Drive MetaDrive with an exported drivelab policy, without drivelab: what a robot or a
competition submission runs. Needs only onnxruntime, numpy and metadrive-simulator.

    drivelab export runs/drive/checkpoints/best --format onnx --out exported/
    python examples/onnx_drive.py exported/ --episodes 5            # validation scenarios 0..4

The exported graph already holds the observation normalisation and the mapping to MetaDrive's
[steering, throttle]; policy.json says what stays outside (observation filters, none for
MetaDrive's state observation) and which scenarios the policy trained on.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import onnxruntime
from metadrive.engine.base_engine import BaseEngine
from metadrive.envs import MetaDriveEnv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("exported", help="directory with policy.onnx and policy.json")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--start-seed", type=int, default=0, help="first scenario (0: MetaDrive's validation split)")
    args = parser.parse_args()

    meta = json.loads((Path(args.exported) / "policy.json").read_text())
    if meta["env_side"]["obs_filters"] or meta["env_side"]["target_speed"]:
        raise SystemExit("this example drives MetaDrive's state observation with [steering, throttle] actions; "
                         f"the policy also needs {meta['env_side']}")
    repeat = meta["env_side"].get("action_repeat", 1)   # the policy decides every `repeat` env steps
    session = onnxruntime.InferenceSession(str(Path(args.exported) / meta["file"]))

    # MetaDrive downloads a 3D asset pack when an engine starts; physics and state observations
    # do not use it, so switch the download off (as drivelab does).
    BaseEngine.try_pull_asset = staticmethod(lambda: None)
    # vehicle_config shapes the observation (e.g. lidar.num_others: the nearest vehicles): it must
    # be the one the policy trained with; the rest of the training kwargs (rewards) do not matter here.
    vehicle_config = meta["env_side"]["env_kwargs"].get("vehicle_config", {})
    env = MetaDriveEnv({"use_render": False, "horizon": 1000, "start_seed": args.start_seed,
                        "num_scenarios": args.episodes, "log_level": 50, "vehicle_config": vehicle_config})
    try:
        for k in range(args.episodes):
            obs, _ = env.reset(seed=args.start_seed + k)
            total, done, info, t = 0.0, False, {}, 0
            while not done:
                if t % repeat == 0:
                    action = session.run(None, {"obs": obs[None].astype(np.float32)})[0][0]
                obs, reward, terminated, truncated, info = env.step(action)
                total, done, t = total + reward, terminated or truncated, t + 1
            print(f"scenario {args.start_seed + k}: return {total:7.1f}, route {info['route_completion']:.0%}, "
                  f"{'arrived' if info['arrive_dest'] else 'crashed' if info['crash'] else 'off road' if info['out_of_road'] else 'time out'}")
    finally:
        env.close()


if __name__ == "__main__":
    main()
