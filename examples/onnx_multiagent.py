"""Drive every car of a MetaDrive multi-agent scene with one exported drivelab policy, without
drivelab: all live cars' observations go through the ONNX graph as one batch each step. Needs only
onnxruntime, numpy and metadrive-simulator.

    drivelab train --config ma_intersection --run-dir runs/ma_intersection
    drivelab export runs/ma_intersection --format onnx --out exported_ma/
    python examples/onnx_multiagent.py exported_ma/ --episodes 2
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import metadrive.envs.marl_envs as marl
import numpy as np
import onnxruntime
from metadrive.engine.base_engine import BaseEngine

# drivelab's scene ids -> MetaDrive's classes
SCENES = {"MultiAgentIntersection-v0": "MultiAgentIntersectionEnv", "MultiAgentRoundabout-v0": "MultiAgentRoundaboutEnv",
          "MultiAgentTollgate-v0": "MultiAgentTollgateEnv", "MultiAgentBottleneck-v0": "MultiAgentBottleneckEnv",
          "MultiAgentParkingLot-v0": "MultiAgentParkingLotEnv", "MultiAgentPGMap-v0": "MultiAgentMetaDrive"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("exported", help="directory with policy.onnx and policy.json")
    parser.add_argument("--episodes", type=int, default=2, help="scene episodes")
    parser.add_argument("--scene", default=None, help="a drivelab scene id (default: the one the policy trained on)")
    args = parser.parse_args()

    meta = json.loads((Path(args.exported) / "policy.json").read_text())
    scene = args.scene or meta["env_id"]
    if scene not in SCENES:
        raise SystemExit(f"--scene must be one of {', '.join(SCENES)}, got {scene}")
    session = onnxruntime.InferenceSession(str(Path(args.exported) / meta["file"]))
    BaseEngine.try_pull_asset = staticmethod(lambda: None)  # no 3D assets needed (as drivelab does)
    kwargs = {**meta["env_side"]["env_kwargs"], "use_render": False, "log_level": 50}
    env = getattr(marl, SCENES[scene])(kwargs)
    try:
        for episode in range(args.episodes):
            obs, _ = env.reset()
            outcomes = {"arrived": 0, "crashed": 0, "off road": 0, "time out": 0}
            done = False
            while not done:
                cars = list(obs)
                actions = session.run(None, {"obs": np.stack([obs[c] for c in cars]).astype(np.float32)})[0]
                obs, _, terminated, truncated, infos = env.step(dict(zip(cars, actions)))
                for car, ended in terminated.items():
                    if car != "__all__" and (ended or truncated.get(car)):
                        info = infos[car]
                        outcomes["arrived" if info["arrive_dest"] else "crashed" if info["crash"]
                                 else "off road" if info["out_of_road"] else "time out"] += 1
                done = terminated["__all__"] or truncated["__all__"]
            total = sum(outcomes.values())
            print(f"{scene} episode {episode}: {total} cars, "
                  + ", ".join(f"{name} {n / max(total, 1):.0%}" for name, n in outcomes.items()))
    finally:
        env.close()


if __name__ == "__main__":
    main()
