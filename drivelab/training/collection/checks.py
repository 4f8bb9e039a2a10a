"""Checks on what the envs hand the collectors: a non-finite reward or observation is caught
where it enters, in one line that names it, before any update learns from it (and before any
checkpoint could keep the weights it would spoil)."""

from __future__ import annotations

import numpy as np

from drivelab.errors import DrivelabError


def check_finite_step(obs: np.ndarray, reward: np.ndarray, step: int | None, first_env: int = 0) -> None:
    """Raise one line if ``reward`` (N,) or a float ``obs`` (N, ...) holds NaN or infinity;
    ``step`` is the run's env step (None inside an env worker, which does not know it) and
    ``first_env`` the index of the batch's first env."""
    for what, values in (("reward", reward), ("observation", obs)):
        rows = np.asarray(values).reshape(len(values), -1)
        if rows.dtype.kind != "f" or np.isfinite(rows).all():
            continue
        row, column = np.argwhere(~np.isfinite(rows))[0]
        where = f"env {first_env + row}" if step is not None else "an env worker's env"
        when = f" near env step {step}" if step is not None else ""
        raise DrivelabError(f"{where} returned a non-finite {what} ({rows[row, column]}){when}: drivelab cannot "
                            "learn from it; fix the env (or its reward terms and observation filters), then --resume "
                            "from the last checkpoint, which is intact")
