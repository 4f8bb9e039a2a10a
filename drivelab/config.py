"""Typed run configuration: dataclasses, filled from defaults <- YAML file <- overrides (the
CLI's dotted flags or the Python API's keywords, both merged by :func:`merge_overrides`).

A config file looks like the one saved in every run directory (``config.yaml``)::

    algo: reinforce
    steps: 200000
    seed: 0
    env: {id: MetaDrive-10env-v0, num_envs: 2, action_grid: 3x3, kwargs: {traffic_density: 0.1}}
    reinforce: {lr: 0.003, gamma: 0.99}      # the section named after `algo`

Unknown or ill-typed fields are reported as one-line :class:`DrivelabError` naming the field.

This module knows nothing of the algorithms: :func:`parse_config` is handed the registry
(name -> hyperparameter dataclass) by its caller (:mod:`drivelab.api`), so no module below the
algorithms imports them.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import os
import re
import sys
from collections.abc import Hashable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import dacite
import yaml

from drivelab.envs.config import BACKENDS, EnvConfig  # noqa: F401  (re-exported: the env section)
from drivelab.envs.costs import refuse_cost_to_reward
from drivelab.envs.registration import is_known, is_multiagent
from drivelab.errors import DrivelabError


@dataclass
class EvalConfig:
    """Periodic deterministic evaluation during training, in its own env (subprocess for MetaDrive)."""
    every: int = 0                 # env steps between evaluations (0: never, and no checkpoints/best)
    episodes: int = 10             # deterministic episodes per evaluation
    # Also evaluate when the run ends (steps or max_minutes reached) between two evaluations, so
    # that checkpoints/best weighs the final policy too (with eval.every > 0).
    final: bool = False
    # Another env id for held-out evaluation (e.g. MetaDrive-validation-v0); None: the training
    # env. With another id the training env's kwargs are dropped (they may redefine the
    # scenarios) and `kwargs` is used instead; wrappers (action grid, filters, reward) and the
    # kwargs that shape the observation (MetaDrive's vehicle_config) are kept.
    env_id: str | None = None
    kwargs: dict[str, Any] = field(default_factory=dict)   # the env kwargs with env_id (replacing the training env's)
    seed: int = 10_000             # episode k is reset with seed + k
    num_envs: int = 1              # envs that play the evaluation episodes in parallel
    # The checkpoint with the best value of this eval/* metric is kept as checkpoints/best.
    best_metric: str = "return_mean"
    # Keep as best the evaluations with a mean episode cost (eval/cost) <= this first, then by
    # best_metric (for an env with a cost: SafeMetaDrive, env.cost). None: the cost is ignored.
    cost_limit: float | None = None
    # On a new best, film one episode: RUN/videos/step_<N>.mp4 (needs the env's rgb_array render).
    video: bool = True
    # local: the trainer pauses while it evaluates; ray: a Ray actor evaluates a copy of the
    # policy while training goes on (results are logged at the step they were taken).
    backend: str = "local"


@dataclass
class TrackConfig:
    mlflow: bool = False              # also track with MLflow
    # None: the store shared by the runs beside this one, sqlite:///<run dir's parent>/mlflow.db
    # (runs/mlflow.db for runs/NAME), with artifacts in <run dir's parent>/mlartifacts.
    mlflow_uri: str | None = None
    experiment: str = "drivelab"      # the MLflow experiment
    # Weights & Biases (pip install 'drivelab[wandb]'): files in RUN/wandb. Without an API key
    # (`wandb login`, WANDB_API_KEY) it logs offline; `wandb sync RUN/wandb/offline-run-*` uploads later.
    wandb: bool = False
    wandb_project: str = "drivelab"   # the W&B project
    wandb_entity: str | None = None   # the W&B team or user (None: your default)
    wandb_mode: str | None = None     # online | offline | disabled; None: WANDB_MODE, else online with a key


@dataclass
class TrainConfig:
    algo: str = "reinforce"           # reinforce, a2c, ppo, grpo, ddpg, td3, sac, ppo_lag or sac_lag
    env: EnvConfig = field(default_factory=EnvConfig)
    steps: int = 100_000              # env steps to train for (all envs together)
    # Stop (with a final checkpoint) after this much training time, even if `steps` is not reached.
    max_minutes: float | None = None
    seed: int = 0                     # seeds torch, numpy and the envs' resets
    run_dir: str | None = None        # None: runs/<algo>-<env>-s<seed>-<time>
    # Intra-op threads for torch. 1 is fastest when env subprocesses share a few cores.
    torch_threads: int = 1
    # Intra-op threads inside gradient updates (None: torch_threads). The env workers wait
    # while the trainer updates, so the update may use every core this run has to itself
    # (docs/results.md, Throughput of PPO on MetaDrive). Other float results, so another random
    # stream than with None; keep None when other jobs share the cores.
    update_threads: int | None = None
    device: str = "cpu"               # cpu, cuda[:N], or auto (cuda when torch sees one)
    checkpoint_every: int = 50_000    # env steps between checkpoints (also one at the end)
    keep_checkpoints: int = 3         # how many step_<N> checkpoints are kept (checkpoints/best besides)
    # Episodes in the recent-return window (progress bar and logged means).
    stats_window: int = 20
    # Env steps between metric logs (the last iteration's or the means since the last log).
    log_every: int = 1000
    eval: EvalConfig = field(default_factory=EvalConfig)
    # The Ray cluster for env.backend / eval.backend ray: None starts a local Ray instance (or
    # joins $RAY_ADDRESS), "auto" joins the cluster on this machine, "ray://host:10001" a remote one.
    ray_address: str | None = None
    track: TrackConfig = field(default_factory=TrackConfig)
    # Hyperparameters of `algo`: an instance of that algorithm's dataclass (its section in YAML).
    algo_params: Any = None


def _coerce_float(value: Any) -> Any:
    # YAML and CLI write 1 or 1e3 for floats; accept ints (not bools) where a float is expected.
    return float(value) if isinstance(value, int) and not isinstance(value, bool) else value


_DACITE = dacite.Config(strict=True, type_hooks={float: _coerce_float})


def _from_dict(cls: type, data: dict, where: str) -> Any:
    if not isinstance(data, dict):
        raise DrivelabError(f"{where}: expected a mapping, got {type(data).__name__}")
    try:
        return dacite.from_dict(cls, data, config=_DACITE)
    except dacite.UnexpectedDataError as exc:
        names = unknown_fields(data, cls) or sorted(exc.keys)  # dotted: env.num_env, not num_env
        meant = closest_field(names[0], cls)
        hint = f" (did you mean {meant}?)" if meant else ""
        raise DrivelabError(f"{where}: unknown field(s) {', '.join(names)}{hint}") from None
    except dacite.WrongTypeError as exc:
        raise DrivelabError(
            f"{where}: field '{exc.field_path}' expects {_type_name(exc.field_type)}, got {exc.value!r}"
        ) from None
    except dacite.DaciteError as exc:
        raise DrivelabError(f"{where}: {exc}") from None


def _section(f: dataclasses.Field) -> type | None:
    """The dataclass of a field that holds a nested section (``env``, ``eval``, ``track``), else None."""
    kind = f.default_factory
    return kind if isinstance(kind, type) and dataclasses.is_dataclass(kind) else None


def field_paths(cls: type, prefix: str = "") -> list[str]:
    """The dotted paths of the fields of a config dataclass and of the sections nested in it, in
    the order they are declared: ``algo``, ``env``, ``env.id``, ``env.num_envs``, ..."""
    paths = []
    for f in dataclasses.fields(cls):
        paths.append(prefix + f.name)
        if _section(f) is not None:
            paths += field_paths(_section(f), f"{prefix}{f.name}.")
    return paths


def is_field(path: str, cls: type) -> bool:
    """Whether a dotted path names a field of ``cls``: a section's field (``env.num_envs``), or a
    key inside a field that holds a free-form mapping (``env.kwargs.traffic_density``)."""
    name, _, rest = path.partition(".")
    f = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    if f is None:
        return False
    return not rest or _section(f) is None or is_field(rest, _section(f))


def unknown_fields(data: Mapping, cls: type, prefix: str = "") -> list[str]:
    """The dotted paths of the keys in nested config data that name no field of ``cls``."""
    sections = {f.name: _section(f) for f in dataclasses.fields(cls)}
    unknown = []
    for key, value in data.items():
        if key not in sections:
            unknown.append(f"{prefix}{key}")
        elif sections[key] is not None and isinstance(value, Mapping):  # a section: its keys too
            unknown += unknown_fields(value, sections[key], f"{prefix}{key}.")
    return unknown


def closest_field(path: str, cls: type) -> str | None:
    """The field that a mistyped dotted ``path`` most likely meant, as a dotted path: the closest
    name in the same section (``env.num_env`` -> ``env.num_envs``), else the same or a close name
    in any section (``num_envs`` -> ``env.num_envs``, the first section that has one); None if
    nothing is close."""
    paths = field_paths(cls)
    section, _, name = path.rpartition(".")
    siblings = [p.rpartition(".")[2] for p in paths if p.rpartition(".")[0] == section]
    close = difflib.get_close_matches(name, siblings, n=1)
    if close:
        return f"{section}.{close[0]}" if section else close[0]
    leaves = [p.rpartition(".")[2] for p in paths]
    close = difflib.get_close_matches(name, leaves, n=1)
    return paths[leaves.index(close[0])] if close else None


def field_docs(cls: type) -> list[tuple[str, str, Any, str]]:
    """(name, type, default, meaning) of each field of a config dataclass, the meaning taken
    from the comment beside or above the field in its source (base classes included). A comment
    above a group of fields (no blank line between them) is the meaning of each field in the group
    that has no comment of its own."""
    import inspect

    comments: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        above: list[str] = []   # the comment lines read since the last field
        group = ""              # the comment above the fields just read, for the next ones
        for line in inspect.getsource(klass).splitlines():
            stripped = line.strip()
            match = re.match(r"(\w+)\s*:\s*[^=]+(?:=.*?)?(?:#\s*(.*))?$", stripped)
            if stripped.startswith("#"):
                above.append(stripped.lstrip("# "))
            elif match and not stripped.startswith(("def ", "class ", "return")):
                group = " ".join(above) or group
                text = match.group(2) or group
                if text or match.group(1) not in comments:
                    comments[match.group(1)] = text
                above = []
            else:
                above, group = [], ""
    rows = []
    for f in dataclasses.fields(cls):
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        rows.append((f.name, _type_name(f.type) if not isinstance(f.type, str) else f.type, default, comments.get(f.name, "")))
    return rows


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def parse_value(text: str) -> Any:
    """A command-line value as YAML reads it (``3x3`` stays text, ``[64, 64]`` is a list, ``null``
    is None), except that numbers like ``1e-3`` are numbers (YAML 1.1 reads them as text)."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    if isinstance(value, str):
        try:
            return float(value) if any(c in value for c in ".eE") else int(value)
        except ValueError:
            return value
    return value


def set_dotted(data: dict, dotted: str, value: Any) -> None:
    """data["a"]["b"] = value for dotted == "a.b", creating intermediate mappings (a mapping value
    merges into the section there, as in :func:`merge_overrides`)."""
    merge_overrides(data, {dotted: value})


def merge_overrides(data: dict, overrides: Mapping[str, Any]) -> dict:
    """Merge ``overrides`` into the config data ``data`` (in place; returned too), deeply.

    A key is a field or a dotted path to one (``"env.kwargs.traffic_density"``); a mapping merges
    into the section at its place and keeps that section's other fields, at every depth; any
    other value (a number, a list, None) replaces. So ``{"env": {"kwargs": {"a": 1}}}`` (the
    Python API's keyword sections) and ``{"env.kwargs.a": 1}`` (the CLI's ``--env.kwargs.a 1``)
    mean the same: the config file's other ``env.kwargs`` stay. Both faces merge with this.
    """
    for dotted, value in overrides.items():
        *sections, name = dotted.split(".")
        node = data
        for key in sections:
            child = node.get(key)
            if child is None:
                child = node[key] = {}
            if not isinstance(child, dict):
                raise DrivelabError(f"config field '{dotted}': '{key}' is not a section")
            node = child
        _merge_field(node, name, value)
    return data


def _merge_field(section: dict, name: str, value: Any) -> None:
    """section[name] = value, merging a mapping into the mapping already there (copies, so that
    the caller's mappings and lists are never shared with the config)."""
    current = section.get(name)
    if isinstance(value, Mapping) and isinstance(current, dict):
        for key, item in value.items():
            _merge_field(current, key, item)
    else:
        section[name] = copy.deepcopy(dict(value) if isinstance(value, Mapping) else value)


SHIPPED_CONFIGS = Path(__file__).resolve().parent / "configs"


def shipped_configs() -> dict[str, Path]:
    """The ready-made configs installed with drivelab (``drivelab/configs``, also ``configs/`` in
    the repository), by name: ``ppo_metadrive_drive`` -> its YAML file."""
    return {p.stem: p for p in sorted(SHIPPED_CONFIGS.glob("*.yaml"))}


def resolve_config_file(name: str | Path) -> Path:
    """A config file path, or the name of a shipped config (``ppo_lunarlander``)."""
    path = Path(name)
    if path.is_file():
        return path
    shipped = shipped_configs()
    if str(name) in shipped or path.stem in shipped and path.suffix in ("", ".yaml") and len(path.parts) == 1:
        return shipped[path.stem]
    close = difflib.get_close_matches(path.stem, list(shipped), n=1)
    hint = f" (did you mean the shipped config '{close[0]}'?)" if close else "; `drivelab configs` lists the shipped ones"
    raise DrivelabError(f"config file not found: {name}{hint}")


class UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key written twice in one mapping. Plain PyYAML keeps the
    last value without a word, so a file with ``lr: 0.1`` and, further down, ``lr: 0.001`` would
    train with whichever came last."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base` merges a mapping: overriding it is the point
                continue
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, Hashable):
                continue  # a list as a key: SafeLoader refuses it itself below
            if key in seen:  # the line of the second one, in read_yaml's message
                raise yaml.constructor.ConstructorError(None, None, f"key '{key}' appears twice in one mapping; keep one",
                                                        key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path, allow_empty: bool = False) -> dict:
    """The mapping of fields in a YAML file (a config, a reward config, a run's ``config.yaml``).

    An empty file (nothing, or comments only) is refused, since reading it as "no fields" would
    quietly train the defaults; ``allow_empty`` returns ``{}`` instead, for a caller with a better
    message of its own. A key written twice in one mapping is refused (:class:`UniqueKeyLoader`)."""
    path = Path(path)
    if not path.is_file():
        raise DrivelabError(f"config file not found: {path}")
    try:
        data = yaml.load(path.read_text(), Loader=UniqueKeyLoader)
    except (UnicodeDecodeError, ValueError) as exc:
        raise DrivelabError(f"config file {path} is not a text YAML file ({type(exc).__name__})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark else ""
        raise DrivelabError(f"config file {path}{where}: invalid YAML ({getattr(exc, 'problem', exc)})") from None
    if data is None:  # no document at all: an empty file, or comments only
        if allow_empty:
            return {}
        raise DrivelabError(f"config file {path} is empty: it sets no field (to train the defaults, leave out --config)")
    if not isinstance(data, dict):
        raise DrivelabError(f"config file {path}: expected a mapping of fields at the top level")
    return data


# Hyperparameters that drivelab no longer has, with the value that meant "off": configs saved in
# run directories and checkpoints by earlier versions still load when they left them off.
RETIRED_FIELDS: dict[str, dict[str, Any]] = {"ppo": {"overlap_update": False}}


def _without_retired(algo: str, params: Any, where: str) -> Any:
    if not isinstance(params, dict):
        return params
    retired = RETIRED_FIELDS.get(algo, {})
    for name in set(params) & set(retired):
        if params[name] != retired[name]:
            raise DrivelabError(f"{where}: field '{algo}.{name}' was removed from drivelab; remove it from the config")
    return {name: value for name, value in params.items() if name not in retired}


def parse_config(data: dict, algo_params: Mapping[str, type], where: str = "config") -> TrainConfig:
    """Validate a nested dict (YAML file + overrides) into a TrainConfig.

    ``algo_params`` maps each algorithm's name to its hyperparameter dataclass (the registry's
    view, passed down by the caller); the hyperparameters come from the section named after
    ``algo``.
    """
    data = dict(data)
    env = data.get("env")
    if isinstance(env, dict) and "vectorization" in env:  # backend's old name, in saved configs (run dirs, --resume)
        data["env"] = {("backend" if k == "vectorization" else k): v for k, v in env.items()}
    algo = data.get("algo", TrainConfig.algo)
    if algo not in algo_params:
        close = difflib.get_close_matches(str(algo), list(algo_params), n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise DrivelabError(f"unknown algorithm '{algo}'{hint}; available: {', '.join(algo_params)}")
    params = _without_retired(algo, data.pop(algo, None) or {}, where)
    stray = [name for name in algo_params if name in data]
    if stray:
        raise DrivelabError(f"{where}: section '{stray[0]}' does not apply to algo '{algo}'")
    if "sweep" in data:
        raise DrivelabError(f"{where}: this config holds a sweep; run it with `drivelab sweep`")
    if "algo_params" in data:
        raise DrivelabError(f"{where}: unknown field(s) algo_params (use a section named '{algo}')")
    cfg = _from_dict(TrainConfig, data, where)
    cfg.algo_params = _from_dict(algo_params[algo], params, f"{where} section '{algo}'")
    _validate(cfg)
    _fit_heat_up(cfg)
    return cfg


# Rounding ``steps`` up to one iteration may lengthen a short run several times over (a smoke
# test of steps=64 becomes PPO's default rollout of 4 envs x 128 steps, with a note); an iteration
# more than this many times ``steps`` is a mistake (--num-envs 10000 turning --steps 500 into
# 1,280,000 env steps) and is refused.
MAX_ITERATION_OVER_STEPS = 10


def fit_steps(cfg: TrainConfig) -> None:
    """Round ``steps`` up to the algorithm's iteration (PPO and A2C: a rollout of ``num_steps``
    in each env; DDPG, TD3 and SAC: one step of each env), with one line, so that the run ends
    at the number its config, progress bar and report state; an iteration far beyond ``steps``
    (:data:`MAX_ITERATION_OVER_STEPS`) is refused in one line. REINFORCE and GRPO update on whole
    episodes: their last batch is cut to the steps left, and the run ends with its episodes.
    Only training calls it (a saved config evaluates as it was written)."""
    iteration_steps = getattr(cfg.algo_params, "iteration_steps", None)
    if iteration_steps is None or cfg.steps == 0:
        return
    size = iteration_steps(cfg.env.num_envs)
    if size > MAX_ITERATION_OVER_STEPS * cfg.steps:
        rollout = f" x {cfg.algo}.num_steps" if hasattr(cfg.algo_params, "num_steps") else ""  # PPO, A2C
        raise DrivelabError(f"config: one {cfg.algo} iteration collects env.num_envs{rollout} = {size:,} env steps, "
                            f"more than {MAX_ITERATION_OVER_STEPS} times steps ({cfg.steps:,}): "
                            f"lower env.num_envs{rollout.replace(' x ', ' or ')}, or raise steps")
    rounded = -(-cfg.steps // size) * size
    if rounded != cfg.steps:
        # stdout: a note, not a warning (stderr stays for errors and warnings, one line each)
        print(f"drivelab: note: steps {cfg.steps} -> {rounded}, a whole number of {cfg.algo} iterations "
              f"of {size} env steps")
        cfg.steps = rounded


def _fit_heat_up(cfg: TrainConfig) -> None:
    """An off-policy run shorter than its random-action heat-up (``learning_starts``, 5000 by
    default) would end without one gradient step and look like a run that cannot learn: its
    heat-up becomes a tenth of the run, and one line says so (the saved config holds the value)."""
    heat_up = getattr(cfg.algo_params, "learning_starts", None)
    if heat_up is None or heat_up < cfg.steps or cfg.steps == 0:
        return
    cfg.algo_params.learning_starts = max(1, cfg.steps // 10)
    print(f"drivelab: warning: {cfg.algo}.learning_starts ({heat_up}) is not below steps ({cfg.steps}), so the run "
          f"would never update: its heat-up is {cfg.algo_params.learning_starts} steps instead "
          f"(set --{cfg.algo}.learning_starts to choose)", file=sys.stderr)


def resolve_device(cfg: TrainConfig) -> None:
    """The one place that decides where a run trains (its tensors all follow ``cfg.device``):
    ``auto`` becomes cuda when torch sees one, else cpu; a CUDA device this machine lacks is
    refused in one line. Only training asks: a config saved by a GPU run still parses here, so
    its checkpoints load, evaluate and export on a CPU-only machine (safetensors hold no device)."""
    if cfg.device == "cpu":
        return
    import torch

    if cfg.device == "auto":
        cfg.device = "cuda" if torch.cuda.is_available() else "cpu"
    elif not torch.cuda.is_available():
        raise DrivelabError(f"config field 'device' is {cfg.device!r}, but this torch build sees no CUDA device "
                            f"(on a CPU-only machine: --device cpu)")
    elif int(cfg.device.partition(":")[2] or 0) >= torch.cuda.device_count():
        raise DrivelabError(f"config field 'device' is {cfg.device!r}, but this machine has "
                            f"{torch.cuda.device_count()} CUDA device(s)")


def _validate(cfg: TrainConfig) -> None:
    checks = [
        ("seed", 0 <= cfg.seed < 2**63, "must be in [0, 2^63)"),
        ("eval.seed", 0 <= cfg.eval.seed < 2**63, "must be in [0, 2^63)"),
        ("steps", cfg.steps >= 0, "must be >= 0"),
        ("max_minutes", cfg.max_minutes is None or cfg.max_minutes > 0, "must be > 0"),
        ("torch_threads", cfg.torch_threads >= 1, "must be >= 1"),
        ("update_threads", cfg.update_threads is None or cfg.update_threads >= 1, "must be >= 1"),
        (f"{cfg.algo}.act_in_workers", not getattr(cfg.algo_params, "act_in_workers", False)
         or (cfg.env.resolved_backend() == "async" and cfg.env.resolved_step_groups() == 1),
         "needs subprocess envs (env.backend: async, or auto for a simulator such as MetaDrive) that step "
         "together (env.step_groups unset or 1)"),
        ("checkpoint_every", cfg.checkpoint_every >= 1, "must be >= 1"),
        ("keep_checkpoints", cfg.keep_checkpoints >= 1, "must be >= 1"),
        ("stats_window", cfg.stats_window >= 1, "must be >= 1"),
        ("log_every", cfg.log_every >= 1, "must be >= 1"),
        ("eval.every", cfg.eval.every >= 0, "must be >= 0"),
        ("eval.episodes", cfg.eval.episodes >= 1, "must be >= 1"),
        ("eval.num_envs", cfg.eval.num_envs >= 1, "must be >= 1"),
        ("eval.backend", cfg.eval.backend in ("local", "ray"), "must be local or ray"),
        ("eval.cost_limit", cfg.eval.cost_limit is None or 0 <= cfg.eval.cost_limit < math.inf,
         "must be a finite number >= 0"),
        ("track.wandb_mode", cfg.track.wandb_mode in (None, "online", "offline", "disabled"),
         "must be online, offline or disabled"),
        ("device", cfg.device in ("cpu", "auto") or re.fullmatch(r"cuda(:\d+)?", cfg.device) is not None,
         "must be cpu, cuda[:N] or auto"),
    ]
    for name, ok, message in checks:
        if not ok:
            raise DrivelabError(f"config field '{name}' {message}")
    if cfg.run_dir is not None:
        if not str(cfg.run_dir).strip():
            raise DrivelabError("config field 'run_dir' is empty: name a directory for the run")
        _check_writable(Path(cfg.run_dir))
    _check_hyperparameters(cfg.algo, cfg.algo_params)
    cfg.env.validate()
    _check_agents(cfg)
    refuse_cost_to_reward(cfg.eval.kwargs, "config field 'eval.kwargs'")
    if hasattr(cfg.algo_params, "validate"):
        cfg.algo_params.validate()
    if hasattr(cfg.algo_params, "validate_env"):  # constraints between the algorithm and the env
        cfg.algo_params.validate_env(cfg.env)


def _check_agents(cfg: TrainConfig) -> None:
    """Multi-agent scenes train with the multi-agent algorithms (``Params.multiagent``), and only they do."""
    if not is_known(cfg.env.id):
        return  # an unknown id is said, with close matches, where the env is built
    scene = is_multiagent(cfg.env.id)
    if scene != getattr(cfg.algo_params, "multiagent", False):
        which = "a multi-agent scene: train it with ippo or mappo" if scene else "a single-agent env"
        raise DrivelabError(f"config field 'algo': {cfg.algo} cannot train on '{cfg.env.id}', {which}")
    if scene and cfg.eval.every:
        raise DrivelabError("config field 'eval.every': multi-agent runs log episode/* over the cars' episodes "
                            "and are evaluated afterwards with `drivelab eval RUN`; set it to 0")


def _check_hyperparameters(algo: str, params: Any) -> None:
    """What holds for every algorithm's hyperparameters: finite numbers, positive learning rates
    and layer widths, discounts in [0, 1]."""
    for f in dataclasses.fields(params):
        value, name = getattr(params, f.name), f"{algo}.{f.name}"
        if isinstance(value, float) and not math.isfinite(value):
            raise DrivelabError(f"config field '{name}' must be a finite number, got {value}")
        if (f.name == "lr" or f.name.endswith("_lr")) and not isinstance(value, bool) and value <= 0:
            raise DrivelabError(f"config field '{name}' (a learning rate) must be > 0, got {value}")
        if f.name == "hidden" and (not value or any(width < 1 for width in value)):
            raise DrivelabError(f"config field '{name}' must list layer widths >= 1, got {value}")
        if f.name in ("gamma", "gae_lambda") and not 0 <= value <= 1:
            raise DrivelabError(f"config field '{name}' must be in [0, 1], got {value}")


def _check_writable(run_dir: Path) -> None:
    """The run directory can be created and written (checked before anything is written)."""
    if run_dir.exists() and not run_dir.is_dir():
        raise DrivelabError(f"config field 'run_dir': {run_dir} exists and is not a directory")
    existing = next((p for p in [run_dir, *run_dir.resolve().parents] if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise DrivelabError(f"config field 'run_dir': {existing} is a file, so {run_dir} cannot be created under it")
    if existing is not None and not os.access(existing, os.W_OK):
        raise DrivelabError(f"config field 'run_dir': {existing} is not writable")


def check_output_path(path: str | Path, what: str, directory: bool = False) -> None:
    """``path`` can be created and written: a file, or with ``directory`` a directory. Checked
    before any work starts, so that an evaluation or an export ends in one line naming ``what``
    (``--video``, ``export --out``) rather than in a traceback once its results are ready. The
    same cases as a run directory's (:func:`_check_writable`): the path is of the other kind, a
    component above it is a file, or the nearest existing directory is not writable."""
    path = Path(path)
    if path.exists() and path.is_dir() != directory:
        kind = "is not a directory" if directory else "is a directory"
        raise DrivelabError(f"{what}: {path} exists and {kind}")
    # the path itself, or the nearest existing directory above it, in which it will be created
    existing = next(p for p in [path, *path.resolve().parents] if p.exists())  # the root always exists
    if existing != path and not existing.is_dir():
        raise DrivelabError(f"{what}: {existing} is a file, so {path} cannot be created under it")
    if not os.access(existing, os.W_OK):
        raise DrivelabError(f"{what}: {existing} is not writable")


def config_to_dict(cfg: TrainConfig) -> dict:
    """The resolved config as plain data, with the hyperparameters under the algorithm's name."""
    data = dataclasses.asdict(dataclasses.replace(cfg, algo_params=None))
    data.pop("algo_params")
    data[cfg.algo] = dataclasses.asdict(cfg.algo_params)
    return data


def save_config(cfg: TrainConfig, path: str | Path) -> None:
    """Write the resolved config atomically (a temporary file, then a rename): a process killed
    meanwhile leaves the previous file or none, never half of one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        f.write(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


# Fields that may change when a run is resumed; anything else would change the experiment that
# the checkpoints continue.
RESUMABLE_FIELDS = ("steps", "max_minutes", "torch_threads", "update_threads", "checkpoint_every", "keep_checkpoints",
                    "stats_window", "log_every", "eval", "device", "track", "ray_address")


def experiment_differences(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[str]:
    """The dotted fields, outside :data:`RESUMABLE_FIELDS` and ``run_dir`` (a run may move), where
    two configs (as plain data, :func:`config_to_dict`) differ: the same experiment when empty."""
    def leaves(data: Any, prefix: str = "") -> dict[str, Any]:
        if not isinstance(data, Mapping) or not data:
            return {prefix[:-1]: data}
        return {k: v for key, value in data.items() for k, v in leaves(value, f"{prefix}{key}.").items()}

    left, right = leaves(a), leaves(b)
    return sorted(key for key in left.keys() | right.keys()
                  if key.split(".")[0] not in (*RESUMABLE_FIELDS, "run_dir") and left.get(key) != right.get(key))
