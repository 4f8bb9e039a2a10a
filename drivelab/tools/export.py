"""Trained policies outside the training loop: one module from observation to simulator action,
used by the Python API (:func:`drivelab.api.load`) and exported to ONNX and TorchScript.

A run's policy network maps an observation of the env it trained on to that env's action; the
env may have adapted the simulator's action (``env.action_grid``: an index into N x M
[steering, throttle] pairs; ``env.fixed_throttle``: steering only). :class:`DeployedPolicy` puts
both halves in one ``nn.Module``, deterministic:

    observation (B, *obs_shape), as the run's env returns it (after its observation filters)
      -> observation normalisation (inside the network, with the run's statistics)
      -> the network's deterministic action (argmax, Gaussian mean clipped to the bounds,
         tanh-squashed mean scaled to the bounds)
      -> the action adapter (grid index -> [steering, throttle]; [steering] -> [steering, throttle])
      -> the simulator's action (B, A) float32 (or (B,) int64 for a plain Discrete env).

What cannot be a tensor operation stays outside and is written into ``policy.json`` so that a
robot or a submission can do it: the observation filters (image processing, frame stacking)
and a speed controller (the lane-following task's ``target_speed``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from drivelab.config import EnvConfig, TrainConfig, check_output_path, config_to_dict
from drivelab.envs.wrappers import grid_table, parse_grid
from drivelab.errors import DrivelabError

FORMATS = ("onnx", "torchscript")


class DeployedPolicy(nn.Module):
    """network + the run's action adapter: observation -> simulator action (see the module docstring)."""

    def __init__(self, network: nn.Module, env_cfg: EnvConfig):
        super().__init__()
        self.network = network
        table = None
        if env_cfg.action_grid:
            table = torch.as_tensor(grid_table(*parse_grid(env_cfg.action_grid), max_steering=env_cfg.max_steering))
        self.register_buffer("grid", table)
        throttle = env_cfg.fixed_throttle
        self.register_buffer("throttle", None if throttle is None else torch.tensor([float(throttle)]))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.adapt(self.network.deterministic_action(obs))

    def adapt(self, action: torch.Tensor) -> torch.Tensor:
        """The env's action (B,) or (B, A) -> the simulator's (what the env's action wrapper does)."""
        if self.grid is not None:
            return self.grid[action]
        if self.throttle is not None:
            return torch.cat([action, self.throttle.expand(action.shape[0], 1)], dim=-1)
        return action


def space_json(space: gym.Space) -> dict[str, Any]:
    if isinstance(space, gym.spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n)}
    low, high = np.asarray(space.low), np.asarray(space.high)
    same = low.size and np.all(low == low.flat[0]) and np.all(high == high.flat[0])
    return {"type": "Box", "shape": list(space.shape), "dtype": str(space.dtype),
            "low": float(low.flat[0]) if same else low.tolist(), "high": float(high.flat[0]) if same else high.tolist()}


def metadata(cfg: TrainConfig, step: int, obs_space: gym.Space, action_space: gym.Space) -> dict[str, Any]:
    """What a user of the exported files must know: spaces, env-side processing, provenance."""
    from drivelab.version import __version__

    return {
        "drivelab_version": __version__, "algo": cfg.algo, "env_id": cfg.env.id, "step": step,
        "input": {"name": "obs", "batch_axis": 0, **space_json(obs_space)},
        "output": {"name": "action", "batch_axis": 0, **space_json(action_space)},
        "env_side": {
            "obs_filters": list(cfg.env.obs_filters),   # applied to the simulator's observation first
            "target_speed": cfg.env.kwargs.get("target_speed"),  # a speed controller sets the throttle
            "action_repeat": cfg.env.action_repeat,   # each action is held for this many env steps
            "env_kwargs": dict(cfg.env.kwargs),
        },
        "in_graph": {"observation_normalisation": bool(getattr(cfg.algo_params, "normalize_obs", False)),
                     "action_grid": cfg.env.action_grid, "fixed_throttle": cfg.env.fixed_throttle},
        "config": config_to_dict(cfg),
    }


def export_policy(deployed: DeployedPolicy, meta: dict[str, Any], obs_space: gym.Space, fmt: str, out: Path) -> Path:
    """Write ``policy.onnx`` or ``policy.pt`` (TorchScript) and ``policy.json`` into ``out``."""
    if fmt not in FORMATS:
        raise DrivelabError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    check_output_path(out, "export --out", directory=True)  # one line, not a traceback from mkdir or torch
    out.mkdir(parents=True, exist_ok=True)
    deployed = deployed.eval()
    example = torch.as_tensor(np.stack([obs_space.sample() for _ in range(2)]))
    with torch.no_grad():
        if fmt == "onnx":
            path = out / "policy.onnx"
            torch.onnx.export(deployed, (example,), str(path), input_names=["obs"], output_names=["action"],
                              dynamic_axes={"obs": {0: "batch"}, "action": {0: "batch"}}, dynamo=False)
        else:
            path = out / "policy.pt"
            torch.jit.trace(deployed, example).save(str(path))
    (out / "policy.json").write_text(json.dumps({**meta, "format": fmt, "file": path.name}, indent=1) + "\n")
    return path
