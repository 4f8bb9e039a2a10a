"""Demonstration files: transitions recorded from a reference policy (``drivelab demos``) for an
off-policy learner's prior data (:mod:`drivelab.training.learning.prior_data` samples them).

A demonstration file is safetensors: the fields of :data:`FIELDS` (one row per transition; ``costs``
optional) and, as metadata, the layout it was recorded in (observation shape and dtype, action
dimension), the env and the policy that played, and ``env_steps``: what collecting it cost, which
a fair comparison adds to the learner's own budget.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, safe_open, save_file

from drivelab.errors import DrivelabError

FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated", "truncated")


def layout(obs_space: gym.Space, act_space: gym.Space) -> dict[str, Any]:
    """What a demonstration must share with the learner: observation shape and dtype, action dimension."""
    return {"obs_shape": list(obs_space.shape), "obs_dtype": np.dtype(obs_space.dtype).name,
            "act_dim": int(np.prod(act_space.shape))}


def save_demonstrations(path: str | Path, rows: dict[str, np.ndarray], obs_space: gym.Space, act_space: gym.Space,
                        **about: Any) -> Path:
    """Write transitions (``rows``: each field of :data:`FIELDS`, and optionally ``costs``, with one
    row per transition; actions in the policy's [-1, 1] units) with their layout and ``about``
    (env, policy, env_steps, seconds: any JSON values) as metadata."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {name: torch.from_numpy(np.ascontiguousarray(values)) for name, values in rows.items()}
    metadata = {"drivelab_demonstrations": json.dumps({**layout(obs_space, act_space), **about})}
    save_file(tensors, str(path), metadata=metadata)
    return path


def read_about(path: str | Path) -> dict[str, Any]:
    """The metadata of a demonstration file (layout, env, policy, env_steps), refused in one line
    when the file is missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise DrivelabError(f"prior_data: no such file: {path}")
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
    except (SafetensorError, OSError, ValueError) as exc:
        raise DrivelabError(f"prior_data: {path} is not a demonstration file (safetensors): {exc}") from None
    if "drivelab_demonstrations" not in metadata:
        raise DrivelabError(f"prior_data: {path} is a safetensors file without drivelab's demonstration metadata "
                            "(write one with drivelab demos)")
    return json.loads(metadata["drivelab_demonstrations"])


def load_demonstrations(path: str | Path, obs_space: gym.Space, act_space: gym.Space,
                        costs: bool = False) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(rows, metadata) of a demonstration file, refused in one line naming it when it was recorded
    in another layout (observations or actions), lacks the costs a constrained learner needs, or is empty."""
    about = read_about(path)
    expected = layout(obs_space, act_space)
    for key, what in (("obs_shape", "observations of shape"), ("obs_dtype", "observations of dtype"),
                      ("act_dim", "actions of dimension")):
        if about.get(key) != expected[key]:
            raise DrivelabError(f"prior_data: {path} holds {what} {about.get(key)}, the env has {expected[key]}: "
                                f"record the demonstrations in this config's env (drivelab demos --config ...)")
    tensors = load_file(str(path))
    needed = FIELDS + (("costs",) if costs else ())
    missing = [name for name in needed if name not in tensors]
    if missing:
        raise DrivelabError(f"prior_data: {path} lacks {', '.join(missing)}"
                            + (" (a constrained learner needs each step's cost)" if "costs" in missing else ""))
    rows = {name: tensors[name].numpy() for name in needed}
    sizes = {len(values) for values in rows.values()}
    if len(sizes) != 1 or 0 in sizes:
        raise DrivelabError(f"prior_data: {path} holds no transitions or fields of different lengths ({sorted(sizes)})")
    return rows, about
