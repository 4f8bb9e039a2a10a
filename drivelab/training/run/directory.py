"""The run directory of a training run: its lock, its leftovers, its ``config.yaml``, and the seeds.

A run directory has one writer at a time (``RUN/.lock``, held for the whole run); whatever a
killed writer left half-done is removed before the run starts, and the resolved config is
written first, so the directory always says what produced it.
"""

from __future__ import annotations

import fcntl
import os
import shutil
from pathlib import Path
from typing import TextIO

import numpy as np
import torch

from drivelab.config import TrainConfig, save_config
from drivelab.errors import DrivelabError, kill_point

MARKER = ".drivelab-run"   # written into every run directory drivelab creates


def open_run_dir(cfg: TrainConfig) -> TextIO:
    """Create (or recognise) and lock ``cfg.run_dir``, remove stale temporaries and write
    ``config.yaml``. Returns the lock's file: the lock is held until it is closed."""
    run_dir = Path(cfg.run_dir)
    claim_run_dir(run_dir)
    lock = lock_run_dir(run_dir)
    remove_stale_temporaries(run_dir)
    kill_point("before-config")
    save_config(cfg, run_dir / "config.yaml")  # atomic: the file is whole or absent
    return lock


def claim_run_dir(run_dir: Path) -> None:
    """Make ``run_dir`` drivelab's: create it with its marker, or accept a directory that holds
    the marker, that is empty, or that is a run written before markers existed (which gets one).
    Any other existing directory holds someone's files, which a run would overwrite
    (``config.yaml``, ``metrics.csv``): refused in one line that names what is there."""
    if (run_dir / MARKER).is_file():
        return
    if run_dir.is_dir():
        content = sorted(p.name + ("/" if p.is_dir() else "") for p in run_dir.iterdir())
        # a run written before markers existed, or fetched from MLflow: a config and checkpoints
        legacy = (run_dir / "config.yaml").is_file() and any((run_dir / "checkpoints").glob("step_*"))
        if content and not legacy:
            shown = ", ".join(content[:5]) + (f" and {len(content) - 5} more" if len(content) > 5 else "")
            raise DrivelabError(f"run directory {run_dir} already exists and is not a drivelab run (it holds {shown}): "
                                "choose a new --run-dir, or empty this one")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / MARKER).write_text("a drivelab run directory: drivelab trains, resumes and evaluates here\n")


def seed_everything(cfg: TrainConfig) -> np.random.Generator:
    """Seed torch (action sampling, initialisation) with ``cfg.seed``, set its thread count, and
    return the numpy Generator that draws the env reset seeds."""
    torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(cfg.seed)
    return np.random.default_rng(cfg.seed)


def lock_run_dir(run_dir: Path) -> TextIO:
    """An exclusive lock on ``RUN/.lock`` for the lifetime of the returned file: a second writer
    (a fresh run or a --resume) is refused; a killed process's lock goes with it (flock)."""
    handle = open(run_dir / ".lock", "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        owner = handle.read().strip() or "?"
        handle.close()
        raise DrivelabError(f"run directory {run_dir} is in use by another drivelab process (pid {owner})") from None
    handle.seek(0)
    handle.truncate()
    handle.write(str(os.getpid()))
    handle.flush()
    return handle


def remove_stale_temporaries(run_dir: Path) -> None:
    """What a killed process left half-done: checkpoint directories half-written
    (``checkpoints/.tmp_*``), the state of an evaluation that never finished
    (``checkpoints/.eval_pending``), a checkpoint set aside while its replacement was moved in
    (``checkpoints/.old_*``: put back if the replacement is missing) and a half-written config.
    With the lock held, none of them can still be in use."""
    root = run_dir / "checkpoints"
    for tmp in [*root.glob(".tmp_*"), root / ".eval_pending"]:
        shutil.rmtree(tmp, ignore_errors=True)
    for old in root.glob(".old_*"):  # killed while replacing a checkpoint (e.g. best): keep the old one
        target = root / old.name[len(".old_"):].rsplit("_", 1)[0]
        if target.exists() or target.name.startswith("."):
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(old, target)
    (run_dir / ".config.yaml.tmp").unlink(missing_ok=True)
