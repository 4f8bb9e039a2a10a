"""Gymnasium ids that drivelab registers on import.

MetaDrive 0.4.2 no longer registers its ``MetaDrive-*`` / ``SafeMetaDrive-*`` Gymnasium ids, which
older MetaDrive code calls ``gym.make`` with. drivelab registers them again with their historical
meaning (scenario = map + traffic, selected by an integer seed):

==========================  ==========  =============  ===================================
id                          start_seed  num_scenarios  use
==========================  ==========  =============  ===================================
MetaDrive-validation-v0     0           1000           evaluation (disjoint from training)
MetaDrive-10env-v0          1000        10             small training set
MetaDrive-100envs-v0        1000        100            training set
MetaDrive-1000envs-v0       1000        1000           large training set
==========================  ==========  =============  ===================================

``SafeMetaDrive-*`` are the same splits of MetaDrive's safety task (more traffic accidents,
crashes do not end the episode, a cost signal in ``info["cost"]``).

Driving tasks (defaults for learning a skill, trainable by every algorithm that fits the action
space):

* ``drivelab/MetaDriveLaneFollow-v0``: empty MetaDrive roads (100 scenarios from seed 1000), state
  observations, the cross-track-error reward (:func:`drivelab.envs.rewards.cte_reward`) paid per
  unit of route progress; ``target_speed=8.0`` (a speed controller) or ``fixed_throttle=0.3``
  give steering-only control.
* ``drivelab/MetaDriveTopDown-v0``: MetaDrive with uint8 (84, 84, 5) bird's-eye observations for
  CNN agents (no 3D assets needed).
* ``drivelab/DuckietownLaneFollow-v0``: Duckietown camera lane following, an optional extra
  (``make duckietown``).

Multi-agent scenes (:mod:`drivelab.envs.multiagent`): ``MultiAgentIntersection-v0``,
``MultiAgentRoundabout-v0``, ``MultiAgentTollgate-v0``, ``MultiAgentBottleneck-v0``,
``MultiAgentParkingLot-v0`` and ``MultiAgentPGMap-v0``, as Gymnasium envs of K agent slots
(:class:`~drivelab.envs.multiagent.AgentSlots`) that the multi-agent trainers step.
"""

from __future__ import annotations

import importlib
import os
import sys

import gymnasium as gym

from drivelab.errors import DrivelabError

METADRIVE_ENTRY_POINT = "drivelab.envs.metadrive:MetaDriveGym"
LANE_FOLLOW_ENTRY_POINT = "drivelab.envs.tasks:lane_follow"
DUCKIETOWN_ENTRY_POINT = "drivelab.envs.duckietown:DuckietownLaneFollow"
MULTIAGENT_ENTRY_POINT = "drivelab.envs.multiagent:AgentSlots"
# drivelab id -> MetaDrive multi-agent scene (drivelab.envs.multiagent.SCENES)
MULTIAGENT_SCENES = {f"MultiAgent{scene}-v0": scene
                     for scene in ("Intersection", "Roundabout", "Tollgate", "Bottleneck", "ParkingLot", "PGMap")}

# (id suffix, start_seed, num_scenarios)
_METADRIVE_SPLITS = (
    ("validation-v0", 0, 1000),
    ("10env-v0", 1000, 10),
    ("100envs-v0", 1000, 100),
    ("1000envs-v0", 1000, 1000),
)


def metadrive_ids() -> list[str]:
    """Every MetaDrive id that drivelab registers."""
    return [f"{prefix}-{suffix}" for prefix in ("MetaDrive", "SafeMetaDrive") for suffix, _, _ in _METADRIVE_SPLITS]


def is_multiagent(env_id: str) -> bool:
    """Whether ``env_id`` is one of the multi-agent scenes (an env of agent slots)."""
    register_envs()
    try:
        return gym.spec(registered_id(env_id)).entry_point == MULTIAGENT_ENTRY_POINT
    except gym.error.Error:
        return False


def is_known(env_id: str) -> bool:
    """Whether ``env_id`` names a registered env (after importing its module, for "module:EnvId")."""
    register_envs()
    try:
        return registered_id(env_id) in gym.registry
    except DrivelabError:
        return False


def registered_id(env_id: str) -> str:
    """The id under which ``env_id`` is registered.

    Gymnasium's ``"module:EnvId"`` form names a module whose import registers ``EnvId`` (as
    ``gym.make`` does, this imports it first); ``"module:EnvClass"`` names an env class (or a
    function that returns an env) in that module, which is registered here as
    ``"module.EnvClass"``. Envs from outside drivelab thus need no entry in drivelab; the module
    is looked up on ``sys.path`` and, failing that, in the current directory. Other ids are
    returned as they are."""
    module, colon, name = env_id.rpartition(":")
    if not colon:
        return env_id
    try:
        imported = _import(module)
    except Exception as exc:  # any failure, reported in one line (ModuleNotFoundError, or the module's own)
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DrivelabError(f"env id '{env_id}': could not import module '{module}' ({detail})") from None
    if name in gym.registry:
        return name
    entry = getattr(imported, name, None)
    if entry is None or not callable(entry):
        return name  # not registered by the module: the caller says so, with close matches
    own_id = f"{module}.{name}"
    if own_id not in gym.registry:
        gym.register(id=own_id, entry_point=f"{module}:{name}")
    return own_id


def import_attribute(reference: str, what: str):
    """``"module:name"`` -> that object of that module (found as an env module is), or one line
    that says why not; ``what`` names the config field for that line."""
    module, colon, name = reference.rpartition(":")
    if not colon or not module or not name:
        raise DrivelabError(f"{what}: expected 'module:name', got {reference!r}")
    try:
        imported = _import(module)
    except Exception as exc:  # any failure, reported in one line
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DrivelabError(f"{what}: could not import module '{module}' ({detail})") from None
    if not hasattr(imported, name):
        raise DrivelabError(f"{what}: module '{module}' has no '{name}'")
    return getattr(imported, name)


def _import(module: str):
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        # A console script's sys.path lacks the current directory (python -m has it); spawned
        # env workers inherit this process's sys.path, so they find the module too.
        if exc.name != module.split(".")[0] or os.getcwd() in sys.path:
            raise
        sys.path.append(os.getcwd())
        return importlib.import_module(module)


def needs_own_process(env_id: str) -> bool:
    """True for simulators that allow one instance per process (MetaDrive's engine is a singleton),
    which must therefore always run in worker subprocesses, even when there is only one."""
    try:
        entry_point = gym.spec(registered_id(env_id)).entry_point
    except gym.error.Error:
        return False
    return isinstance(entry_point, str) and (entry_point in (METADRIVE_ENTRY_POINT, LANE_FOLLOW_ENTRY_POINT,
                                                             MULTIAGENT_ENTRY_POINT)
                                             or entry_point.startswith("metadrive"))


TASKS = {
    "drivelab/MetaDriveLaneFollow-v0": (LANE_FOLLOW_ENTRY_POINT, {}),
    "drivelab/MetaDriveTopDown-v0": (METADRIVE_ENTRY_POINT,
                                     {"observation": "topdown", "start_seed": 1000, "num_scenarios": 100}),
    "drivelab/DuckietownLaneFollow-v0": (DUCKIETOWN_ENTRY_POINT, {}),
}


def register_envs() -> None:
    """Register drivelab's ids with Gymnasium. Idempotent; the simulators are imported lazily."""
    for env_id, (entry_point, kwargs) in TASKS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, kwargs=kwargs)
    for prefix, safe in (("MetaDrive", False), ("SafeMetaDrive", True)):
        for suffix, start_seed, num_scenarios in _METADRIVE_SPLITS:
            env_id = f"{prefix}-{suffix}"
            if env_id in gym.registry:
                continue
            gym.register(
                id=env_id,
                entry_point=METADRIVE_ENTRY_POINT,
                kwargs={"start_seed": start_seed, "num_scenarios": num_scenarios, "safe": safe},
            )
    for env_id, scene in MULTIAGENT_SCENES.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=MULTIAGENT_ENTRY_POINT, kwargs={"scene": scene})
