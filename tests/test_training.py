"""End-to-end training: determinism, exact resume, tracking, evaluation, and learning."""

import csv
import json

import pytest
import torch
from safetensors.torch import load_file

from drivelab.training.outputs.checkpoint import checkpoint_step, resolve_checkpoint
from drivelab.api import build_config
from drivelab.api import evaluate_checkpoint
from drivelab.api import train


def _cartpole(run_dir, steps, **extra):
    data = {"algo": "reinforce", "steps": steps, "seed": 3, "run_dir": str(run_dir), "checkpoint_every": 1,
            "env": {"id": "CartPole-v1", "num_envs": 4}, "reinforce": {"batch_steps": 1000, "lr": 0.01}}
    data.update(extra)
    return build_config(data)


def _weights(run_dir):
    tensors = load_file(str(resolve_checkpoint(run_dir) / "tensors.safetensors"))
    return {k: v for k, v in tensors.items() if k.startswith("module/")}


def _metrics(run_dir):
    with open(run_dir / "metrics.csv") as f:
        return [(r["step"], r["name"], r["value"]) for r in csv.DictReader(f) if not r["name"].startswith("perf/")]


def test_same_seed_same_metrics_and_interrupted_run_resumes_exactly(tmp_path):
    straight, again, split = tmp_path / "straight", tmp_path / "again", tmp_path / "split"
    train(_cartpole(straight, 6000), progress=False)
    train(_cartpole(again, 6000), progress=False)
    assert _metrics(straight) == _metrics(again), "same seed -> identical metrics"

    # "killed" after ~3000 steps (stopped by a callback: the same config, as a requeued job has)
    train(_cartpole(split, 6000), progress=False, callback=lambda event: event.step < 3000)
    assert 3000 <= checkpoint_step(resolve_checkpoint(split)) < 6000
    with open(split / "metrics.csv", "a") as f:            # a row written after the last checkpoint
        f.write("999999,0,episode/return,1\n")
    train(run_dir=split, resume=True, steps=6000, progress=False)   # the run's saved config, as `train --resume`
    a, b = _weights(straight), _weights(split)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert resolve_checkpoint(split).name == resolve_checkpoint(straight).name
    assert _metrics(split) == _metrics(straight), "the resumed history equals the uninterrupted one"
    assert list((split / "tb").glob("events.out.tfevents.*"))


def test_mlflow_tracking_in_the_project_store_beside_the_run_directories(tmp_path):
    import mlflow

    run_dir = tmp_path / "ml"
    train(_cartpole(run_dir, 1000, track={"mlflow": True, "experiment": "drivelab-test"}), progress=False)
    run_id = (run_dir / "mlflow_run_id").read_text().strip()
    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")   # one store per project
    run = client.get_run(run_id)
    assert "episode/return" in run.data.metrics and run.data.params["reinforce.lr"] == "0.01"


def test_wandb_tracking_offline_writes_its_run_files_and_a_resumed_run_continues_it(tmp_path):
    pytest.importorskip("wandb")
    run_dir = tmp_path / "wb"
    track = {"wandb": True, "wandb_mode": "offline", "wandb_project": "drivelab-test"}
    train(_cartpole(run_dir, 1000, track=track), progress=False)
    run_id = (run_dir / "wandb_run_id").read_text().strip()
    train(run_dir=run_dir, resume=True, steps=2000, progress=False)
    runs = sorted((run_dir / "wandb").glob(f"offline-run-*-{run_id}"))
    assert runs, "the offline run lies in RUN/wandb"
    logged = b"".join(path.read_bytes() for run in runs for path in run.glob("*.wandb"))
    assert b"episode/return" in logged and b"loss/policy" in logged and b"reinforce" in logged


def test_evaluation_is_deterministic_and_reports_json_keys(tmp_path):
    train(_cartpole(tmp_path / "r", 2000), progress=False)
    first, _, _ = evaluate_checkpoint(tmp_path / "r", episodes=5, num_envs=2)
    second, _, _ = evaluate_checkpoint(tmp_path / "r", episodes=5, num_envs=3)
    assert first.returns.tolist() == second.returns.tolist(), "episode k's seed does not depend on num_envs"
    assert set(first.summary()) >= {"return_mean", "return_std", "episodes"} and first.summary()["episodes"] == 5
    # Sampled actions repeat with the seed too.
    sampled = [evaluate_checkpoint(tmp_path / "r", episodes=5, num_envs=2, seed=s, deterministic=False)[0]
               .returns.tolist() for s in (0, 0, 1)]
    assert sampled[0] == sampled[1] != sampled[2]


@pytest.mark.slow
def test_reinforce_solves_cartpole(tmp_path):
    cfg = build_config({"algo": "reinforce", "steps": 100_000, "seed": 0, "run_dir": str(tmp_path / "cp"),
                        "env": {"id": "CartPole-v1", "num_envs": 8}, "reinforce": {"lr": 0.01, "batch_steps": 4000}})
    train(cfg, progress=False)
    result, _, _ = evaluate_checkpoint(tmp_path / "cp", episodes=20)
    assert result.summary()["return_mean"] >= 195


def test_cli_train_resume_eval_on_metadrive(tmp_path, run_cli):
    run_dir = tmp_path / "md"
    # num_others adds the 4 nearest vehicles to the observation (275-d): evaluating on another
    # env id below must keep it, or the policy would see the 259-d layout
    common = ["--env.kwargs.horizon", "60", "--env.kwargs.traffic_density", "0.0", "--reinforce.batch_steps", "100",
              "--env.kwargs.vehicle_config.lidar.num_others", "4"]
    out = run_cli("train", "--algo", "reinforce", "--env", "MetaDrive-10env-v0", "--actions", "3x3", "--steps", "100",
                  "--num-envs", "1", "--run-dir", run_dir, "--no-progress", *common)
    assert out.returncode == 0, out.stderr
    assert (run_dir / "config.yaml").is_file() and (run_dir / "metrics.csv").is_file()
    assert list((run_dir / "tb").glob("events.out.tfevents.*"))
    first = resolve_checkpoint(run_dir)
    assert (first / "tensors.safetensors").is_file()

    out = run_cli("train", "--resume", run_dir, "--steps", "200", "--no-progress")
    assert out.returncode == 0, out.stderr
    assert resolve_checkpoint(run_dir).name > first.name

    out = run_cli("eval", run_dir, "--episodes", "2", "--env", "MetaDrive-validation-v0",
                  "--env-kwarg", "horizon=60", "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["episodes"] == 2 and result["env"] == "MetaDrive-validation-v0"
    for key in ("return_mean", "return_std", "success_rate", "crash_rate", "out_of_road_rate", "route_completion"):
        assert key in result
    table = run_cli("eval", run_dir, "--episodes", "1", "--env-kwarg", "horizon=30")
    assert "route completion" in table.stdout and "out-of-road rate" in table.stdout


@pytest.mark.parametrize("args, fragment", [
    (["train", "--algo", "dqn", "--env", "CartPole-v1"], "unknown algorithm 'dqn'"),
    (["train", "--env", "CartPol-v1"], "unknown env id 'CartPol-v1'"),
    (["train", "--env", "CartPole-v1", "--reinforce.lrate", "0.1"], "lrate"),
    (["train", "--config", "missing.yaml"], "missing.yaml"),
    (["eval", "no/such/run"], "no/such/run"),
    (["train", "--resume", "no/such/run"], "no/such/run"),
])
def test_bad_input_is_one_line_without_traceback(args, fragment, run_cli, tmp_path):
    out = run_cli(*args, "--steps", "10", "--run-dir", tmp_path / "x") if args[0] == "train" and "--resume" not in args \
        else run_cli(*args)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    lines = [line for line in out.stderr.strip().splitlines() if line]
    assert len(lines) == 1 and fragment in lines[0], out.stderr


def test_max_minutes_stops_training_with_a_final_checkpoint(tmp_path):
    # 6 s: the clock starts before the env processes do, and the first 1000-step batch must fit
    # in what is left on a loaded machine (1.8 s once ended a run at step 0 beside other tests)
    cfg = _cartpole(tmp_path / "t", 10**9, max_minutes=0.1)
    train(cfg, progress=False)
    last = resolve_checkpoint(tmp_path / "t")
    assert 0 < int(last.name.split("_")[-1]) < 10**6


def test_updates_run_with_update_threads_and_collection_goes_back_to_torch_threads():
    from drivelab.training.run.timing import Timing

    outside = torch.get_num_threads()
    timing = Timing(update_threads=outside + 1)
    with timing.update:
        assert torch.get_num_threads() == outside + 1
    assert torch.get_num_threads() == outside and timing.update.seconds > 0
    with Timing().update:            # None: the update keeps torch_threads
        assert torch.get_num_threads() == outside


def test_eval_final_weighs_the_policy_the_run_ends_with(tmp_path):
    from drivelab.training.outputs.plots import read_metrics

    for final, expected in ((False, [256]), (True, [256, 384])):
        run_dir = tmp_path / f"final_{final}"
        train(build_config({"algo": "ppo", "steps": 384, "seed": 0, "run_dir": str(run_dir),
                            "env": {"id": "CartPole-v1", "num_envs": 2}, "ppo": {"num_steps": 64},
                            "eval": {"every": 256, "episodes": 2, "final": final}}), progress=False)
        steps, _, _ = read_metrics(run_dir)["eval/return_mean"]
        assert list(steps) == expected
