"""Safe checkpoints: tensors in safetensors, everything else in JSON. No pickle anywhere.

A checkpoint is a directory ``RUN_DIR/checkpoints/step_<12 digits>/`` holding

* ``tensors.safetensors``: module weights (``module/<name>/<param>``), optimiser tensors
  (``optim/<name>/<param index>/<key>``) and RNG states (``rng/torch``);
* ``state.json``: step, resolved config, optimiser hyper-parameters, numpy RNG states, and
  whatever small state the trainer adds.

It is written into a temporary directory and renamed into place, so a run killed mid-write
never leaves a half checkpoint behind: the latest complete one is always loadable.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file
from torch import nn

from drivelab.errors import DrivelabError, kill_point
from drivelab.version import __version__

_STEP_DIR = re.compile(r"^step_(\d{12})$")


@dataclass
class Checkpoint:
    path: Path
    tensors: dict[str, torch.Tensor]
    state: dict[str, Any]

    @property
    def step(self) -> int:
        return int(self.state["step"])


def optimizer_to_flat(name: str, optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    """Split an optimiser state_dict into safetensors-able tensors and JSON-able rest."""
    sd = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for index, param_state in sd["state"].items():
        for key, value in param_state.items():
            if torch.is_tensor(value):
                tensors[f"optim/{name}/{index}/{key}"] = value.detach().cpu().contiguous()
            else:
                scalars.setdefault(str(index), {})[key] = value
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars, "tensors": len(tensors)}


def optimizer_from_flat(name: str, optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    state: dict[int, dict[str, Any]] = {}
    prefix = f"optim/{name}/"
    for key, value in tensors.items():
        if key.startswith(prefix):
            index, field = key[len(prefix):].split("/", 1)
            state.setdefault(int(index), {})[field] = value
    for index, fields in meta["scalars"].items():
        state.setdefault(int(index), {}).update(fields)
    # JSON has no tuples: restore them (e.g. Adam's betas) so the state is exactly as saved.
    groups = [{k: (v if k == "params" or not isinstance(v, list) else tuple(v)) for k, v in group.items()}
              for group in meta["param_groups"]]
    optimizer.load_state_dict({"state": state, "param_groups": groups})


def save_checkpoint(run_dir: str | Path, step: int, *, modules: dict[str, nn.Module],
                    optimizers: dict[str, torch.optim.Optimizer] | None = None,
                    tensors: dict[str, torch.Tensor] | None = None, state: dict[str, Any] | None = None,
                    keep: int = 3, dirname: str | None = None) -> Path:
    """Write a checkpoint atomically and prune old ones (the step-0 checkpoint is always kept,
    for before/after comparisons). Returns its directory, ``step_<N>``, or ``dirname`` when given
    (e.g. ``best``: replaced in place, never pruned, never taken as the latest)."""
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    flat: dict[str, torch.Tensor] = {}
    for name, module in modules.items():
        for key, value in module.state_dict().items():
            flat[f"module/{name}/{key}"] = value.detach().cpu().contiguous()
    optim_meta = {}
    for name, optimizer in (optimizers or {}).items():
        optim_tensors, optim_meta[name] = optimizer_to_flat(name, optimizer)
        flat.update(optim_tensors)
    for key, value in (tensors or {}).items():
        flat[key] = value.detach().cpu().contiguous()
    flat["rng/torch"] = torch.get_rng_state()
    full_state = {"step": int(step), "drivelab_version": __version__, "optimizers": optim_meta, **(state or {})}

    final = root / (dirname or f"step_{step:012d}")
    tmp = root / f".tmp_{final.name}_{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir()
        save_file(flat, str(tmp / "tensors.safetensors"))
        if dirname is None:  # a periodic checkpoint (best and .eval_pending have their own phases)
            kill_point("mid-checkpoint")
        with open(tmp / "state.json", "w") as f:
            json.dump(full_state, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
    except Exception as exc:  # noqa: BLE001 - a full disk, a lost mount: the previous checkpoint stays the latest
        shutil.rmtree(tmp, ignore_errors=True)
        raise DrivelabError(f"could not write checkpoint {final}: {str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__}") from None
    if dirname == "best":
        kill_point("best-copy")
    if final.exists():  # set the old one aside first: a kill between the renames loses neither
        aside = root / f".old_{final.name}_{os.getpid()}"
        os.replace(final, aside)
        os.replace(tmp, final)
        shutil.rmtree(aside)
    else:
        os.replace(tmp, final)
    if dirname is not None:
        return final

    kept = [p for p in list_checkpoints(run_dir) if not p.name.endswith("000000000000")]
    for old in kept[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def list_checkpoints(run_dir: str | Path) -> list[Path]:
    root = Path(run_dir) / "checkpoints"
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if _STEP_DIR.match(p.name) and (p / "state.json").is_file())


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint directory, a run directory (-> its latest checkpoint), or ``RUN/best`` (-> the
    best evaluated checkpoint, ``RUN/checkpoints/best``)."""
    path = Path(path)
    if (path / "state.json").is_file() and (path / "tensors.safetensors").is_file():
        return path
    if path.name == "best" and not path.exists() and (path.parent / "checkpoints" / "best").is_dir():
        return path.parent / "checkpoints" / "best"
    if path.name == "best" and not path.exists():
        _refuse_missing_best(path)
    if not path.exists():
        raise DrivelabError(f"checkpoint or run directory not found: {path}")
    found = list_checkpoints(path)
    if not found:
        raise DrivelabError(f"no checkpoint found in {path}")
    return found[-1]


def _refuse_missing_best(path: Path) -> None:
    """``RUN/best`` (or ``RUN/checkpoints/best``) asked of a run that kept no best checkpoint: one
    line that says why (no evaluation ran during training) and what to do instead. A path that
    is not in a run is left to the caller's "not found"."""
    run = path.parent.parent if path.parent.name == "checkpoints" else path.parent
    found = list_checkpoints(run)
    if not found:
        return
    try:  # the run's config, as its latest checkpoint saved it: was evaluation on at all?
        every = json.loads((found[-1] / "state.json").read_text())["config"]["eval"]["every"]
    except (OSError, ValueError, KeyError, TypeError):
        every = 0
    if every:
        raise DrivelabError(f"{path}: no evaluation has run yet in {run} (eval.every {every}), so there is no best "
                            f"checkpoint: load the latest checkpoint instead ({run})")
    raise DrivelabError(f"{path}: no evaluation ran in {run} (eval.every 0), so there is no best checkpoint: train with "
                        f"eval.every > 0 (--eval.every N) to keep one, or load the latest checkpoint ({run})")


def checkpoint_step(path: str | Path) -> int:
    """The env step a checkpoint directory (``step_<N>`` or ``best``) was written at."""
    return int(json.loads((Path(path) / "state.json").read_text())["step"])


def read_checkpoint(path: Path) -> Checkpoint:
    """One checkpoint directory, checked before any tensor is used: a complete safetensors file
    and a well-formed ``state.json`` (a one-line error naming the file otherwise)."""
    try:
        state = json.loads((path / "state.json").read_text())
    except (OSError, ValueError) as exc:
        raise DrivelabError(f"checkpoint file {path / 'state.json'} is unreadable: {exc}") from None
    if not isinstance(state, dict) or not isinstance(state.get("step"), int):
        raise DrivelabError(f"checkpoint file {path / 'state.json'} is not a drivelab checkpoint state (no step)")
    try:
        tensors = load_file(str(path / "tensors.safetensors"))
    except Exception as exc:  # noqa: BLE001 - safetensors raises its own error type for torn files
        raise DrivelabError(f"checkpoint file {path / 'tensors.safetensors'} is unreadable: "
                            f"{str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__}") from None
    written_by = str(state.get("drivelab_version", "0.1"))
    if written_by.split(".")[0] != __version__.split(".")[0]:
        raise DrivelabError(f"checkpoint {path} was written by drivelab {written_by}; this is drivelab {__version__}, "
                            "whose checkpoints differ: evaluate it with that version")
    return Checkpoint(path=path, tensors=tensors, state=state)


def load_checkpoint(path: str | Path) -> Checkpoint:
    """A checkpoint directory, or a run's newest intact checkpoint: an unreadable newer one is
    skipped with a warning on stderr (a run killed while writing, a damaged disk)."""
    resolved = resolve_checkpoint(path)
    if resolved.parent.name != "checkpoints" or resolved.name == "best" or resolved == Path(path):
        return read_checkpoint(resolved)
    candidates = list_checkpoints(resolved.parent.parent)[::-1]
    first_error = None
    for candidate in candidates:
        try:
            checkpoint = read_checkpoint(candidate)
        except DrivelabError as exc:
            first_error = first_error or exc
            continue
        if first_error is not None:
            print(f"drivelab: warning: {first_error}; using the newest intact checkpoint, {candidate}", file=sys.stderr)
        return checkpoint
    raise first_error or DrivelabError(f"no checkpoint found in {path}")


def restore(ckpt: Checkpoint, modules: dict[str, nn.Module],
            optimizers: dict[str, torch.optim.Optimizer] | None = None, rng: bool = True) -> None:
    """Load module weights, optimiser states and the torch RNG from a checkpoint."""
    for name, module in modules.items():
        prefix = f"module/{name}/"
        weights = {k[len(prefix):]: v for k, v in ckpt.tensors.items() if k.startswith(prefix)}
        try:
            module.load_state_dict(weights)
        except RuntimeError as exc:
            first = str(exc).strip().splitlines()[0]
            raise DrivelabError(f"checkpoint {ckpt.path} does not fit the '{name}' network: {first}") from None
    for name, optimizer in (optimizers or {}).items():
        meta = (ckpt.state.get("optimizers") or {}).get(name)
        stored = sum(key.startswith(f"optim/{name}/") for key in ckpt.tensors)
        if meta is None or stored != meta.get("tensors", stored):
            raise DrivelabError(f"checkpoint {ckpt.path} lacks the '{name}' optimiser state needed to resume")
        optimizer_from_flat(name, optimizer, ckpt.tensors, meta)
    if rng:
        torch.set_rng_state(ckpt.tensors["rng/torch"])
