"""The Ray backend on a real local Ray cluster: started here with `ray start --head` on 127.0.0.1,
joined by address like a remote one, stopped at the end."""

from __future__ import annotations

import csv
import fcntl
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

import drivelab  # noqa: E402
from flaky_env import importable_env  # noqa: E402
from drivelab.errors import DrivelabError  # noqa: E402

RAY = str(Path(sys.executable).with_name("ray"))


@pytest.fixture(scope="module")
def cluster():
    """The address of a fresh one-node Ray cluster (4 logical CPUs, no dashboard, no token auth).

    `ray stop --force` stops every Ray process of the machine, so the pytest-xdist workers take
    turns: each holds a machine-wide lock while its cluster lives (the other waits for it)."""
    lock = open(Path(tempfile.gettempdir()) / "drivelab-tests-ray.lock", "w")
    fcntl.flock(lock, fcntl.LOCK_EX)
    try:
        yield from _cluster()
    finally:
        lock.close()


def _cluster():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    temp = tempfile.mkdtemp(prefix="dlray", dir="/tmp")  # short: Ray's socket paths must stay < 108 chars
    # Ray workers inherit the cluster's environment: with tests/ on their path they import the test
    # env modules, as a real cluster would have a user's env package installed.
    env = importable_env({**os.environ, "RAY_AUTH_MODE": "disabled"})
    os.environ["RAY_AUTH_MODE"] = "disabled"
    subprocess.run([RAY, "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port), "--num-cpus", "4",
                    "--temp-dir", temp, "--include-dashboard", "false", "--disable-usage-stats",
                    "--object-store-memory", "100000000"], check=True, capture_output=True, env=env, timeout=120)
    address = f"127.0.0.1:{port}"
    ray.init(address=address, log_to_driver=False)
    try:
        yield address
    finally:
        ray.shutdown()
        subprocess.run([RAY, "stop", "--force"], capture_output=True, env=env, timeout=120)
        shutil.rmtree(temp, ignore_errors=True)


def metrics(run_dir: Path) -> list[tuple[str, str, str]]:
    """(step, name, value) rows, without the wall-clock-dependent perf/* ones."""
    with open(run_dir / "metrics.csv", newline="") as f:
        return [(r["step"], r["name"], r["value"]) for r in csv.DictReader(f) if not r["name"].startswith("perf/")]


@pytest.mark.parametrize("algo, env, extra", [
    ("ppo", "CartPole-v1", {"ppo": {"num_steps": 128}}),
    ("sac", "Pendulum-v1", {"sac": {"learning_starts": 200, "batch_size": 32}}),
])
def test_training_on_ray_actors_equals_the_local_backend(algo, env, extra, cluster, tmp_path):
    """Same seed, same envs: the Ray backend (2 actors x 2 envs) gives the local run's metrics exactly."""
    runs = {}
    for backend in ("sync", "ray"):
        env_section = {"id": env, "num_envs": 4, "backend": backend, "envs_per_actor": 2, "actor_cpus": 0.5}
        runs[backend] = drivelab.train(algo, env_section, steps=1200, seed=3, run_dir=tmp_path / backend,
                                       progress=False, ray_address=cluster, log_every=200, **extra).run_dir
    local, remote = metrics(runs["sync"]), metrics(runs["ray"])
    assert {name for _, name, _ in remote} >= {"episode/return", "episode/length"}
    assert remote == local


def test_multiagent_scenes_train_on_ray_actors_as_in_subprocesses(cluster, tmp_path):
    """IPPO on MetaDrive's Intersection (two scenes of four cars): the same metrics on Ray actors as
    in local subprocesses, so a multi-agent run scales out with env.backend: ray unchanged."""
    runs = {}
    for backend in ("async", "ray"):
        env_section = {"id": "MultiAgentIntersection-v0", "num_envs": 2, "backend": backend, "actor_cpus": 0.5,
                       "kwargs": {"num_agents": 4, "horizon": 60}}
        runs[backend] = drivelab.train("ippo", env_section, steps=128, seed=3, run_dir=tmp_path / backend,
                                       progress=False, ray_address=cluster, log_every=64, eval={"every": 0},
                                       ippo={"num_steps": 32, "hidden": [32, 32]}).run_dir
    local, remote = metrics(runs["async"]), metrics(runs["ray"])
    assert {name for _, name, _ in remote} >= {"episode/return", "charts/live_agents"}
    assert remote == local


def test_a_killed_env_actor_is_replaced_and_the_run_completes(cluster, tmp_path, run_cli):
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "drivelab", "train", "--algo", "ppo", "--env", "CartPole-v1",
                             "--steps", "6000", "--num-envs", "2", "--env.backend", "ray", "--env.actor_cpus", "0.5",
                             "--ppo.num_steps", "128", "--log-every", "256", "--run-dir", str(run_dir),
                             "--ray-address", cluster, "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "RAY_AUTH_MODE": "disabled"})
    try:
        deadline = time.time() + 120
        while not (run_dir / "metrics.csv").is_file() or (run_dir / "metrics.csv").stat().st_size < 200:
            assert proc.poll() is None and time.time() < deadline, proc.communicate()
            time.sleep(0.2)
        pids = subprocess.run(["pgrep", "-f", "ray::EnvGroup"], capture_output=True, text=True).stdout.split()
        assert pids
        os.kill(int(pids[-1]), signal.SIGKILL)  # the newest env actor: this run's
        out, err = proc.communicate(timeout=240)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "Ray env actor" in err and "restarting it" in err and "Traceback" not in err
    restarts = [float(v) for _, name, v in metrics(run_dir) if name == "env/restarts"]
    assert restarts and restarts[-1] >= 1
    assert any(name == "episode/return" and int(step) > 4000 for step, name, _ in metrics(run_dir))


def test_repeated_env_failures_stop_the_run_with_one_line_and_an_intact_checkpoint(cluster, tmp_path):
    env = {"id": "flaky_env:Flaky-v0", "num_envs": 2, "backend": "ray", "actor_cpus": 0.5, "max_restarts": 0,
           "kwargs": {"fail": "raise", "at_step": 30, "marker": str(tmp_path / "failed")}}
    with pytest.raises(DrivelabError, match=r"the env failed 1 times .*RuntimeError: the simulator crashed"):
        drivelab.train("ppo", env, steps=2000, run_dir=tmp_path / "run", progress=False, ray_address=cluster,
                       ppo={"num_steps": 64})
    assert drivelab.load(tmp_path / "run").checkpoint.name == "step_000000000000"


def test_evaluation_runs_on_its_own_ray_actor_while_training_goes_on(cluster, tmp_path):
    result = drivelab.train("ppo", {"id": "CartPole-v1", "num_envs": 2}, steps=2048, run_dir=tmp_path / "run",
                            progress=False, ray_address=cluster, ppo={"num_steps": 128},
                            eval={"every": 512, "episodes": 3, "backend": "ray", "video": False})
    rows = metrics(result.run_dir)
    eval_steps = sorted({int(step) for step, name, _ in rows if name == "eval/return_mean"})
    assert eval_steps == [512, 1024, 1536, 2048]
    best = json.loads((result.run_dir / "checkpoints" / "best" / "eval.json").read_text())
    assert best["step"] in eval_steps and best["episodes"] == 3
    assert not (result.run_dir / "checkpoints" / ".eval_pending").exists() or best["step"] != 2048
    policy = drivelab.load(result.run_dir / "checkpoints" / "best")
    assert policy.act(np.zeros(4, np.float32)).shape == ()


def test_sweep_of_two_settings_and_two_seeds_writes_its_table(cluster, tmp_path, run_cli):
    config = tmp_path / "sweep.yaml"
    config.write_text("algo: ppo\nsteps: 1024\nenv: {id: CartPole-v1, num_envs: 2}\nppo: {num_steps: 128}\n"
                      "eval: {every: 1024, episodes: 2, video: false}\n")
    out = tmp_path / "sweep"
    done = subprocess.run([sys.executable, "-m", "drivelab", "sweep", str(config), "--grid", "ppo.lr=0.0003,0.001",
                           "--seeds", "0-1", "--out", str(out), "--ray-address", cluster],
                          capture_output=True, text=True, timeout=400, env={**os.environ, "RAY_AUTH_MODE": "disabled"})
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((out / "sweep.json").read_text())
    assert [s["name"] for s in summary["settings"]] == ["lr=0.0003", "lr=0.001"]
    for setting in summary["settings"]:
        assert setting["metrics"]["eval/return_mean"][2] == 2          # two seeds each
        assert setting["metrics"]["episode/return"][0] > 0
    assert "| lr=0.0003 |" in done.stdout and (out / "sweep.md").is_file()
    assert (out / "curves.png").stat().st_size > 0 and (out / "final.png").stat().st_size > 0
    assert sorted(p.name for p in out.iterdir() if (p / "metrics.csv").is_file()) == \
        ["lr=0.0003-s0", "lr=0.0003-s1", "lr=0.001-s0", "lr=0.001-s1"]
    # Run again: every run is finished, so nothing is trained twice and Ray Tune is not started.
    before = (out / "lr=0.001-s1" / "metrics.csv").read_text()
    tune_state = sorted((out / ".tune").rglob("*"))
    again = subprocess.run([sys.executable, "-m", "drivelab", "sweep", str(config), "--grid", "ppo.lr=0.0003,0.001",
                            "--seeds", "0-1", "--out", str(out), "--ray-address", cluster],
                           capture_output=True, text=True, timeout=400, env={**os.environ, "RAY_AUTH_MODE": "disabled"})
    assert again.returncode == 0, again.stderr[-3000:]
    assert (out / "lr=0.001-s1" / "metrics.csv").read_text() == before
    assert sorted((out / ".tune").rglob("*")) == tune_state and "| lr=0.001  |" in again.stdout


def test_an_optuna_search_of_four_trials_with_asha_ranks_them_in_its_table(cluster, tmp_path):
    config = tmp_path / "search.yaml"
    config.write_text("algo: ppo\nsteps: 1024\nenv: {id: CartPole-v1, num_envs: 2}\nppo: {num_steps: 64}\n"
                      "eval: {every: 256, episodes: 2, video: false}\n"
                      "sweep: {search: {trials: 4, metric: eval/return_mean, asha: true,\n"
                      "                 space: {ppo.lr: [loguniform, 0.0001, 0.01], ppo.num_steps: [choice, 64, 128]}}}\n")
    out = tmp_path / "search"
    done = subprocess.run([sys.executable, "-m", "drivelab", "sweep", str(config), "--out", str(out),
                           "--env", "flaky_env:TallyEnv",   # a user's env class: the cluster imports it
                           "--ray-address", cluster], capture_output=True, text=True, timeout=400, env=importable_env())
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((out / "sweep.json").read_text())
    trials = summary["trials"]
    assert len(trials) == 4 and all(t["metric"] is not None for t in trials)
    assert [t["metric"] for t in trials] == sorted((t["metric"] for t in trials), reverse=True)   # best first
    assert all(t["setting"]["ppo.num_steps"] in (64, 128) and 1e-4 <= t["setting"]["ppo.lr"] <= 1e-2 for t in trials)
    for t in trials:   # each a normal run, trained to the end or stopped by ASHA at an evaluation
        assert t["step"] == 1024 or (t["stopped_early"] and t["step"] % 256 == 0), t
        assert (out / t["run"] / "checkpoints").is_dir()
        assert "flaky_env:TallyEnv" in (out / t["run"] / "config.yaml").read_text()
    assert summary["best"]["run"] in done.stdout and "| run " in done.stdout
    assert "Token authentication" not in done.stdout + done.stderr and "tensorboard" not in done.stdout.lower()
    assert (out / "sweep.md").is_file() and (out / "curves.png").stat().st_size > 0


def test_search_input_errors_are_one_line(tmp_path, run_cli):
    config = tmp_path / "s.yaml"
    config.write_text("algo: ppo\nsteps: 1024\nenv: {id: CartPole-v1}\n")
    for flags, message in ((["--space", "ppo.lr=normal:1,2"], "--space"),
                           (["--space", "ppo.lr=loguniform:0,1"], "low > 0"),
                           (["--space", "ppo.lr=uniform:0.1,0.2", "--seeds", "0-1"], "one seed per trial"),
                           (["--space", "ppo.lr=uniform:0.1,0.2", "--grid", "ppo.gamma=0.9"], "not both")):
        out = run_cli("sweep", config, *flags)
        assert out.returncode == 2 and out.stderr.count("\n") == 1 and message in out.stderr, (flags, out.stderr)


def test_bad_ray_input_is_one_line(tmp_path, run_cli):
    out = run_cli("sweep", "nonexistent.yaml", "--grid", "ppo.lr=1")
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "config file not found" in out.stderr
    out = run_cli("train", "--algo", "ppo", "--env", "CartPole-v1", "--env.backend", "rays", "--run-dir", tmp_path / "r")
    assert out.returncode == 2 and "env.backend" in out.stderr and out.stderr.count("\n") == 1
    out = run_cli("train", "--algo", "ppo", "--env", "MetaDrive-10env-v0", "--env.backend", "ray",
                  "--env.envs_per_actor", "2", "--run-dir", tmp_path / "r")
    assert out.returncode == 2 and "envs_per_actor" in out.stderr


def test_merge_infos_keeps_gymnasiums_layout():
    from drivelab.envs.ray_backend import merge_infos

    a = {"speed": np.array([1.0, 2.0]), "_speed": np.array([True, False]),
         "final_info": {"crash": np.array([True, False]), "_crash": np.array([True, False])},
         "_final_info": np.array([True, False])}
    b = {"speed": np.array([3.0]), "_speed": np.array([True]), "name": np.array(["x"], dtype=object)}
    merged = merge_infos([(slice(0, 2), a), (slice(2, 3), b)], 3)
    assert merged["speed"][[0, 2]].tolist() == [1.0, 3.0] and merged["_speed"].tolist() == [True, False, True]
    assert merged["name"][2] == "x" and merged["_name"].tolist() == [False, False, True]
    assert merged["final_info"]["crash"].tolist() == [True, False, False]
    assert merged["_final_info"].tolist() == [True, False, False]
    # an env's value may be an array (a multi-agent scene's slots): stacked as (n, K)
    slots = merge_infos([(slice(0, 1), {"alive": np.array([[True, False]])}),
                         (slice(1, 2), {"alive": np.array([[False, True]])})], 2)
    assert slots["alive"].tolist() == [[True, False], [False, True]] and slots["_alive"].tolist() == [True, True]


def test_sweep_plan_grid_and_seeds():
    from drivelab.tools.sweep import parse_grid, parse_seeds, plan

    grid = parse_grid(["ppo.lr=1e-4,3e-4", "env.kwargs.num_scenarios=1,10"])
    assert grid == {"ppo.lr": [1e-4, 3e-4], "env.kwargs.num_scenarios": [1, 10]}
    assert parse_seeds("0-2") == [0, 1, 2] and parse_seeds("0,5") == [0, 5]
    trials = plan(grid, [0, 1])
    assert len(trials) == 8 and trials[0].name == "lr=0.0001,num_scenarios=1-s0"
    with pytest.raises(DrivelabError, match="--grid"):
        parse_grid(["ppo.lr"])
    with pytest.raises(DrivelabError, match="--seeds"):
        parse_seeds("a-b")
