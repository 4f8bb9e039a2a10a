"""Prior data for off-policy learners: transitions recorded from a reference policy (a run, a
shipped driver) that every replay batch mixes in at a fixed share.

RLPD (Ball, Smith, Kostrikov & Levine 2023, "Efficient Online Reinforcement Learning with Offline
Data") draws each batch half from the prior data and half from the online replay ("symmetric
sampling"), with layer-normed critics and a high update-to-data ratio; ``prior_share`` is that
half. The prior transitions are one-step rows (their target bootstraps after one reward, whatever
the learner's ``n_step``), fixed for the whole run, and saved in every checkpoint, so that a
resumed run draws exactly the batches it would have drawn (the file may be gone by then).

A demonstration file is safetensors: the fields of :data:`FIELDS` (one row per transition; ``costs``
optional) and, as metadata, the layout it was recorded in (observation shape and dtype, action
dimension), the env and the policy that played, and ``env_steps``: what collecting it cost, which
a fair comparison adds to the learner's own budget. ``drivelab demos`` writes one.
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
from drivelab.training.learning.replay_buffer import ReplayBatch

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


class PriorData:
    """Fixed transitions that :meth:`sample` draws uniformly (with replacement), as a
    :class:`ReplayBatch` whose target bootstraps after one step."""

    def __init__(self, rows: dict[str, np.ndarray], about: dict[str, Any], device: torch.device | str = "cpu",
                 gamma: float = 0.99, cost_gamma: float | None = None):
        self.rows, self.about, self.device = rows, about, torch.device(device)
        self.gamma = gamma
        self.cost_gamma = gamma if cost_gamma is None else cost_gamma
        self.size = len(rows["rewards"])

    @classmethod
    def load(cls, path: str | Path, obs_space: gym.Space, act_space: gym.Space, costs: bool = False,
             device: torch.device | str = "cpu", gamma: float = 0.99, cost_gamma: float | None = None) -> PriorData:
        """Read a demonstration file, refusing in one line naming it one recorded in another
        layout (observations or actions), without costs where the learner needs them, or empty."""
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
        return cls(rows, about, device, gamma, cost_gamma)

    def sample(self, batch_size: int, rng: np.random.Generator) -> ReplayBatch:
        """``batch_size`` rows drawn uniformly, one-step targets (discount gamma)."""
        idx = rng.integers(0, self.size, size=batch_size)
        to = lambda x: torch.as_tensor(x, device=self.device)  # noqa: E731
        r = self.rows
        batch = ReplayBatch(to(r["obs"][idx]), to(r["actions"][idx]), to(r["rewards"][idx]), to(r["next_obs"][idx]),
                            to(r["terminated"][idx].astype(np.float32)),
                            to(np.full(batch_size, self.gamma, np.float32)))
        if "costs" not in r:
            return batch
        return batch._replace(costs=to(r["costs"][idx]), cost_discount=to(np.full(batch_size, self.cost_gamma, np.float32)))

    # Checkpointing: the rows as tensors beside the replay buffer's, the metadata in the JSON state.
    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        return ({f"prior/{name}": torch.from_numpy(np.ascontiguousarray(values)) for name, values in self.rows.items()},
                {"about": self.about, "fields": list(self.rows)})

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict, device: torch.device | str = "cpu",
                   gamma: float = 0.99, cost_gamma: float | None = None) -> PriorData:
        rows = {name: tensors[f"prior/{name}"].numpy() for name in meta["fields"]}
        return cls(rows, meta["about"], device, gamma, cost_gamma)


def mixed_batch(online: ReplayBatch, prior: ReplayBatch) -> ReplayBatch:
    """One batch of the online rows then the prior rows, field by field (B_online + B_prior rows)."""
    return ReplayBatch(*(None if a is None else torch.cat([a, b]) for a, b in zip(online, prior)))


def prior_rows(batch_size: int, share: float) -> int:
    """How many of a batch's rows come from the prior data: ``share`` of them, rounded."""
    return int(round(share * batch_size))
