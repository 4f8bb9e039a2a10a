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

from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from drivelab.algos import a2c, ddpg, grpo, ppo, reinforce, sac, td3


@dataclass(frozen=True)
class AlgoSpec:
    name: str
    params: type
    build_policy: Callable[..., Any]
    train: Callable[..., None]
    summary: str


def _spec(name: str, module: ModuleType) -> AlgoSpec:
    return AlgoSpec(name, module.Params, module.build_policy, module.train, (module.__doc__ or "").strip().splitlines()[0])


ALGORITHMS: dict[str, AlgoSpec] = {
    name: _spec(name, module)
    for name, module in (("reinforce", reinforce), ("a2c", a2c), ("ppo", ppo), ("grpo", grpo),
                         ("ddpg", ddpg), ("td3", td3), ("sac", sac))
}
