"""Nothing lost: interrupts checkpoint, one writer per run, damaged files are refused or skipped,
a diverged run stops with one line and never saves non-finite weights."""

import json
import signal
import subprocess
import sys
import time

import pytest

from drivelab.checkpoint import list_checkpoints

TRAIN = ["-m", "drivelab", "train", "--algo", "ppo", "--env", "CartPole-v1", "--num-envs", "2", "--no-progress"]


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.strip().splitlines() if line and not line.startswith("drivelab: warning")]
    assert "Traceback" not in stderr and len(lines) == 1, stderr
    return lines[0]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_the_run_with_a_checkpoint_that_resumes(sig, tmp_path):
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, *TRAIN, "--steps", "100000000", "--run-dir", str(run_dir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (run_dir / "metrics.csv").is_file() or (run_dir / "metrics.csv").stat().st_size < 500:
        assert time.time() < deadline and proc.poll() is None
        time.sleep(0.2)
    started = time.time()
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=30)
    assert time.time() - started < 10 and proc.returncode == 130
    assert "--resume" in _one_line(stderr)
    step = int(list_checkpoints(run_dir)[-1].name.split("_")[-1])
    assert step > 0 and not list((run_dir / "checkpoints").glob(".tmp_*"))
    resumed = subprocess.run([sys.executable, "-m", "drivelab", "train", "--resume", str(run_dir), "--steps",
                              str(step + 4096), "--no-progress"], capture_output=True, text=True, timeout=120)
    assert resumed.returncode == 0, resumed.stderr
    assert int(list_checkpoints(run_dir)[-1].name.split("_")[-1]) >= step + 4096


def test_a_second_writer_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    first = subprocess.Popen([sys.executable, *TRAIN, "--steps", "100000000", "--run-dir", str(run_dir)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while not (run_dir / ".lock").is_file():
            assert time.time() < deadline
            time.sleep(0.1)
        time.sleep(1.0)
        second = subprocess.run([sys.executable, "-m", "drivelab", "train", "--resume", str(run_dir), "--steps",
                                 "200000000", "--no-progress"], capture_output=True, text=True, timeout=60)
        assert second.returncode == 2 and "in use by another drivelab process" in _one_line(second.stderr)
    finally:
        first.kill()
        first.wait()
    # a killed writer leaves no stuck lock: the run can be resumed at once
    again = subprocess.run([sys.executable, "-m", "drivelab", "train", "--resume", str(run_dir), "--steps",
                            str(int(list_checkpoints(run_dir)[-1].name.split("_")[-1]) + 2048), "--no-progress"],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr


def _short_run(run_dir):
    from drivelab.api import build_config, train

    train(build_config({"algo": "ppo", "steps": 3072, "seed": 0, "run_dir": str(run_dir), "checkpoint_every": 1024,
                        "env": {"id": "CartPole-v1", "num_envs": 2}, "ppo": {"num_steps": 256}}), progress=False)


def test_damaged_files_are_skipped_or_refused_in_one_line(tmp_path, run_cli):
    run_dir = tmp_path / "run"
    _short_run(run_dir)
    newest, older = list_checkpoints(run_dir)[-1], list_checkpoints(run_dir)[-2]
    (newest / "tensors.safetensors").write_bytes((newest / "tensors.safetensors").read_bytes()[:100])  # torn write
    out = run_cli("eval", run_dir, "--episodes", "1", "--json")
    assert out.returncode == 0 and "using the newest intact checkpoint" in out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1])["checkpoint"] == str(older)
    for bad in ("{}", "[1, 2]", "not json"):
        (older / "state.json").write_text(bad)
        out = run_cli("eval", older, "--episodes", "1")
        assert out.returncode == 2 and str(older / "state.json") in _one_line(out.stderr)
    # an emptied metrics.csv (killed before its first flush) and a stale temp checkpoint: resume works
    (run_dir / "metrics.csv").write_text("")
    (run_dir / "checkpoints" / ".tmp_step_000000009999_1").mkdir()
    out = run_cli("train", "--resume", run_dir, "--steps", "5000", "--no-progress")
    assert out.returncode == 0, out.stderr
    assert not list((run_dir / "checkpoints").glob(".tmp_*"))


def test_divergence_stops_the_run_and_saves_no_non_finite_weights(tmp_path, run_cli):
    out = run_cli("train", "--algo", "sac", "--env", "Pendulum-v1", "--steps", "3000", "--sac.learning_starts", "200",
                  "--sac.actor_lr", "1e6", "--sac.critic_lr", "1e6", "--run-dir", tmp_path / "d", "--no-progress")
    assert out.returncode == 2 and "diverged" in _one_line(out.stderr)
    from safetensors.torch import load_file
    import torch

    for checkpoint in list_checkpoints(tmp_path / "d"):
        tensors = load_file(str(checkpoint / "tensors.safetensors"))
        assert all(torch.isfinite(t).all() for t in tensors.values() if t.is_floating_point())
