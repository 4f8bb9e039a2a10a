"""A run killed at any phase continues with one command that is safe to requeue.

Each kill is chosen by what the run is doing (``DRIVELAB_KILL_AT=PHASE[:N]``, see
:func:`drivelab.errors.kill_point`), never by the clock, so these tests check the same moments on
an idle laptop and on a loaded CI machine. The killed process gets SIGKILL, which nothing can
catch; then the same command (``--resume-if-exists``) finishes the run. Where the resumed run
continues from a point at which the uninterrupted run was between episodes (the step-0
checkpoint, or Pendulum's 200-step episodes at a checkpoint every 400 steps), its final weights
must equal those of the uninterrupted run bit for bit.
"""

import functools
import subprocess
from pathlib import Path

import pytest
import torch
import yaml
from safetensors.torch import load_file

from drivelab.cli import main
from drivelab.errors import KILL_PHASES
from drivelab.training.outputs.checkpoint import list_checkpoints, load_checkpoint
from flaky_env import importable_env
from processes import run_drivelab

# Tiny runs with a periodic checkpoint, an evaluation that films its best, and a final checkpoint.
RUNS = {
    "ppo": ["--algo", "ppo", "--env", "CartPole-v1", "--num-envs", "2", "--steps", "768", "--ppo.num_steps", "128"],
    "sac": ["--algo", "sac", "--env", "Pendulum-v1", "--num-envs", "1", "--steps", "800", "--sac.learning_starts", "200",
            "--sac.hidden", "[16,16]", "--sac.batch_size", "32"],
    "td3": ["--algo", "td3", "--env", "Pendulum-v1", "--num-envs", "1", "--steps", "800", "--td3.learning_starts", "200",
            "--td3.hidden", "[16,16]", "--td3.batch_size", "32"],
}
COMMON = ["--seed", "3", "--checkpoint_every", "400", "--eval.every", "400", "--eval.episodes", "1",
          "--no-progress", "--resume-if-exists"]

# phase -> (which time it is reached, the step of the checkpoint the requeued run continues from)
PHASES = {
    "before-config": (1, 0),
    "after-first-checkpoint": (1, 0),
    "mid-checkpoint": (2, 0),            # writing the first periodic checkpoint
    "mid-evaluation": (1, 0),            # the first evaluation comes before the first periodic checkpoint
    "mid-video": (1, 0),
    "best-copy": (1, 0),
}
LATE_CHECKPOINT = ("mid-checkpoint", 3)  # writing the final checkpoint: continues from step 400


def _train_in_process(args: list[str], capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["train", *args])
    out = capsys.readouterr()
    assert exit_.value.code == 0, out.err


def _killed(args: list[str], phase: str, tmp_path: Path) -> subprocess.CompletedProcess:
    """``drivelab train ARGS`` killed at ``phase`` (``NAME:N``); ``tmp_path/killed-NAME`` records the kill."""
    marker = tmp_path / f"killed-{phase.split(':')[0]}"
    env = {**importable_env(), "DRIVELAB_KILL_AT": phase, "DRIVELAB_KILL_MARKER": str(marker)}
    return run_drivelab("train", *args, env=env, timeout=300)


def _final_weights(run_dir: Path) -> dict[str, torch.Tensor]:
    tensors = load_file(str(list_checkpoints(run_dir)[-1] / "tensors.safetensors"))
    return {k: v for k, v in tensors.items() if k.startswith(("module/", "replay/"))}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The final weights of a run of ``algo`` trained without a kill: ``uninterrupted(algo)``.
    Each is trained when first asked for, so a pytest-xdist worker trains only the algorithms of
    the tests it runs."""

    @functools.cache
    def weights(algo: str) -> dict[str, torch.Tensor]:
        run_dir = tmp_path_factory.mktemp(f"straight-{algo}")
        with pytest.raises(SystemExit) as exit_:
            main(["train", *RUNS[algo], *COMMON, "--run-dir", str(run_dir)])
        assert exit_.value.code == 0
        return _final_weights(run_dir)

    return weights


def test_every_phase_is_tested():
    assert set(PHASES) | {"env-worker"} == set(KILL_PHASES)


@pytest.mark.parametrize("algo", sorted(RUNS))
def test_a_run_killed_at_each_phase_finishes_with_the_same_weights(algo, uninterrupted, tmp_path, capsys):
    cases = [(phase, n, start) for phase, (n, start) in PHASES.items()]
    # The phases are the Run's, shared by every algorithm: PPO meets each of them. TD3 meets the two
    # that an off-policy run reaches with a replay, target networks and optimisers to keep (writing
    # a checkpoint, evaluating between updates); SAC checks its own state (alpha, its optimiser).
    if algo == "td3":
        cases = [(phase, n, start) for phase, n, start in cases if phase in ("mid-checkpoint", "mid-evaluation")]
    if algo == "sac":
        cases = [(phase, n, start) for phase, n, start in cases if phase == "mid-checkpoint"]
    if algo != "ppo":  # Pendulum's episodes end at the step-400 checkpoint: continuing from it is exact too
        cases.append((*LATE_CHECKPOINT, 400))
    for phase, n, start in cases:
        run_dir = tmp_path / f"{phase}-{n}"
        args = [*RUNS[algo], *COMMON, "--run-dir", str(run_dir)]
        killed = _killed(args, f"{phase}:{n}", tmp_path)
        assert killed.returncode == -9, (phase, killed.stderr)
        assert (tmp_path / f"killed-{phase}").exists(), phase
        if phase != "before-config":
            assert load_checkpoint(run_dir).step == start, phase
        _train_in_process(args, capsys)          # the same command, requeued
        assert load_checkpoint(run_dir).step == int(RUNS[algo][RUNS[algo].index("--steps") + 1]), phase
        weights = _final_weights(run_dir)
        assert weights.keys() == uninterrupted(algo).keys(), phase
        for key, value in weights.items():
            assert torch.equal(value, uninterrupted(algo)[key]), (phase, key)
        leftovers = [p.name for p in (run_dir / "checkpoints").iterdir() if p.name.startswith(".")]
        assert leftovers == [], (phase, leftovers)
        (tmp_path / f"killed-{phase}").unlink()


def test_an_env_worker_killed_mid_run_is_replaced_and_the_run_finishes(tmp_path):
    run_dir = tmp_path / "run"
    args = [*RUNS["sac"], *COMMON, "--env.backend", "async", "--run-dir", str(run_dir)]
    done = _killed(args, "env-worker:300", tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "killed-env-worker").exists()
    assert "restarting the envs" in done.stderr
    assert load_checkpoint(run_dir).step == 800


def test_a_metadrive_run_killed_while_checkpointing_finishes_from_its_last_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    args = ["--algo", "ppo", "--env", "MetaDrive-10env-v0", "--num-envs", "2", "--steps", "512", "--ppo.num_steps", "128",
            "--checkpoint_every", "256", "--seed", "0", "--no-progress", "--resume-if-exists", "--run-dir", str(run_dir)]
    killed = _killed(args, "mid-checkpoint:3", tmp_path)     # writing the step-512 checkpoint
    assert killed.returncode == -9 and load_checkpoint(run_dir).step == 256, killed.stderr
    # requeued in a process of its own: MetaDrive engines must not pile up in the pytest process
    again = run_drivelab("train", *args, timeout=300)
    assert again.returncode == 0, again.stderr
    assert load_checkpoint(run_dir).step == 512
    assert not [p for p in (run_dir / "checkpoints").iterdir() if p.name.startswith(".")]


def test_a_requeued_command_that_describes_another_run_is_refused(tmp_path, capsys):
    run_dir = tmp_path / "run"
    _train_in_process([*RUNS["ppo"], *COMMON, "--run-dir", str(run_dir)], capsys)
    with pytest.raises(SystemExit) as exit_:
        main(["train", *RUNS["ppo"], *COMMON, "--ppo.lr", "0.01", "--run-dir", str(run_dir)])
    assert exit_.value.code == 2
    assert "ppo.lr" in capsys.readouterr().err
    # a finished run requeued is done: nothing trains, nothing is refused
    _train_in_process([*RUNS["ppo"], *COMMON, "--run-dir", str(run_dir)], capsys)


def test_resume_refuses_a_config_that_no_longer_matches_its_checkpoint(tmp_path, capsys):
    run_dir = tmp_path / "run"
    args = [*RUNS["ppo"], *COMMON, "--run-dir", str(run_dir)]
    killed = _killed(args, "mid-checkpoint:3", tmp_path)
    assert killed.returncode == -9 and load_checkpoint(run_dir).step == 512
    # an edited config.yaml would silently continue another run
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    saved["ppo"]["lr"] = 0.5
    (run_dir / "config.yaml").write_text(yaml.safe_dump(saved))
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--resume", str(run_dir), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert exit_.value.code == 2 and "\n" not in err and "ppo.lr" in err and "does not match" in err
    # an emptied config.yaml (a torn write by an older drivelab) is named, not read as the defaults
    (run_dir / "config.yaml").write_text("")
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--resume", str(run_dir), "--no-progress"])
    assert exit_.value.code == 2 and "is empty" in capsys.readouterr().err


def test_resume_of_a_directory_without_config_says_what_to_do(tmp_path, capsys):
    (tmp_path / "run").mkdir()
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--resume", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "run the original command again" in err and "--resume-if-exists" in err


def _flaky_args(run_dir: Path, marker: Path) -> list[str]:
    """PPO on an env that raises a RuntimeError at its 300th step, once (then ``marker`` exists);
    with sync envs nothing supervises it, so the error escapes training."""
    return ["--algo", "ppo", "--env", "flaky_env:Flaky-v0", "--env.backend", "sync", "--num-envs", "1",
            "--env.kwargs.at_step", "300", "--env.kwargs.marker", str(marker), "--ppo.num_steps", "128",
            "--steps", "1024", "--checkpoint_every", "128", "--no-progress", "--run-dir", str(run_dir)]


def test_an_unexpected_error_in_training_is_one_line_with_a_log_and_the_checkpoint_intact(tmp_path, capsys):
    run_dir = tmp_path / "run"
    done = run_drivelab("train", *_flaky_args(run_dir, tmp_path / "marker"), env=importable_env(), timeout=300)
    lines = [line for line in done.stderr.strip().splitlines() if not line.startswith("drivelab: warning")]
    assert done.returncode == 1 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert "RuntimeError: the simulator crashed (on purpose)" in lines[0] and str(run_dir / "error.log") in lines[0]
    assert f"drivelab train --resume {run_dir}" in lines[0]
    log = (run_dir / "error.log").read_text()
    assert "Traceback (most recent call last)" in log and "flaky_env.py" in log
    latest = load_checkpoint(run_dir)
    assert latest.step == 256 and latest.tensors
    _train_in_process(["--resume", str(run_dir), "--no-progress"], capsys)   # the env behaves now
    assert load_checkpoint(run_dir).step == 1024
    # --debug shows the traceback on the terminal too
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--debug", *_flaky_args(tmp_path / "again", tmp_path / "marker2")])
    err = capsys.readouterr().err
    assert exit_.value.code == 1 and "Traceback (most recent call last)" in err
    assert err.strip().splitlines()[-1].startswith("drivelab: error: training stopped at step 256")
