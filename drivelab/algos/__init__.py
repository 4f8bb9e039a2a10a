"""The algorithm registry: name -> hyperparameter dataclass, policy builder and training loop.

Each algorithm lives in one readable file, ``drivelab/algos/<name>.py``, exposing:

* ``Params``: a dataclass of its hyperparameters (the YAML section named after it);
* ``build_policy(cfg, obs_space, act_space) -> nn.Module`` with ``act(obs, deterministic)`` and
  ``to_env(action)``, which evaluation uses to load a checkpoint;
* ``update(...)``: one update on a batch, a module-level function that a test can call;
* ``train(cfg, run)``: the loop, top to bottom: collect, compute targets, update, then
  ``run.end_iteration`` (log, evaluate, checkpoint).

The registry sits above everything it lists: :mod:`drivelab.api` and the CLI hand it down;
nothing below the algorithms imports it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from types import ModuleType
from typing import Any


@dataclass(frozen=True)
class AlgoSpec:
    name: str
    params: type
    build_policy: Callable[..., Any]
    train: Callable[..., None]
    summary: str


def _spec(name: str, module: ModuleType) -> AlgoSpec:
    return AlgoSpec(name, module.Params, module.build_policy, module.train, (module.__doc__ or "").strip().splitlines()[0])


class Registry(Mapping[str, AlgoSpec]):
    """name -> :class:`AlgoSpec`, a read-only dict that imports ``drivelab/algos/<name>.py`` the
    first time that entry is read. Its names (iterating, ``in``, ``len``) need no import, so
    ``drivelab --help`` and ``drivelab train --help`` list the algorithms without loading torch."""

    def __init__(self, names: tuple[str, ...]):
        self._names = names
        self._specs: dict[str, AlgoSpec] = {}

    def __getitem__(self, name: str) -> AlgoSpec:
        if name not in self._names:
            raise KeyError(name)
        if name not in self._specs:  # first use: import the algorithm's module (and torch with it)
            self._specs[name] = _spec(name, importlib.import_module(f"drivelab.algos.{name}"))
        return self._specs[name]

    def __contains__(self, name: object) -> bool:  # Mapping's default would import the module
        return name in self._names

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


# The algorithms, in the order that help texts and tables list them.
ALGORITHMS: Registry = Registry((
    "reinforce", "a2c", "ppo", "grpo", "ddpg", "td3", "sac",
    # constrained: maximise the return while the mean episode cost stays under a limit
    "ppo_lag", "sac_lag",
    # multi-agent: one policy shared by every car of a MetaDrive multi-agent scene
    "ippo", "mappo",
))
