"""The parts that ``drivelab.training.run.Run`` composes, each tested on its own: the run directory,
the metrics, evaluation and the best checkpoint, checkpoints and resume."""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode
from processes import run_drivelab

from drivelab.algos import ALGORITHMS
from drivelab.api import build_config
from drivelab.envs import env_spaces, make_vector_env
from drivelab.envs.config import EnvConfig
from drivelab.errors import DrivelabError
from drivelab.training.collection.evaluation import EvalActor, evaluate_policy, new_best
from drivelab.training.outputs.checkpoint import load_checkpoint
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.outputs.tracking import Tracker
from drivelab.training.run.checkpoints import RunCheckpoints
from drivelab.training.run.directory import MARKER, open_run_dir, seed_everything
from drivelab.training.run.metrics import RunMetrics, check_finite
from drivelab.training.run.periodic_evaluation import RunEvaluation, eval_env_config
from drivelab.training.run.timing import Timing


def _config(tmp_path: Path, **overrides):
    data = {"algo": "ppo", "seed": 3, "run_dir": str(tmp_path / "run"), "steps": 1000,
            "env": {"id": "CartPole-v1", "num_envs": 2},
            "eval": {"every": 500, "episodes": 2, "video": False}}
    for key, value in overrides.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    return build_config(data)


def _policy(cfg) -> torch.nn.Module:
    return ALGORITHMS[cfg.algo].build_policy(cfg, *env_spaces(cfg.env))


# ---- the run directory ------------------------------------------------------------------------

def test_the_run_directory_is_locked_cleaned_and_holds_the_config(tmp_path):
    cfg = _config(tmp_path)
    stale = tmp_path / "run" / "checkpoints" / ".tmp_123"   # left by a killed run
    stale.mkdir(parents=True)
    (tmp_path / "run" / MARKER).write_text("")
    lock = open_run_dir(cfg)
    try:
        assert (tmp_path / "run" / "config.yaml").is_file() and not stale.exists()
        with pytest.raises(DrivelabError, match="in use by another drivelab process"):
            open_run_dir(cfg)
    finally:
        lock.close()
    open_run_dir(cfg).close()  # released with its file


def test_a_folder_that_is_not_a_run_is_refused_and_left_as_it_was(tmp_path):
    cfg = _config(tmp_path)
    mine = tmp_path / "run"
    mine.mkdir()
    (mine / "config.yaml").write_text("my: own\n")
    (mine / "metrics.csv").write_text("a,b\n")
    with pytest.raises(DrivelabError, match=r"not a drivelab run \(it holds config.yaml, metrics.csv\)"):
        open_run_dir(cfg)
    assert (mine / "config.yaml").read_text() == "my: own\n" and sorted(p.name for p in mine.iterdir()) == \
        ["config.yaml", "metrics.csv"]


def test_an_empty_folder_or_a_run_written_before_markers_is_a_run_dir(tmp_path):
    empty = tmp_path / "run"
    empty.mkdir()
    open_run_dir(_config(tmp_path)).close()
    assert (empty / MARKER).is_file()
    old = tmp_path / "old"
    (old / "checkpoints" / "step_000000000000").mkdir(parents=True)
    (old / "config.yaml").write_text("algo: ppo\n")
    open_run_dir(_config(tmp_path, run_dir=str(old))).close()
    assert (old / MARKER).is_file()


def test_the_cli_refuses_a_users_folder_an_empty_name_and_a_path_through_a_file(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "config.yaml").write_text("my: own\n")
    (tmp_path / "afile").write_text("")
    for run_dir, message in [(str(mine), "is not a drivelab run"), ("", "'run_dir' is empty"),
                             (str(tmp_path / "afile" / "x"), "is a file")]:
        result = run_drivelab("train", "--algo", "ppo", "--env", "CartPole-v1", "--steps", "512", "--run-dir", run_dir,
                              cwd=tmp_path)
        assert result.returncode == 2 and message in result.stderr and "Traceback" not in result.stderr, result.stderr
    assert (mine / "config.yaml").read_text() == "my: own\n"


def test_seeding_gives_the_same_streams(tmp_path):
    cfg = _config(tmp_path)
    first = seed_everything(cfg).integers(0, 1000, 5), torch.rand(3)
    second = seed_everything(cfg).integers(0, 1000, 5), torch.rand(3)
    assert (first[0] == second[0]).all() and torch.equal(first[1], second[1])


# ---- metrics and progress ---------------------------------------------------------------------

def test_metrics_are_means_since_the_last_log_with_perf_numbers(tmp_path):
    cfg = _config(tmp_path)
    (tmp_path / "run").mkdir()
    metrics = RunMetrics(cfg, tmp_path / "run", EpisodeTracker(2), Timing(), progress=False)
    try:
        metrics.record({"loss/a": torch.tensor(1.0), "charts/b": 2.0})
        metrics.record({"loss/a": torch.tensor(3.0), "charts/b": 4.0})
        assert metrics.flush() == {"loss/a": 2.0, "charts/b": 3.0}
        assert metrics.flush() == {}
        metrics.log(10, {"loss/a": 2.0})
    finally:
        metrics.close()
    with open(tmp_path / "run" / "metrics.csv") as f:
        names = {row["name"] for row in csv.DictReader(f)}
    assert {"loss/a", "perf/steps_per_s", "perf/env_fraction", "perf/other_fraction"} <= names


def test_a_diverged_loss_stops_the_run_with_one_line():
    assert check_finite({"loss/a": 1.0, "charts/x": math.nan}, 5, 0) == {"loss/a": 1.0, "charts/x": math.nan}
    with pytest.raises(DrivelabError, match="diverged at step 5: loss/a is nan.*step 0"):
        check_finite({"loss/a": math.nan}, 5, 0)


# ---- evaluation and the best checkpoint -------------------------------------------------------

def test_the_best_score_needs_a_higher_metric_or_on_a_tie_a_higher_return():
    summary = {"success_rate": 0.5, "return_mean": 10.0}
    assert new_best(summary, "success_rate", None) == [0.5, 10.0]
    assert new_best(summary, "success_rate", [0.5, 9.0]) == [0.5, 10.0]
    assert new_best(summary, "success_rate", [0.5, 10.0]) is None
    assert new_best(summary, "route_completion", None) is None  # a metric the env does not report


def test_local_evaluation_keeps_the_best_and_logs_eval_metrics(tmp_path):
    cfg = _config(tmp_path)
    (tmp_path / "run").mkdir()
    torch.manual_seed(0)
    policy, saved = _policy(cfg), []

    def save(name: str) -> Path:
        saved.append(name)
        (tmp_path / "run" / "checkpoints" / name).mkdir(parents=True, exist_ok=True)
        return tmp_path / "run" / "checkpoints" / name

    tracker = Tracker(tmp_path / "run", cfg)
    evaluation = RunEvaluation(cfg, tmp_path / "run", tracker, torch.device("cpu"), save, on_restart=print)
    try:
        first = evaluation.evaluate(500, policy)
        again = evaluation.evaluate(1000, policy)   # the same policy: the same episodes, not a new best
    finally:
        evaluation.close()
        tracker.close()
    assert first == again and first["episodes"] == 2 and policy.training
    assert saved == ["best"] and evaluation.best == [first["return_mean"], first["return_mean"]]
    assert json.loads((tmp_path / "run" / "checkpoints" / "best" / "eval.json").read_text())["step"] == 500


def test_the_ray_actor_body_plays_what_local_evaluation_plays(tmp_path):
    """One code path: the actor (called here in-process) gives the local summary, and a video
    as bytes when the result is a new best."""
    cfg = _config(tmp_path, eval={"video": True})
    torch.manual_seed(0)
    policy = _policy(cfg)
    envs = make_vector_env(eval_env_config(cfg), num_envs=1, autoreset_mode=AutoresetMode.DISABLED)
    try:
        local = evaluate_policy(envs, policy, cfg.eval.episodes, cfg.eval.seed)
    finally:
        envs.close()
    actor = EvalActor(eval_env_config(cfg), num_envs=1)
    try:
        summary, video, strip = actor.evaluate(policy, cfg.eval, None)
        assert summary == local and video[4:8] == b"ftyp" and strip.ndim == 3
        assert actor.evaluate(policy, cfg.eval, new_best(summary, "return_mean", None))[1:] == (None, None)
    finally:
        actor.close()


def test_the_evaluation_env_takes_the_eval_id_and_kwargs(tmp_path):
    cfg = _config(tmp_path, env={"kwargs": {"max_episode_steps": 50}}, eval={"kwargs": {"sutton_barto_reward": True}})
    assert eval_env_config(cfg).kwargs == {"max_episode_steps": 50, "sutton_barto_reward": True}
    other = _config(tmp_path, eval={"env_id": "Acrobot-v1", "kwargs": {}})
    assert eval_env_config(other).id == "Acrobot-v1" and eval_env_config(other).kwargs == {}


def test_another_env_id_keeps_the_kwargs_that_shape_the_observation():
    # MetaDrive's num_others adds 16 entries to the observation: a policy trained with it must
    # be evaluated with it, while the training set's scenario range and rewards stay behind
    cfg = EnvConfig(id="MetaDrive-1000envs-v0", obs_filters=["a"],
                    kwargs={"vehicle_config": {"lidar": {"num_others": 4}}, "success_reward": 30.0, "start_seed": 5})
    other = cfg.on("MetaDrive-validation-v0", {"traffic_density": 0.2})
    assert other.id == "MetaDrive-validation-v0" and other.obs_filters == ["a"]
    assert other.kwargs == {"vehicle_config": {"lidar": {"num_others": 4}}, "traffic_density": 0.2}
    assert cfg.kwargs["start_seed"] == 5 and cfg.id == "MetaDrive-1000envs-v0"


# ---- checkpoints and resume -------------------------------------------------------------------

def test_checkpoints_are_due_first_every_n_steps_and_at_the_end(tmp_path):
    cfg = _config(tmp_path, checkpoint_every=100)
    checkpoints = RunCheckpoints(cfg, tmp_path, np.random.default_rng(0), EpisodeTracker(2))
    assert checkpoints.due(0, done=False)
    checkpoints.last_step = 0
    assert not checkpoints.due(0, done=True) and not checkpoints.due(50, done=False)
    assert checkpoints.due(50, done=True) and checkpoints.due(100, done=False)


def test_a_checkpoint_holds_the_resume_state_and_a_resume_restores_it(tmp_path):
    cfg = _config(tmp_path)
    rng, episodes = np.random.default_rng(0), EpisodeTracker(2)
    episodes.step(np.ones(2), np.array([True, False]), {})
    checkpoints = RunCheckpoints(cfg, tmp_path, rng, episodes)
    checkpoints.modules = {"policy": torch.nn.Linear(2, 2)}
    checkpoints.save(40, iteration=4, best=[1.0, 2.0], extra_state=lambda: ({"buffer": torch.ones(3)}, {"n": 3}))
    assert checkpoints.last_step == 40
    expected = rng.integers(0, 1000, 4)

    again_rng, again_episodes = np.random.default_rng(99), EpisodeTracker(2)
    again = RunCheckpoints(cfg, tmp_path, again_rng, again_episodes)
    assert again.resume(load_checkpoint(tmp_path)) == (40, 4, [1.0, 2.0])
    assert (again_rng.integers(0, 1000, 4) == expected).all()
    assert list(again_episodes.returns) == [1.0] and again.last_step == 40


def test_a_diverged_network_is_never_saved(tmp_path):
    cfg = _config(tmp_path)
    checkpoints = RunCheckpoints(cfg, tmp_path, np.random.default_rng(0), EpisodeTracker(2))
    net = torch.nn.Linear(2, 2)
    with torch.no_grad():
        net.weight[0, 0] = math.inf
    checkpoints.modules = {"policy": net}
    with pytest.raises(DrivelabError, match="'policy' weight weight is not finite; not saved"):
        checkpoints.save(10, iteration=1, best=None)
    assert not (tmp_path / "checkpoints").exists() or not any((tmp_path / "checkpoints").iterdir())
