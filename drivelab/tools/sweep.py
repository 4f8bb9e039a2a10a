"""Experiments in parallel on Ray Tune: ``drivelab sweep CONFIG --grid K=V1,V2 ... --seeds 0-4``.

Every combination of the grid values and seeds is a normal drivelab run (its own run directory
``SWEEP/<setting>-s<seed>``, resumable) trained inside a Ray Tune trial by the ``train``
function that the caller hands down (:func:`drivelab.api.train`: the face above the tools), as
many at once as the cluster has CPUs (``cpus_per_trial`` each). Running the same sweep again
resumes unfinished runs and skips finished ones (a sweep whose runs are all finished writes its
table again without starting Ray). At the end: a table of the final metrics
per setting (mean and 95% confidence interval over the seeds, Student's t), ``sweep.json``,
``sweep.md``, the runs' curves (``curves.png``, seeds grouped) and, when a grid key is numeric,
the final metrics against it (``final.png``: MetaDrive's generalisation plot, success against
the number of training scenarios).

A config file may carry its sweep in a ``sweep:`` section (``grid``: {key: [values]}, ``seeds``),
which the command line extends; see ``configs/metadrive_generalization.yaml``.

Or a search instead of a grid (``drivelab sweep CONFIG --trials 16 --space ppo.lr=loguniform:1e-5,1e-3
--metric eval/return_mean --asha``, or a ``search:`` block in the section, see
``configs/ppo_cartpole_search.yaml``): Optuna's TPE sampler (Ray Tune's ``OptunaSearch``) picks
each trial's values from the space after the results of the earlier ones, and ASHA (Li et al.
2020, ``ASHAScheduler``) stops the trials whose metric at an evaluation step trails the others
(every ``reduction_factor``-th one goes on past each rung). A trial is a normal run in
``SWEEP/<trial id>-<values>-s<seed>``; one that ASHA stopped keeps its checkpoints. The table ranks
the trials by the metric.
"""

from __future__ import annotations

import copy
import itertools
import json
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm.auto import tqdm

from drivelab.config import TrainConfig, merge_overrides, parse_value, read_yaml, resolve_config_file
from drivelab.errors import DrivelabError
from drivelab.tools.policies import build_config
from drivelab.tools.tables import format_table
from drivelab.training.outputs.plots import last_metrics, read_metrics
from drivelab.training.outputs.statistics import mean_and_ci95

# The final metrics summarised per setting, the first of each pair that the runs logged.
SUMMARY_METRICS = ("eval/success_rate", "eval/route_completion", "eval/return_mean", "episode/success_rate",
                   "episode/route_completion", "episode/return")


@dataclass(frozen=True)
class Trial:
    setting: dict[str, Any]      # dotted config key -> value
    seed: int

    @property
    def setting_name(self) -> str:
        parts = [f"{key.split('.')[-1]}={value}" for key, value in self.setting.items()]
        return re.sub(r"[^A-Za-z0-9_.,=+-]", "_", ",".join(parts)) or "base"

    @property
    def name(self) -> str:
        return f"{self.setting_name}-s{self.seed}"


def parse_grid(items: list[str]) -> dict[str, list[Any]]:
    """``["ppo.lr=1e-4,3e-4", ...]`` -> {"ppo.lr": [0.0001, 0.0003]} (values read as on the command line)."""
    grid: dict[str, list[Any]] = {}
    for item in items:
        key, sep, values = item.partition("=")
        if not sep or not key or not values:
            raise DrivelabError(f"--grid expects KEY=V1,V2,..., got {item!r}")
        grid[key.strip()] = [parse_value(v) for v in values.split(",")]
    return grid


def parse_seeds(text: str | list[int]) -> list[int]:
    """``"0-4"`` -> [0, 1, 2, 3, 4]; ``"0,2,7"`` -> [0, 2, 7]."""
    if isinstance(text, list):
        return [int(s) for s in text]
    seeds: list[int] = []
    try:
        for part in str(text).split(","):
            low, _, high = part.partition("-")
            seeds += list(range(int(low), int(high) + 1)) if high else [int(low)]
    except ValueError:
        raise DrivelabError(f"--seeds expects a range like 0-4 or a list like 0,2,7, got {text!r}") from None
    if not seeds:  # e.g. "3-1"; the range of each seed is the config's rule (field 'seed')
        raise DrivelabError(f"--seeds names no seed, got {text!r}")
    return seeds


def load_sweep(config: str | Path, grid: Sequence[str] = (), seeds: str | None = None, steps: int | None = None,
               env: str | None = None) -> tuple[dict, dict[str, list[Any]], list[int]]:
    """(base config data, grid, seeds) of a sweep: the config file (or shipped config) and its
    optional ``sweep:`` section, extended by ``grid`` items (``KEY=V1,V2``, as ``--grid``), with
    ``seeds`` (as ``--seeds``; default the section's, else 0), and ``steps`` and the ``env`` id if given."""
    base, section = _read_sweep(config)
    values = {key: v if isinstance(v, list) else [v] for key, v in (section.get("grid") or {}).items()}
    values.update(parse_grid(list(grid)))
    if steps is not None:
        base["steps"] = steps
    if env is not None:
        merge_overrides(base, {"env.id": env})
    return base, values, parse_seeds(seeds if seeds is not None else section.get("seeds", [0]))


class TrialProgress:
    """Trials done out of the total, on a progress bar (stderr): Ray Tune trains the trials in
    other processes and says nothing until all are done. A trial that finishes, that ASHA stops
    or that fails (after its retry) moves it by one; ``progress=False`` shows nothing."""

    def __init__(self, total: int, progress: bool = True):
        # shown after a second: an error raised before the trials start stays one line
        self.bar = tqdm(total=total, desc="sweep", unit="trial", dynamic_ncols=True, disable=not progress, delay=1)
        self.failed = 0

    def trial_ended(self, failed: bool = False) -> None:
        if failed:
            self.failed += 1
            self.bar.set_postfix_str(f"{self.failed} failed", refresh=False)
        self.bar.update(1)

    def tune_callback(self) -> Any:
        """The Ray Tune callback that tells :meth:`trial_ended` (Tune calls it in this process)."""
        from ray.tune import Callback

        progress = self

        class TrialEnded(Callback):
            def on_trial_complete(self, iteration: int, trials: list, trial: Any, **info: Any) -> None:
                progress.trial_ended()

            def on_trial_error(self, iteration: int, trials: list, trial: Any, **info: Any) -> None:
                progress.trial_ended(failed=True)

        return TrialEnded()

    def close(self) -> None:
        self.bar.close()


# ---- search: Optuna's sampler and ASHA's early stopping on Ray Tune -------------------------

DISTRIBUTIONS = ("loguniform", "uniform", "int", "choice")


@dataclass
class Search:
    """A ``sweep.search`` block: ``space`` maps a dotted config key to ``[distribution, ...]``
    (``[loguniform, low, high]``, ``[uniform, low, high]``, ``[int, low, high]`` (both included),
    ``[choice, v1, v2, ...]``); ``trials`` runs are sampled, each ranked by ``metric`` (a logged
    name, e.g. ``eval/return_mean``) towards ``mode`` (max or min)."""
    space: dict[str, list[Any]]
    trials: int = 8
    metric: str = "eval/return_mean"
    mode: str = "max"
    asha: bool = False                 # stop the trials that trail at an evaluation (ASHA)
    grace_period: int | None = None    # env steps every trial trains before ASHA may stop it (default: eval.every)
    reduction_factor: int = 2          # ASHA keeps 1 trial in this many at each rung

    def validate(self) -> None:
        where = "sweep.search"
        if not self.space:
            raise DrivelabError(f"{where}.space names no config field to search (e.g. ppo.lr: [loguniform, 1e-5, 1e-3])")
        for key, spec in self.space.items():
            if not isinstance(spec, list) or not spec or spec[0] not in DISTRIBUTIONS:
                raise DrivelabError(f"{where}.space.{key} must be [distribution, ...] with a distribution in "
                                    f"{', '.join(DISTRIBUTIONS)}, got {spec!r}")
            if spec[0] != "choice" and (len(spec) != 3 or not all(isinstance(x, (int, float)) for x in spec[1:])
                                        or not spec[1] < spec[2] or (spec[0] == "loguniform" and spec[1] <= 0)):
                raise DrivelabError(f"{where}.space.{key}: {spec[0]} needs low < high (low > 0 for loguniform), got {spec!r}")
            if spec[0] == "choice" and len(spec) < 2:
                raise DrivelabError(f"{where}.space.{key}: choice needs at least one value")
        if self.trials < 1 or self.mode not in ("max", "min") or self.reduction_factor < 2:
            raise DrivelabError(f"{where}: trials must be >= 1, mode max or min, reduction_factor >= 2")
        if self.grace_period is not None and self.grace_period < 1:
            raise DrivelabError(f"{where}.grace_period must be >= 1 env step")

    def domains(self) -> dict[str, Any]:
        """Ray Tune's search space (OptunaSearch converts it into Optuna's distributions)."""
        from ray import tune

        make = {"loguniform": lambda lo, hi: tune.loguniform(lo, hi), "uniform": lambda lo, hi: tune.uniform(lo, hi),
                "int": lambda lo, hi: tune.randint(int(lo), int(hi) + 1)}
        return {key: tune.choice(spec[1:]) if spec[0] == "choice" else make[spec[0]](*spec[1:])
                for key, spec in self.space.items()}


def parse_space(items: list[str]) -> dict[str, list[Any]]:
    """``["ppo.lr=loguniform:1e-5,1e-3", "ppo.num_steps=choice:64,128"]`` -> the ``space`` of a :class:`Search`."""
    space: dict[str, list[Any]] = {}
    for item in items:
        key, sep, spec = item.partition("=")
        kind, colon, values = spec.partition(":")
        if not sep or not colon or not key or kind not in DISTRIBUTIONS:
            raise DrivelabError(f"--space expects KEY=DISTRIBUTION:A,B with a distribution in {', '.join(DISTRIBUTIONS)}, "
                                f"got {item!r}")
        space[key.strip()] = [kind, *(parse_value(v) for v in values.split(","))]
    return space


def _search_trial(setting: dict[str, Any], base: dict, out: Path, seed: int, train: Callable[..., Any]) -> None:
    """One search trial: a drivelab run with the sampled ``setting``, reporting its metrics to
    Tune at each evaluation (at each log without evaluations), where ASHA may stop it."""
    from ray import tune

    trial_id = tune.get_context().get_trial_id()
    rounded = {key: float(f"{value:.3g}") if isinstance(value, float) else value for key, value in setting.items()}
    data = trial_config(base, Trial(setting, seed), out / f"{trial_id}-{Trial(rounded, seed).name}")
    cfg = build_config(data, where=f"search trial {trial_id}")
    report_on = "eval" if cfg.eval.every else "log"
    latest: dict[str, float] = {}

    def report(event) -> None:
        if event.kind in ("log", "eval"):
            prefix = "eval/" if event.kind == "eval" else ""
            latest.update({prefix + key: float(value) for key, value in event.metrics.items()})
        if event.kind == report_on:
            tune.report({**{k: v for k, v in latest.items() if math.isfinite(v)}, "step": event.step,
                         "run": Path(cfg.run_dir).name})

    train(cfg, progress=False, callback=report)


def run_search(base: dict, search: Search, seed: int, out: Path, train: Callable[..., Any],
               ray_address: str | None = None, cpus_per_trial: float = 1.0, max_concurrent: int | None = None,
               progress: bool = True) -> dict:
    """Sample ``search.trials`` runs with Optuna on Ray Tune (ASHA stopping the laggards when
    ``search.asha``), then rank them by ``search.metric``; writes sweep.json, sweep.md and
    curves.png into ``out`` and returns the summary. ``progress``: trials done on stderr."""
    from drivelab.envs.ray_backend import connect, import_ray

    search.validate()
    probe = build_config(merge_overrides(copy.deepcopy(base), {k: _example(v) for k, v in search.space.items()}),
                         where="sweep base config")  # the base and the space's keys are valid before anything runs
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    (out / "sweep.yaml").write_text(yaml.safe_dump({"base": base, "search": search.__dict__, "seed": seed}, sort_keys=False))
    _quiet_tune()
    import_ray()
    connect(ray_address)
    bar = TrialProgress(search.trials, progress)
    try:
        tuner = _search_tuner(base, search, seed, out, train, probe, cpus_per_trial, max_concurrent, bar.tune_callback())
        results = tuner.fit()
    finally:
        bar.close()
    trials = _search_trials(results, out, search.metric, probe.steps)
    ranked = sorted((t for t in trials if t.get("metric") is not None), key=lambda t: t["metric"],
                    reverse=search.mode == "max")
    summary = {"search": {**search.__dict__, "steps": probe.steps, "seed": seed},
               "trials": ranked + [t for t in trials if t.get("metric") is None]}
    if ranked:
        summary["best"] = ranked[0]
    (out / "sweep.json").write_text(json.dumps(summary, indent=1))
    (out / "sweep.md").write_text(format_search(summary) + "\n")
    runs = [out / t["run"] for t in ranked]
    if runs:
        from drivelab.training.outputs.plots import plot_runs

        plot_runs(runs, out / "curves.png")
    return summary


def _search_tuner(base: dict, search: Search, seed: int, out: Path, train: Callable[..., Any], probe: TrainConfig,
                  cpus_per_trial: float, max_concurrent: int | None, callback: Any) -> Any:
    """The Ray Tune ``Tuner`` of a search: :func:`_search_trial` as the trainable, Optuna's TPE
    sampler (seeded with ``seed``) picking the values and, with ``search.asha``, ASHA stopping
    trials once they trained ``search.grace_period`` env steps (default: the base config's
    ``eval.every``, or its ``log_every`` without evaluations), up to ``probe.steps``; ``callback``
    hears each trial end (:meth:`TrialProgress.tune_callback`)."""
    from ray import tune
    from ray.tune.schedulers import ASHAScheduler

    try:
        import optuna
        from ray.tune.search.optuna import OptunaSearch
    except ImportError:
        raise DrivelabError("a search needs optuna: pip install 'drivelab[ray]'") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    scheduler = None
    if search.asha:
        grace = search.grace_period or probe.eval.every or probe.log_every
        scheduler = ASHAScheduler(time_attr="step", max_t=probe.steps, grace_period=grace,
                                  reduction_factor=search.reduction_factor)
    return tune.Tuner(
        tune.with_resources(tune.with_parameters(_search_trial, base=base, out=out, seed=seed, train=train),
                            {"cpu": cpus_per_trial}),
        param_space=search.domains(),
        tune_config=tune.TuneConfig(metric=search.metric, mode=search.mode, num_samples=search.trials,
                                    search_alg=OptunaSearch(sampler=optuna.samplers.TPESampler(seed=seed)),
                                    scheduler=scheduler, max_concurrent_trials=max_concurrent),
        run_config=tune.RunConfig(name="tune", storage_path=str(out / ".tune"), verbose=0, callbacks=[callback]),
    )


def _search_trials(results: Any, out: Path, metric: str, planned_steps: int) -> list[dict]:
    """One entry per trial of Tune's ``results``: its run directory, sampled setting, the env step
    it reached (``stopped_early`` when short of ``planned_steps``) and its final ``metric``; a trial
    that left no metrics gets its error instead."""
    trials = []
    for result in results:
        metrics = result.metrics or {}
        run = out / str(metrics.get("run", ""))
        if not metrics.get("run") or not (run / "metrics.csv").is_file():
            error = str(result.error).strip().splitlines()[-1] if result.error else "no result"
            trials.append({"run": None, "setting": result.config, "error": error})
            continue
        final = last_metrics(run)
        step = max(int(steps[-1]) for steps, _, _ in read_metrics(run).values() if len(steps))
        trials.append({"run": run.name, "setting": result.config, "step": step, "stopped_early": step < planned_steps,
                       "metric": final.get(metric, metrics.get(metric))})
    return trials


def _quiet_tune() -> None:
    """Tune's legacy reporter, which ``verbose=0`` silences: the newer one still prints its
    configuration box and a TensorBoard hint into Ray's temporary session folder."""
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")


def _example(spec: list[Any]) -> Any:
    """A value inside a space entry (to validate the config it would make)."""
    return spec[1] if spec[0] == "choice" else (int(spec[1]) if spec[0] == "int" else spec[1])


def format_search(summary: dict) -> str:
    """A Markdown table of the trials, best first: values, the metric, env steps trained, stopped or not."""
    search = summary["search"]
    keys = list(search["space"])
    rows = []
    for t in summary["trials"]:
        values = [f"{t['setting'].get(k):.3g}" if isinstance(t["setting"].get(k), float) else str(t["setting"].get(k))
                  for k in keys]
        if t.get("metric") is None:
            rows.append([t["run"] or "-", *values, "-", "-", t.get("error", "")])
        else:
            stopped = f"stopped by ASHA at {t['step']:,}" if t["stopped_early"] else f"{t['step']:,}"
            rows.append([t["run"], *values, f"{t['metric']:.4g}", stopped, ""])
    if not any(row[-1] for row in rows):  # no trial failed: no error column
        rows = [row[:-1] for row in rows]
    return format_table(["run", *keys, search["metric"], "env steps", "error"][:len(rows[0]) if rows else None], rows,
                        markdown=True)


def _read_sweep(config: str | Path) -> tuple[dict, dict]:
    """(base config data, its ``sweep:`` section)."""
    path = resolve_config_file(config)
    base = read_yaml(path)
    section = base.pop("sweep", None) or {}
    if not isinstance(section, dict) or set(section) - {"grid", "seeds", "search"}:
        raise DrivelabError(f"config file {path}: the sweep section holds only grid, seeds and search")
    return base, section


def load_search(config: str | Path, space: Sequence[str] = (), seeds: str | None = None, steps: int | None = None,
                env: str | None = None, **fields: Any) -> tuple[dict, Search, int] | None:
    """(base config data, search, seed) when the config's sweep section has a ``search`` block or
    ``space`` items (``KEY=DISTRIBUTION:A,B``, as ``--space``) are given, with the ``fields`` of
    :class:`Search` given on the command line (None: the block's, else the default); else None."""
    base, section = _read_sweep(config)
    block = section.get("search")
    if block is None and not space:
        return None
    if block is not None and not isinstance(block, dict):
        raise DrivelabError("sweep.search must be a mapping (space, trials, metric, mode, asha, ...)")
    block = dict(block or {})
    unknown = set(block) - set(Search.__dataclass_fields__)
    if unknown:
        raise DrivelabError(f"sweep.search: unknown field(s) {', '.join(sorted(unknown))}; "
                            f"known: {', '.join(Search.__dataclass_fields__)}")
    block["space"] = {**(block.get("space") or {}), **parse_space(list(space))}
    block.update({key: value for key, value in fields.items() if value is not None})
    search = Search(**block)
    search.validate()
    if section.get("grid"):
        raise DrivelabError("sweep: give a grid or a search, not both")
    chosen = parse_seeds(seeds if seeds is not None else section.get("seeds", [0]))
    if len(chosen) != 1:
        raise DrivelabError(f"a search trains one seed per trial; got seeds {chosen} (rerun the best values over "
                            f"seeds with --grid)")
    if steps is not None:
        base["steps"] = steps
    if env is not None:
        merge_overrides(base, {"env.id": env})
    return base, search, chosen[0]


def plan(grid: dict[str, list[Any]], seeds: list[int]) -> list[Trial]:
    keys = list(grid)
    return [Trial(dict(zip(keys, values)), seed) for values in itertools.product(*grid.values()) for seed in seeds]


def trial_config(base: dict, trial: Trial, run_dir: Path) -> dict:
    """The config data of one trial: the base config with the trial's grid values, seed and run directory."""
    data = merge_overrides(copy.deepcopy(base), trial.setting)
    data["seed"], data["run_dir"] = trial.seed, str(run_dir)
    return data


def _run_trial(config: dict, train: Callable[..., Any]) -> None:
    """A Ray Tune trial: train (or resume, or skip when finished) one drivelab run with ``train``
    (``train(cfg, resume=..., progress=False)``, as :func:`drivelab.api.train`)."""
    from ray import tune

    from drivelab.training.outputs.checkpoint import list_checkpoints

    data, run_dir = config["data"], Path(config["data"]["run_dir"])
    cfg = build_config(data, where=f"sweep trial {run_dir.name}")
    if not _finished(run_dir, cfg.steps):
        train(cfg, resume=bool(list_checkpoints(run_dir)), progress=False)
    tune.report({k: v for k, v in last_metrics(run_dir).items() if math.isfinite(v)})


def _finished(run_dir: Path, steps: int) -> bool:
    """Whether the run in ``run_dir`` has a checkpoint at ``steps`` or later."""
    from drivelab.training.outputs.checkpoint import list_checkpoints

    checkpoints = list_checkpoints(run_dir)
    return bool(checkpoints) and int(checkpoints[-1].name.split("_")[-1]) >= steps


def run_sweep(base: dict, grid: dict[str, list[Any]], seeds: list[int], out: Path, train: Callable[..., Any],
              ray_address: str | None = None, cpus_per_trial: float = 1.0, max_concurrent: int | None = None,
              progress: bool = True) -> dict:
    """Train every trial on Ray Tune with ``train`` (:func:`drivelab.api.train`, handed down by
    the face, which the tools may not import; Ray pickles a module-level function by reference),
    then summarise (see the module docstring). Returns the summary. ``progress``: trials done on stderr."""
    trials = plan(grid, seeds)
    out = out.resolve()
    datas = [trial_config(base, t, out / t.name) for t in trials]
    # every trial's config is valid before anything runs
    steps = [build_config(data, where=f"sweep trial {t.name}").steps for data, t in zip(datas, trials)]
    out.mkdir(parents=True, exist_ok=True)
    (out / "sweep.yaml").write_text(yaml.safe_dump({"base": base, "grid": grid, "seeds": seeds}, sort_keys=False))
    todo = [data for data, n in zip(datas, steps) if not _finished(Path(data["run_dir"]), n)]
    failed = _train_on_tune(todo, train, ray_address, cpus_per_trial, max_concurrent, progress, out) if todo else []
    summary = summarise(out, trials)
    if failed:
        summary["failed"] = failed
    (out / "sweep.json").write_text(json.dumps(summary, indent=1))
    (out / "sweep.md").write_text(format_summary(summary) + "\n")
    plot_sweep(out, trials, summary)
    return summary


def _train_on_tune(datas: list[dict], train: Callable[..., Any], ray_address: str | None, cpus_per_trial: float,
                   max_concurrent: int | None, progress: bool, out: Path) -> list[str]:
    """Train the trials of ``datas`` on Ray Tune (see :func:`run_sweep`); returns one line per failed trial."""
    from drivelab.envs.ray_backend import connect, import_ray

    _quiet_tune()
    import_ray()
    connect(ray_address)
    from ray import tune

    bar = TrialProgress(len(datas), progress)
    tuner = tune.Tuner(
        tune.with_resources(tune.with_parameters(_run_trial, train=train), {"cpu": cpus_per_trial}),
        param_space={"data": tune.grid_search(datas)},
        tune_config=tune.TuneConfig(max_concurrent_trials=max_concurrent, trial_dirname_creator=lambda trial: trial.trial_id),
        run_config=tune.RunConfig(name="tune", storage_path=str(out / ".tune"), verbose=0,
                                  failure_config=tune.FailureConfig(max_failures=1),
                                  callbacks=[bar.tune_callback()]),
    )
    try:
        results = tuner.fit()
    finally:
        bar.close()
    return [f"{Path(r.config['data']['run_dir']).name}: {r.error}".splitlines()[0] for r in results if r.error is not None]


def summarise(out: Path, trials: list[Trial]) -> dict:
    """{"settings": [{setting, runs, metrics: {name: [mean, ci95, n]}}]} from the runs' final metrics."""
    groups: dict[str, list[Trial]] = {}
    for t in trials:
        groups.setdefault(t.setting_name, []).append(t)
    settings = []
    for name, members in groups.items():
        finals = []
        for t in members:
            metrics_file = out / t.name / "metrics.csv"
            if metrics_file.is_file():
                finals.append(last_metrics(out / t.name))
        metrics = {}
        for metric in SUMMARY_METRICS:
            values = [f[metric] for f in finals if metric in f and math.isfinite(f[metric])]
            if values:
                mean, ci = mean_and_ci95(np.array(values))
                metrics[metric] = [float(mean), float(ci), len(values)]
        settings.append({"name": name, "setting": members[0].setting, "runs": [t.name for t in members],
                         "metrics": metrics})
    return {"settings": settings}


def format_summary(summary: dict) -> str:
    """A Markdown table: one row per setting, mean ± 95% CI (n seeds) of each final metric."""
    metrics = [m for m in SUMMARY_METRICS if any(m in s["metrics"] for s in summary["settings"])]

    def cell(mean: float, ci: float, n: int) -> str:  # one seed has no confidence interval: "–", not "± 0"
        return f"{mean:.3g} ± {ci:.2g} (n={n})" if n > 1 else f"{mean:.3g} ± – (n=1)"

    rows = [[s["name"], *(cell(*s["metrics"][m]) if m in s["metrics"] else "-" for m in metrics)]
            for s in summary["settings"]]
    return format_table(["setting", *metrics], rows, markdown=True)


def plot_sweep(out: Path, trials: list[Trial], summary: dict) -> None:
    """``curves.png`` (every run, seeds grouped) and, for a numeric grid key, ``final.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivelab.training.outputs.plots import plot_runs

    runs = [out / t.name for t in trials if (out / t.name / "metrics.csv").is_file()]
    if runs:
        plot_runs(runs, out / "curves.png")
    numeric = [k for k in trials[0].setting if all(isinstance(t.setting[k], (int, float)) for t in trials)]
    if not numeric:
        return
    key = numeric[0]
    metrics = [m for m in ("eval/success_rate", "episode/success_rate", "eval/route_completion", "episode/route_completion")
               if any(m in s["metrics"] for s in summary["settings"])] or \
              [m for m in SUMMARY_METRICS if any(m in s["metrics"] for s in summary["settings"])][:2]
    fig, ax = plt.subplots(figsize=(6, 4))
    for metric in metrics:
        rows = sorted((s["setting"][key], *s["metrics"][metric][:2]) for s in summary["settings"] if metric in s["metrics"])
        if rows:
            x, mean, ci = map(np.array, zip(*rows))
            label = metric.replace("eval/", "held-out ").replace("episode/", "training ")
            ax.errorbar(x, mean, yerr=ci, marker="o", capsize=3, label=label)
    if all(t.setting[key] > 0 for t in trials) and max(t.setting[key] for t in trials) >= 100 * min(t.setting[key] for t in trials):
        ax.set_xscale("log")
    ax.set_xlabel(key)
    ax.set_title("final metrics (mean and 95% CI over seeds)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "final.png", dpi=90)
    plt.close(fig)
