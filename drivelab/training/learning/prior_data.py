"""Prior data for off-policy learners: transitions recorded from a reference policy (a run, a
shipped driver) that every replay batch mixes in at a fixed share.

RLPD (Ball, Smith, Kostrikov & Levine 2023, "Efficient Online Reinforcement Learning with Offline
Data") draws each batch half from the prior data and half from the online replay ("symmetric
sampling"), with layer-normed critics and a high update-to-data ratio; ``prior_share`` is that
half. The prior transitions are one-step rows (their target bootstraps after one reward, whatever
the learner's ``n_step``), fixed for the whole run, and saved in every checkpoint, so that a
resumed run draws exactly the batches it would have drawn (the file may be gone by then).

The files (``drivelab demos`` writes them) are read by :mod:`drivelab.training.outputs.demonstrations`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from drivelab.training.learning.replay_buffer import ReplayBatch


class PriorData:
    """Fixed transitions that :meth:`sample` draws uniformly (with replacement), as a
    :class:`ReplayBatch` whose target bootstraps after one step."""

    def __init__(self, rows: dict[str, np.ndarray], about: dict[str, Any], device: torch.device | str = "cpu",
                 gamma: float = 0.99, cost_gamma: float | None = None):
        self.rows, self.about, self.device = rows, about, torch.device(device)
        self.gamma = gamma
        self.cost_gamma = gamma if cost_gamma is None else cost_gamma
        self.size = len(rows["rewards"])

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
