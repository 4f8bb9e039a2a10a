"""drivelab from Python: train, load a trained policy, act, evaluate. ``import drivelab`` gives
``drivelab.train``, ``drivelab.load``, ``drivelab.evaluate`` and ``drivelab.make_env``::

    import drivelab
    result = drivelab.train("ppo", "CartPole-v1", steps=50_000, seed=0, ppo={"lr": 3e-4})
    policy = drivelab.load(result.run_dir)              # a run, a checkpoint, or RUN/best
    action = policy.act(obs)                            # one observation or a batch
    drivelab.evaluate(policy, "CartPole-v1", episodes=10)   # the dict of `drivelab eval --json`

The CLI calls these same functions, and nothing else: how a config is built from a file and
overrides, the rules of resuming a run (:func:`train_config`) and which env the baselines play
(:func:`baseline_env`) are decided here or below, so the Python API and the CLI behave alike.
Loading and evaluating checkpoints and baselines live in :mod:`drivelab.tools.policies`
(re-exported here), where the tools (report, sweep, reward comparison) use them too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import numbers
import os
import shlex
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from drivelab.algos import ALGORITHMS, AlgoSpec
from drivelab.config import (
    RESUMABLE_FIELDS,
    EnvConfig,
    TrainConfig,
    config_to_dict,
    experiment_differences,
    merge_overrides,
    read_yaml,
    resolve_config_file,
)
from drivelab.envs import env_spaces
from drivelab.envs.supervised import error_line
from drivelab.errors import DrivelabError, TrainingCrashed, raise_interrupt
from drivelab.tools.drivers import model_card, shipped_drivers  # noqa: F401  (re-exported: the shipped drivers)
from drivelab.tools.policies import (  # noqa: F401  (re-exported: the API's loading and evaluation)
    TrainedPolicy,
    baseline_env,
    build_config,
    check_fits_env,
    checkpoint_config,
    config_differences,
    evaluate_baseline,
    evaluate_checkpoint,
    evaluation_row,
    load,
    load_policy,
    policy_from_checkpoint,
    with_defaults,
)
from drivelab.training.collection.evaluation import EvalResult, play, run_episodes  # noqa: F401  (EvalResult re-exported)
from drivelab.training.outputs.checkpoint import Checkpoint, checkpoint_step, list_checkpoints, load_checkpoint
from drivelab.training.outputs.plots import last_metrics
from drivelab.training.run import Callback, Run, RunEvent  # noqa: F401  (RunEvent re-exported)
from drivelab.version import __version__


def default_run_dir(cfg: TrainConfig) -> str:
    safe_env = cfg.env.id.replace("/", "_")
    return str(Path("runs") / f"{cfg.algo}-{safe_env}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}")


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """While a run trains: SIGTERM raises :class:`~drivelab.errors.Terminated`, a
    ``KeyboardInterrupt`` like Ctrl-C's, so the run stops with a checkpoint of that moment
    instead of dying with up to ``checkpoint_every`` steps lost; and a SIGINT that the shell
    ignores (background jobs, ``nohup ... &``) is heard again.
    The previous handlers come back afterwards. A SIGTERM handler that the caller installed
    (a cluster launcher's requeue, say) is left alone, and so is everything outside the main
    thread, where Python allows no handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    if previous[signal.SIGTERM] == signal.SIG_DFL:
        signal.signal(signal.SIGTERM, raise_interrupt)
    if previous[signal.SIGINT] == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class TrainResult(NamedTuple):
    run_dir: Path
    metrics: dict[str, float]     # the last logged value of each metric (episode/*, loss/*, eval/*, perf/*)


def train(algo: str | TrainConfig | None = None, env: str | Mapping[str, Any] | Callable[..., gym.Env] | None = None, *,
          steps: int | None = None, seed: int | None = None, num_envs: int | None = None,
          run_dir: str | Path | None = None, config: str | Path | None = None,
          resume: bool | str | os.PathLike | None = False, progress: bool = True, callback: Callback | None = None,
          algorithms: Mapping[str, AlgoSpec] = ALGORITHMS, **overrides: Any) -> TrainResult:
    """Train an agent and return its run directory and final metrics.

    Either a :class:`TrainConfig`, or an algorithm name with an env (an id, or the ``env``
    section as a dict: ``{"id": "MetaDrive-10env-v0", "action_grid": "3x3"}``) and any config
    field as a keyword: sections as dicts (``ppo={"lr": 1e-3}``, ``eval={"every": 10_000}``) or
    top-level fields (``checkpoint_every=5000``). ``config`` is a YAML file (or the name of a
    shipped config) that these override, merged deeply as the CLI's dotted flags are
    (:func:`drivelab.config.merge_overrides`).

    ``resume=True`` continues the run in ``run_dir`` from its latest checkpoint:
    ``train(run_dir=R, resume=True, steps=...)`` reads the run's saved config, and only
    :data:`~drivelab.config.RESUMABLE_FIELDS` may change (as ``drivelab train --resume``).
    ``resume="auto"`` is the command to requeue on a preemptible cluster: it starts the run
    when ``run_dir`` holds none yet and continues it otherwise (``--resume-if-exists``).
    ``resume=RUN_DIR`` (a path) is ``run_dir=RUN_DIR, resume=True``, as ``--resume RUN_DIR``.

    ``callback(event)`` hears every log, evaluation and checkpoint (a :class:`RunEvent`: its
    ``kind``, ``step``, ``metrics`` and checkpoint ``path``); when it returns False the run
    stops cleanly, with a checkpoint at the step reached (early stopping, say, on
    ``event.kind == "eval" and event.metrics["success_rate"] >= 0.8``).

    An unexpected exception inside training leaves the latest checkpoint as it was, writes its
    traceback to ``RUN/error.log`` and is raised as :class:`~drivelab.errors.TrainingCrashed`.
    """
    resume, run_dir = _resume_of_call(resume, run_dir)
    requeue = resume == "auto"
    cfg = _config_of_call(algo, env, steps=steps, seed=seed, num_envs=num_envs, run_dir=run_dir, config=config,
                          resume=resume, requeue=requeue, overrides=overrides, algorithms=algorithms)
    spec = algorithms[cfg.algo]
    if cfg.run_dir is None:
        cfg.run_dir = default_run_dir(cfg)
    if requeue:  # continue what the directory holds, if anything
        resume, finished = _requeue_status(cfg)
        if finished:
            return TrainResult(Path(cfg.run_dir), last_metrics(cfg.run_dir))
    checkpoint = _checkpoint_to_resume(cfg) if resume else None
    _check_run_dir_is_free(cfg, checkpoint)
    _check_env_and_network(cfg, spec)
    _connect_ray_if_used(cfg)
    run = Run(cfg, resume_from=checkpoint, progress=progress, callback=callback)
    _train_keeping_evidence(spec, cfg, run)
    metrics = last_metrics(run.dir)
    if not any(name.startswith("loss/") for name in metrics):
        print(f"drivelab: warning: the run ended at step {run.step} without a logged update (no loss/* metric): "
              "it has not learned; train for more steps", file=sys.stderr)
    return TrainResult(run.dir, metrics)


def _resume_of_call(resume: bool | str | os.PathLike | None,
                    run_dir: str | Path | None) -> tuple[bool | str, str | Path | None]:
    """:func:`train`'s ``resume`` as False, True or ``"auto"``, with the run directory it names,
    mirroring the CLI's ``--resume RUN_DIR`` and ``--resume-if-exists``: anything else (``"maybe"``)
    is one line rather than a truthy value that quietly resumes."""
    if resume is None or resume is False:
        return False, run_dir
    if resume is True or (isinstance(resume, str) and resume == "auto"):
        return resume, run_dir
    allowed = "expected True, False, 'auto' or a run directory to continue"
    if not isinstance(resume, (str, os.PathLike)):
        raise DrivelabError(f"resume: {allowed}, got {type(resume).__name__} {resume!r}")
    if not Path(resume).is_dir():
        raise DrivelabError(f"resume: {allowed}, got {str(resume)!r}, which is no directory")
    if run_dir is not None and Path(run_dir).resolve() != Path(resume).resolve():
        raise DrivelabError(f"resume={str(resume)!r} continues that run, run_dir={str(run_dir)!r} names another; "
                            "give one of them")
    return True, resume


def _config_of_call(algo: str | TrainConfig | None, env: str | Mapping[str, Any] | Callable[..., gym.Env] | None, *,
                    steps: int | None, seed: int | None, num_envs: int | None, run_dir: str | Path | None,
                    config: str | Path | None, resume: bool | str, requeue: bool, overrides: Mapping[str, Any],
                    algorithms: Mapping[str, AlgoSpec]) -> TrainConfig:
    """The config that :func:`train`'s arguments describe: a :class:`TrainConfig` as given
    (checked against its run directory when requeued), or one built from the algorithm name,
    the env and the keyword fields by :func:`train_config`, as the CLI builds it."""
    if isinstance(algo, TrainConfig):
        if requeue:
            _check_requeue(algo)
        return algo
    if algo is not None and not isinstance(algo, str):
        raise DrivelabError(f"algo: expected an algorithm's name ({', '.join(algorithms)}) or a TrainConfig, "
                            f"got {type(algo).__name__} {algo!r}")
    if algo is None and config is None and resume is not True:  # the run's own config names it when resumed
        raise DrivelabError(f"algo: name the algorithm to train ({', '.join(algorithms)}), or pass a TrainConfig "
                            "or config=FILE that names it")
    if resume is True and run_dir is None:
        raise DrivelabError("resume=True continues the run in run_dir: pass run_dir (or resume=RUN_DIR)")
    env = env_id_of(env) if env is not None and not isinstance(env, (str, Mapping)) else env
    arguments = {"algo": algo, "env": {"id": env} if isinstance(env, str) else env, "steps": steps, "seed": seed,
                 "run_dir": None if run_dir is None else str(run_dir), **overrides, "env.num_envs": num_envs}
    arguments = {key: value for key, value in arguments.items() if value is not None}
    return train_config(arguments, config, resume=run_dir if resume is True else None, if_exists=requeue,
                        algorithms=algorithms)


def _requeue_status(cfg: TrainConfig) -> tuple[bool, bool]:
    """For ``resume="auto"``: (whether ``cfg.run_dir`` holds a run to continue, whether that run
    has already reached ``cfg.steps``, so that a requeued command has nothing left to do)."""
    exists = (Path(cfg.run_dir) / "config.yaml").is_file()
    reached = list_checkpoints(cfg.run_dir) and load_checkpoint(cfg.run_dir).step >= cfg.steps
    return exists, bool(exists and reached)


def _check_run_dir_is_free(cfg: TrainConfig, checkpoint: Checkpoint | None) -> None:
    """A run that does not continue a checkpoint must not train into a directory that holds one."""
    if checkpoint is None and any(checkpoint_step(p) > 0 for p in list_checkpoints(cfg.run_dir)):
        raise DrivelabError(f"run directory {cfg.run_dir} already holds a run; use --resume {shlex.quote(str(cfg.run_dir))} "
                            "(or --resume-if-exists) or another --run-dir")


def _check_env_and_network(cfg: TrainConfig, spec: AlgoSpec) -> None:
    """Pre-flight: fail on a bad env id, env kwargs, an unsupported action space or a network that
    does not fit the observations before a run directory exists."""
    obs_space, act_space = env_spaces(cfg.env)
    try:
        spec.build_policy(cfg, obs_space, act_space)
    except RuntimeError as exc:  # e.g. an image cropped smaller than the CNN's kernels
        raise DrivelabError(f"the {cfg.algo} network does not fit the observation space {obs_space}: "
                            f"{str(exc).strip().splitlines()[0]}") from None


def _connect_ray_if_used(cfg: TrainConfig) -> None:
    """Join the Ray cluster (``cfg.ray_address``) when the env or the evaluation runs on Ray."""
    if "ray" in (cfg.env.backend, cfg.eval.backend):
        from drivelab.envs.ray_backend import connect

        connect(cfg.ray_address)


def _train_keeping_evidence(spec: AlgoSpec, cfg: TrainConfig, run: Run) -> None:
    """Run the algorithm's training loop and close the run, however it ends: Ctrl-C or SIGTERM
    checkpoints the step reached and goes on as ``KeyboardInterrupt``; a :class:`DrivelabError`
    passes through; any other exception writes ``RUN/error.log`` and becomes
    :class:`~drivelab.errors.TrainingCrashed`, the latest checkpoint left as it was."""
    interrupted = False
    try:
        with stop_signals():
            spec.train(cfg, run)
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM from a scheduler (stop_signals turns it into this)
        interrupted = True
        run.checkpoint_now()
        raise
    except DrivelabError:  # said in one line already (a diverged loss, an env over its restart budget)
        interrupted = True
        raise
    except Exception as exc:  # a bug, or an error drivelab does not know: keep the evidence
        interrupted = True
        log = write_error_log(run.dir, exc)
        # the command is shell-quoted, so that a run directory with spaces pastes as one argument
        resume = shlex.join(["drivelab", "train", "--resume", str(run.dir)])
        raise TrainingCrashed(f"training stopped at step {run.step} by {error_line(exc)}; the traceback is in {log}; "
                              f"the latest checkpoint is intact: continue with {resume}") from exc
    finally:
        run.close(interrupted)


def env_id_of(env: Any) -> str:
    """An env class, or a function that returns an env, as the ``"module:Name"`` id that env
    workers (and later ``eval``, ``--resume``, ``export``) import it by."""
    if isinstance(env, gym.Env):
        raise DrivelabError(f"env: pass the class {type(env).__name__} (or a function that builds the env), not an "
                            "instance: each env worker builds its own")
    module, name = getattr(env, "__module__", None), getattr(env, "__qualname__", "")
    if not callable(env) or module is None or "." in name or "<" in name:
        raise DrivelabError(f"env: expected an id, a config section, an env class or a module-level function, got {env!r}")
    if module == "__main__":
        raise DrivelabError(f"env: {name} is defined in __main__, which env worker processes cannot import; "
                            "move it into a module (my_env.py) and pass it, or 'my_env:" + name + "'")
    return f"{module}:{name}"


def _checkpoint_to_resume(cfg: TrainConfig) -> Checkpoint | None:
    """The latest checkpoint of ``cfg.run_dir``, checked against ``cfg``; None when the run was
    stopped before its first checkpoint after step 0: nothing was trained, and starting afresh
    is exactly the run it would have been (the step-0 checkpoint is saved after the envs drew
    their first reset seeds, so continuing from it would not be). A run that has no checkpoint
    although it logged training past step 0 lost them (deleted, moved): refused, since starting
    afresh would silently throw its training away."""
    if not list_checkpoints(cfg.run_dir) and _logged_past_step_0(Path(cfg.run_dir)):
        where = Path(cfg.run_dir) / "checkpoints"
        missing = "has no checkpoint in checkpoints/" if where.is_dir() else "has no checkpoints/"
        raise DrivelabError(f"run {cfg.run_dir} {missing} although its metrics.csv logged training after step 0: "
                            "its checkpoints were deleted or moved; restore them, or train afresh into a new --run-dir")
    if not any(checkpoint_step(p) > 0 for p in list_checkpoints(cfg.run_dir)):
        if list_checkpoints(cfg.run_dir):
            print(f"drivelab: warning: {cfg.run_dir} was stopped before its first checkpoint after step 0; "
                  "starting it afresh",
                  file=sys.stderr)
        return None
    checkpoint = load_checkpoint(cfg.run_dir)
    if not isinstance(checkpoint.state.get("numpy_rng"), dict):
        raise DrivelabError(f"checkpoint {checkpoint.path} cannot be resumed: its state.json lacks the RNG state")
    if checkpoint.step >= cfg.steps:
        raise DrivelabError(f"run {cfg.run_dir} is already at step {checkpoint.step} >= steps {cfg.steps}; "
                            "pass a larger --steps to continue")
    differences = config_differences(checkpoint, config_to_dict(cfg))  # as eval and export check it
    if differences:
        raise DrivelabError(f"{Path(cfg.run_dir) / 'config.yaml'} does not match the config saved in {checkpoint.path} "
                            f"(fields {', '.join(differences[:5])}); one of them was edited, damaged or copied from "
                            "another run: restore it, or train into a new --run-dir")
    return checkpoint


def _logged_past_step_0(run_dir: Path) -> bool:
    """Whether ``RUN/metrics.csv`` holds a row of a step after 0. A run saves its step-0 checkpoint
    before it logs any later step, so such a row means that checkpoints were written."""
    path = run_dir / "metrics.csv"
    if not path.is_file():
        return False
    with open(path, errors="replace") as f:
        for line in f:  # rows are "step,time,name,value"; the header and a torn row start otherwise
            step = line.split(",", 1)[0]
            if step.isdigit() and int(step) > 0:
                return True
    return False


def write_error_log(run_dir: Path, exc: BaseException) -> Path:
    """``RUN/error.log``: when and where training stopped, and the full traceback."""
    log = Path(run_dir) / "error.log"
    text = "".join(traceback.format_exception(exc))
    log.write_text(f"drivelab {__version__}, {time.strftime('%Y-%m-%d %H:%M:%S')}, pid {os.getpid()}\n{text}")
    return log


def train_config(overrides: Mapping[str, Any], config: str | Path | None = None, resume: str | Path | None = None,
                 if_exists: bool = False, algorithms: Mapping[str, AlgoSpec] = ALGORITHMS) -> TrainConfig:
    """The validated config of a run: the fields of ``config`` (a YAML file or a shipped config's
    name; none: the defaults) with ``overrides`` merged in (dotted keys or nested sections, deeply:
    :func:`drivelab.config.merge_overrides`). Both faces build their config here.

    ``resume`` (a run directory) starts from that run's saved ``config.yaml`` instead, and only
    :data:`~drivelab.config.RESUMABLE_FIELDS` may be overridden with another value than the saved
    one: the rest would change the experiment that the checkpoints continue.

    ``if_exists`` (requeueing, ``--resume-if-exists``): ``config`` and ``overrides`` describe
    the run; when its ``run_dir`` already holds a ``config.yaml``, that must describe the same
    experiment (it may differ in the resumable fields only).
    """
    if resume is None or if_exists:
        data = read_yaml(resolve_config_file(config)) if config else {}
        where = f"config {config}" if config else "config"
        cfg = build_config(merge_overrides(data, overrides), where=where, algorithms=algorithms)
        if if_exists:
            _check_requeue(cfg)
        return cfg
    if config:
        raise DrivelabError("--resume continues a run with its saved config; do not pass --config "
                            "(to start or continue one command, use --config X --run-dir R --resume-if-exists)")
    saved = Path(resume) / "config.yaml"
    if not saved.is_file():
        hint = ("it was stopped before its config was written, so nothing was trained: run the original command "
                "again (with --resume-if-exists it is safe to requeue)") if Path(resume).is_dir() else "no such directory"
        raise DrivelabError(f"{resume} is not a drivelab run directory (no config.yaml): {hint}")
    data = read_yaml(saved, allow_empty=True)
    if not data:
        raise DrivelabError(f"{saved} is empty (a write was interrupted): the config inside its latest checkpoint "
                            "(checkpoints/step_*/state.json) holds the run's settings")
    data["run_dir"] = str(resume)
    for key, value in _leaves(overrides):
        if key.split(".")[0] not in RESUMABLE_FIELDS and _field(data, key) != value:
            raise DrivelabError(f"--resume keeps the run's config; '{key}' cannot change "
                                f"(allowed: {', '.join(RESUMABLE_FIELDS)})")
    return build_config(merge_overrides(data, overrides), where=f"config of run {resume}", algorithms=algorithms)


def _check_requeue(cfg: TrainConfig) -> None:
    """A requeued command must describe the run its directory holds (if it holds one)."""
    if cfg.run_dir is None:
        raise DrivelabError("--resume-if-exists needs --run-dir: the directory to start the run in or continue it from")
    saved = Path(cfg.run_dir) / "config.yaml"
    if not saved.is_file():
        return
    differences = experiment_differences(config_to_dict(cfg), with_defaults(read_yaml(saved, allow_empty=True)))
    if differences:
        raise DrivelabError(f"run directory {cfg.run_dir} holds another experiment: {', '.join(differences[:5])} "
                            f"differ from {saved}; use another --run-dir")


def _leaves(overrides: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted field, value) of every field that ``overrides`` sets, nested sections flattened."""
    for key, value in overrides.items():
        if isinstance(value, Mapping) and value:
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _field(data: dict, dotted: str) -> Any:
    """The value at a dotted path of config data (None where it is not set)."""
    for key in dotted.split("."):
        data = data.get(key) if isinstance(data, dict) else None
    return data


def make_env(env: str | EnvConfig, **kwargs: Any) -> gym.Env:
    """One env as drivelab builds it: an id with keyword overrides (``make_env("MetaDrive-10env-v0",
    traffic_density=0.2)``), or an :class:`EnvConfig` (action grid, filters, reward, ...)."""
    from drivelab.envs import make_env as build

    env_cfg = env if isinstance(env, EnvConfig) else EnvConfig(id=env, kwargs=kwargs)
    env_cfg.validate()
    return build(env_cfg)


def evaluate(policy: TrainedPolicy, env: str | EnvConfig | gym.Env | Callable[..., gym.Env] | None = None,
             episodes: int = 10, seed: int = 0, num_envs: int = 1, deterministic: bool = True) -> dict[str, Any]:
    """Deterministic episodes of ``policy`` (episode k with seed ``seed + k``); returns the dict
    that ``drivelab eval CHECKPOINT --json`` prints (:func:`evaluation_row`). ``env``: None (the
    policy's own env), an env id (where it differs from the training env's, the kwargs but
    ``vehicle_config`` are dropped, as in ``drivelab eval --env``), an env class or a function
    that returns an env (as :func:`train` takes them), an :class:`EnvConfig`, or an env instance.
    An env whose spaces are not the policy's is refused before an episode is played."""
    if not isinstance(policy, TrainedPolicy):
        raise DrivelabError(f"policy: expected a policy from drivelab.load(...), got {type(policy).__name__}")
    for argument, value, least in (("episodes", episodes, 1), ("num_envs", num_envs, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
            raise DrivelabError(f"{argument}: expected an integer >= {least}, got {value!r}")
    if isinstance(env, gym.Env):
        name = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
        check_fits_env(policy, (env.observation_space, env.action_space), name)
        envs = SyncVectorEnv([lambda: env], autoreset_mode=AutoresetMode.DISABLED)
        result = run_episodes(envs, policy, episodes, seed=seed, deterministic=deterministic)
        return evaluation_row(result, name, policy.checkpoint)
    env_cfg = _evaluation_env(policy, env)
    env_cfg = dataclasses.replace(env_cfg, num_envs=max(1, min(num_envs, episodes)))
    result = play(env_cfg, policy, episodes, seed, deterministic)
    return evaluation_row(result, env_cfg.id, policy.checkpoint)


def _evaluation_env(policy: TrainedPolicy, env: str | EnvConfig | Callable[..., gym.Env] | None) -> EnvConfig:
    """The env config that :func:`evaluate` plays for its ``env`` argument, checked against the
    policy's spaces (the policy's own env needs no check)."""
    if isinstance(env, EnvConfig):
        env.validate()
        env_cfg = env
    else:
        env = env_id_of(env) if env is not None and not isinstance(env, str) else env
        if env is None or env == policy.env_config.id:
            return policy.env_config
        env_cfg = policy.env_config.on(env)
    check_fits_env(policy, env_spaces(env_cfg), env_cfg.id)
    return env_cfg
