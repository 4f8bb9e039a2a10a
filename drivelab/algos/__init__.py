"""The algorithm registry: name -> hyperparameter dataclass, policy builder and training loop.

Each algorithm lives in one readable file, ``drivelab/algos/<name>.py``, exposing:

* ``Params``: a dataclass of its hyperparameters (the YAML section named after it);
* ``build_policy(cfg, obs_space, act_space) -> nn.Module`` with ``act(obs, deterministic)`` and
  ``to_env(action)``, which evaluation uses to load a checkpoint;
* ``train(cfg, run)``: the loop, top to bottom.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from types import ModuleType
from typing import Any, Callable

from drivelab.errors import DrivelabError


@dataclass(frozen=True)
class AlgoSpec:
    name: str
    params: type
    build_policy: Callable[..., Any]
    train: Callable[..., None]
    summary: str


def _spec(name: str, module: ModuleType) -> AlgoSpec:
    return AlgoSpec(name, module.Params, module.build_policy, module.train, (module.__doc__ or "").strip().splitlines()[0])


def _load() -> dict[str, AlgoSpec]:
    from drivelab.algos import a2c, ddpg, grpo, ppo, reinforce, sac, td3

    modules = {"reinforce": reinforce, "a2c": a2c, "ppo": ppo, "grpo": grpo, "ddpg": ddpg, "td3": td3, "sac": sac}
    return {name: _spec(name, module) for name, module in modules.items()}


ALGOS: tuple[str, ...] = ("reinforce", "a2c", "ppo", "grpo", "ddpg", "td3", "sac")


def get_algo(name: str) -> AlgoSpec:
    if name not in ALGOS:
        close = difflib.get_close_matches(str(name), ALGOS, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise DrivelabError(f"unknown algorithm '{name}'{hint}; available: {', '.join(ALGOS)}")
    return _load()[name]
