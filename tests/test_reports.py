"""Seeing what the agent does: videos, curves, the HTML report, MLflow round trips."""

import base64
import json
import re
import socket
import subprocess
import sys
import time

import imageio.v2 as imageio
import numpy as np
import pytest

import drivelab
from drivelab.training.outputs.statistics import mean_and_band, rolling_mean
from processes import run_drivelab


@pytest.fixture(scope="module")
def cartpole_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("runs") / "cp"
    drivelab.train("ppo", "CartPole-v1", steps=3072, seed=0, num_envs=2, run_dir=run_dir, progress=False,
                   ppo={"num_steps": 256}, eval={"every": 1024, "episodes": 2})
    return run_dir


def test_video_has_the_frames_of_its_episodes_and_decodes(cartpole_run, run_cli, tmp_path):
    out = run_cli("eval", cartpole_run, "--episodes", "2", "--video", tmp_path / "v.mp4", "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    reader = imageio.get_reader(tmp_path / "v.mp4")
    frames = reader.count_frames()
    first = reader.get_data(0)
    # one frame after each reset and one after each step: length + 1 per episode
    assert frames == round(2 * (result["length_mean"] + 1)) and first.shape == (400, 600, 3)
    plain = run_cli("eval", cartpole_run, "--episodes", "1", "--video-dir", tmp_path / "dir", "--no-overlay")
    assert plain.returncode == 0, plain.stderr
    bare = imageio.get_reader(tmp_path / "dir" / "episode_000.mp4").get_data(0)
    # the overlay darkens the top-left band and writes on it; without it the frame is the env's own
    assert first[:20, :200].mean() < bare[:20, :200].mean() - 50


@pytest.mark.parametrize("repeat", [1, 2])
def test_video_of_an_action_repeat_env_keeps_real_time(tmp_path, repeat):
    from gymnasium.vector import AutoresetMode

    from drivelab.envs import EnvConfig, make_vector_env
    from drivelab.training.outputs.video import Recorder

    envs = make_vector_env(EnvConfig(id="CartPole-v1", num_envs=1, action_repeat=repeat),
                           autoreset_mode=AutoresetMode.DISABLED, render_mode="rgb_array")
    recorder = Recorder(tmp_path / "v.mp4", fps=10)
    try:
        _, info = envs.reset(seed=0)
        recorder.start(envs, info, 0)
        for _ in range(3):
            _, reward, _, _, info = envs.step(np.zeros(1, np.int64))
            recorder.step(envs, np.zeros(1), float(reward[0]), info, False)
    finally:
        recorder.close()
        envs.close()
    # one frame per decision, each held for `repeat` env steps: the recorder's 10 fps / repeat
    assert imageio.get_reader(tmp_path / "v.mp4").get_meta_data()["fps"] == pytest.approx(10 / repeat)


def test_training_keeps_the_best_checkpoint_and_films_it(cartpole_run):
    best = json.loads((cartpole_run / "checkpoints" / "best" / "eval.json").read_text())
    videos = sorted((cartpole_run / "videos").glob("step_*.mp4"))
    assert videos and videos[-1].name == f"step_{best['step']:012d}.mp4"
    assert imageio.get_reader(videos[-1]).count_frames() > 5


def test_rolling_mean_and_confidence_band():
    np.testing.assert_allclose(rolling_mean(np.array([1.0, 2.0, 3.0, 4.0]), 2), [1.0, 1.5, 2.5, 3.5])
    x = np.array([0.0, 1.0, 2.0])
    grid, mean, low, high = mean_and_band([(x, np.array([1.0, 1.0, 1.0])), (x, np.array([3.0, 3.0, 3.0]))], points=3)
    np.testing.assert_allclose(mean, 2.0)
    # two seeds 2 apart: std 1.414, sem 1, t(0.975, 1 dof) = 12.706
    np.testing.assert_allclose(high - mean, 12.706, rtol=1e-3)


def test_plot_draws_the_default_panels_and_groups_seeds(cartpole_run, run_cli, tmp_path):
    out = run_cli("plot", cartpole_run, "--out", tmp_path / "one.png")
    assert out.returncode == 0, out.stderr
    image = imageio.imread(tmp_path / "one.png")
    assert image.shape[0] > 500 and image.shape[1] > 1000  # a grid of panels
    for seed in (1, 2):
        drivelab.train("ppo", "CartPole-v1", steps=1024, seed=seed, num_envs=2, run_dir=tmp_path / f"s{seed}",
                       progress=False, ppo={"num_steps": 256})
    from drivelab.training.outputs.plots import group_runs

    groups = group_runs([tmp_path / "s1", tmp_path / "s2", cartpole_run])
    assert sorted(len(members) for members in groups.values()) == [1, 2]
    out = run_cli("plot", tmp_path / "s1", tmp_path / "s2", "--metric", "episode/return", "--out", tmp_path / "g.png")
    assert out.returncode == 0 and (tmp_path / "g.png").stat().st_size > 10_000


def test_report_is_one_self_contained_html_file(cartpole_run, run_cli):
    out = run_cli("report", cartpole_run, "--episodes", "2")
    assert out.returncode == 0, out.stderr
    page = (cartpole_run / "report.html").read_text()
    # nothing to fetch: no http(s) sources, images and the video embedded as data URIs
    assert not re.search(r'(src|href)="(https?:)?//', page)
    images = re.findall(r'<img alt="[^"]*" src="data:image/png;base64,([^"]+)"', page)
    videos = re.findall(r'<video controls muted src="data:video/mp4;base64,([^"]+)"', page)
    assert images and len(videos) == 1
    assert base64.b64decode(images[0])[:8] == b"\x89PNG\r\n\x1a\n" and len(base64.b64decode(videos[0])) > 1000
    assert "random baseline" in page and "best checkpoint" in page and "full config" in page


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def mlflow_server(tmp_path):
    """A real MLflow tracking server on 127.0.0.1, stopped after the test."""
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port),
                               "--backend-store-uri", f"sqlite:///{tmp_path / 'server.db'}",
                               "--artifacts-destination", str(tmp_path / "server-artifacts"), "--workers", "1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    uri = f"http://127.0.0.1:{port}"
    try:
        for _ in range(120):
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=1):
                    break
            except OSError:
                time.sleep(0.5)
        else:
            pytest.fail("mlflow server did not start")
        yield uri
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_mlflow_round_trip_through_a_tracking_server(mlflow_server, run_cli, tmp_path):
    run_dir = tmp_path / "trained"
    out = run_cli("train", "--algo", "ppo", "--env", "CartPole-v1", "--steps", "1024", "--num-envs", "2",
                  "--ppo.num_steps", "256", "--run-dir", run_dir, "--mlflow-uri", mlflow_server, "--mlflow",
                  "--no-progress")
    assert out.returncode == 0, out.stderr
    run_id = (run_dir / "mlflow_run_id").read_text().strip()
    import mlflow

    run = mlflow.MlflowClient(tracking_uri=mlflow_server).get_run(run_id)
    assert run.data.tags["algo"] == "ppo" and "episode/return" in run.data.metrics
    fresh = tmp_path / "elsewhere"
    fresh.mkdir()
    ev = run_drivelab("eval", f"mlflow:{run_id}", "--mlflow-uri", mlflow_server, "--episodes", "2", "--json",
                      cwd=fresh, timeout=300)
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout.strip().splitlines()[-1])["step"] == 1024
    resumed = run_drivelab("train", "--resume", f"mlflow:{run_id}", "--steps", "2048", "--mlflow-uri", mlflow_server,
                           "--no-progress", cwd=fresh, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert (fresh / "runs" / f"mlflow-{run_id}" / "checkpoints" / "step_000000002048").is_dir()
    metrics = mlflow.MlflowClient(tracking_uri=mlflow_server).get_metric_history(run_id, "perf/steps_per_s")
    assert max(m.step for m in metrics) == 2048   # the resumed run logged into the same MLflow run
