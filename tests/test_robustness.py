"""Nothing lost: interrupts checkpoint, one writer per run, damaged files are refused or skipped,
a diverged run stops with one line and never saves non-finite weights."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints
from drivelab.training.run.directory import MARKER
from processes import run_drivelab

TRAIN = ["-m", "drivelab", "train", "--algo", "ppo", "--env", "CartPole-v1", "--num-envs", "2", "--no-progress"]


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.strip().splitlines() if line and not line.startswith("drivelab: warning")]
    assert "Traceback" not in stderr and len(lines) == 1, stderr
    return lines[0]


# Ctrl-C reaches the whole process group (trainer and env workers, as in a terminal); a
# scheduler's SIGTERM reaches the trainer, which closes its workers itself.
IN_WORKERS = ["--ppo.act_in_workers", "true"]   # the env workers play the rollouts (mid-rollout signals)


# CartPole: each signal with the trainer stepping the envs and with the env workers playing the
# rollouts. MetaDrive (its simulator processes, up to a minute a case): SIGTERM with the workers
# playing the rollouts, the mode with the most processes to stop.
@pytest.mark.parametrize("sig, env, extra", [(signal.SIGTERM, "CartPole-v1", []), (signal.SIGINT, "CartPole-v1", []),
                                             (signal.SIGINT, "CartPole-v1", [*IN_WORKERS, "--env.backend", "async"]),
                                             (signal.SIGTERM, "MetaDrive-10env-v0", IN_WORKERS)])
def test_a_signal_stops_the_run_with_a_checkpoint_that_resumes(sig, env, extra, tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, *TRAIN, "--steps", "100000000", "--run-dir", str(run_dir), "--env", env, *extra]
    if env.startswith("MetaDrive"):  # short episodes and rollouts, so a checkpointable state comes soon
        cmd += ["--env.kwargs.horizon", "50", "--ppo.num_steps", "64"]
    # a process group of its own, as in a terminal: Ctrl-C reaches the env workers too
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.time() + 120
        while not (run_dir / "metrics.csv").is_file() or (run_dir / "metrics.csv").stat().st_size < 500:
            assert time.time() < deadline and proc.poll() is None
            time.sleep(0.2)
        (os.killpg if sig == signal.SIGINT else os.kill)(proc.pid, sig)
        _, stderr = proc.communicate(timeout=120)   # a hang fails; how fast it stops depends on the load
    finally:  # never leave a training process behind, whatever failed
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == (143 if sig == signal.SIGTERM else 130)   # 128 + the signal's number, as a shell says
    assert "--resume" in _one_line(stderr)
    step = int(list_checkpoints(run_dir)[-1].name.split("_")[-1])
    assert step > 0 and not list((run_dir / "checkpoints").glob(".tmp_*"))
    more = 128 if env.startswith("MetaDrive") else 512   # one rollout of MetaDrive's 2 envs x 64 steps
    resumed = run_drivelab("train", "--resume", run_dir, "--steps", step + more, "--no-progress", timeout=180)
    assert resumed.returncode == 0, resumed.stderr
    assert int(list_checkpoints(run_dir)[-1].name.split("_")[-1]) >= step + more


API_SCRIPT = """
import signal, sys
import drivelab
try:
    drivelab.train("ppo", "CartPole-v1", steps=10**8, num_envs=2, run_dir=sys.argv[1], progress=False)
except KeyboardInterrupt:
    restored = signal.getsignal(signal.SIGTERM) == signal.SIG_DFL and signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    sys.exit(3 if restored else 4)
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_stops_a_run_of_the_python_api_with_a_checkpoint(sig, tmp_path):
    """drivelab.train() in a script, started the way a shell starts a background job (SIGINT
    ignored): a scheduler's SIGTERM or a SIGINT stops it with a checkpoint, as the CLI does, and
    the script gets its own signal handlers back."""
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", API_SCRIPT, str(run_dir)], stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        deadline = time.time() + 120
        while not (run_dir / "metrics.csv").is_file() or (run_dir / "metrics.csv").stat().st_size < 500:
            assert time.time() < deadline and proc.poll() is None
            time.sleep(0.2)
        os.kill(proc.pid, sig)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 3, stderr
    assert checkpoint_step(list_checkpoints(run_dir)[-1]) > 0


@pytest.mark.parametrize("moment", ["between two sends", "after the results were read"])
def test_an_interrupt_mid_step_closes_the_workers_quietly(moment, monkeypatch, capfd):
    """Ctrl-C can land while gymnasium sends actions to its workers (one has its action, the
    other not) or reads their results: close() must neither hang nor leave a worker writing
    into a closed pipe (a traceback on the user's terminal, as CI once saw)."""
    import gymnasium.vector.async_vector_env as async_vector_env
    from gymnasium.vector import AutoresetMode

    from drivelab.config import EnvConfig
    from drivelab.envs import make_vector_env

    envs = make_vector_env(EnvConfig(id="CartPole-v1", num_envs=2, backend="async"),
                           autoreset_mode=AutoresetMode.NEXT_STEP)
    envs.reset(seed=0)
    processes = list(envs.envs.processes)

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    if moment == "between two sends":
        def first_action_only(space, actions):
            yield actions[0]
            interrupt()
        monkeypatch.setattr(async_vector_env, "iterate", first_action_only)
    else:
        monkeypatch.setattr(async_vector_env.AsyncVectorEnv, "_raise_if_errors", interrupt)
    with pytest.raises(KeyboardInterrupt):
        envs.step(np.zeros(2, dtype=np.int64))
    closing = threading.Thread(target=envs.close, daemon=True)  # a hung close fails the test, not the suite
    closing.start()
    closing.join(timeout=10)
    assert not closing.is_alive(), "close() hangs waiting for a result that was already read"
    for process in processes:  # once a worker has exited, whatever it would print is printed
        process.join(timeout=60)
    assert not any(p.is_alive() for p in processes)
    assert "Traceback" not in capfd.readouterr().err


def test_a_second_writer_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    first = subprocess.Popen([sys.executable, *TRAIN, "--steps", "100000000", "--run-dir", str(run_dir)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while not list_checkpoints(run_dir):  # the first writer holds the lock, and there is a checkpoint to resume
            assert time.time() < deadline and first.poll() is None
            time.sleep(0.1)
        second = run_drivelab("train", "--resume", run_dir, "--steps", "200000000", "--no-progress", timeout=60)
        assert second.returncode == 2 and "in use by another drivelab process" in _one_line(second.stderr)
    finally:
        first.kill()
        first.wait()
    # a killed writer leaves no stuck lock: the run can be resumed at once
    again = run_drivelab("train", "--resume", run_dir, "--steps",
                         int(list_checkpoints(run_dir)[-1].name.split("_")[-1]) + 2048, "--no-progress", timeout=120)
    assert again.returncode == 0, again.stderr


def _short_run(run_dir):
    from drivelab.api import build_config, train

    train(build_config({"algo": "ppo", "steps": 3072, "seed": 0, "run_dir": str(run_dir), "checkpoint_every": 1024,
                        "env": {"id": "CartPole-v1", "num_envs": 2}, "ppo": {"num_steps": 256}}), progress=False)


@pytest.mark.parametrize("left_behind", ["", "step,ti", "step,time,name,value\n0,17.5,charts/l"])
def test_a_run_killed_before_its_first_checkpoint_starts_afresh(left_behind, tmp_path):
    """kill -9 before the first checkpoint can leave metrics.csv empty or torn; --resume then
    starts the run afresh, with a whole metrics file."""
    from drivelab.api import build_config, last_metrics, train

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / MARKER).write_text("")   # drivelab made the directory before the kill
    (run_dir / "metrics.csv").write_text(left_behind)
    cfg = build_config({"algo": "ppo", "steps": 512, "seed": 0, "run_dir": str(run_dir),
                        "env": {"id": "CartPole-v1", "num_envs": 2}, "ppo": {"num_steps": 128}})
    train(cfg, resume=True, progress=False)
    header, *rows = (run_dir / "metrics.csv").read_text().splitlines()
    assert header == "step,time,name,value" and rows
    assert all(len(row.split(",")) == 4 and row.split(",")[0].isdigit() for row in rows)
    assert last_metrics(run_dir)["perf/steps_per_s"] > 0


def test_damaged_files_are_skipped_or_refused_in_one_line(tmp_path, run_cli):
    run_dir = tmp_path / "run"
    _short_run(run_dir)
    newest, older = list_checkpoints(run_dir)[-1], list_checkpoints(run_dir)[-2]
    (newest / "tensors.safetensors").write_bytes((newest / "tensors.safetensors").read_bytes()[:100])  # torn write
    out = run_cli("eval", run_dir, "--episodes", "1", "--json")
    assert out.returncode == 0 and "using the newest intact checkpoint" in out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1])["checkpoint"] == str(older)
    state = (older / "state.json").read_text()
    for bad in ("{}", "[1, 2]", "not json", json.dumps({k: v for k, v in json.loads(state).items() if k != "config"})):
        (older / "state.json").write_text(bad)
        out = run_cli("eval", older, "--episodes", "1")
        assert out.returncode == 2 and str(older / "state.json") in _one_line(out.stderr)
    (older / "state.json").write_text(state)
    import pickle

    (older / "tensors.safetensors").write_bytes(pickle.dumps({"weights": [1.0, 2.0]}))  # a pickle in its place
    out = run_cli("eval", older, "--episodes", "1")
    assert out.returncode == 2 and str(older / "tensors.safetensors") in _one_line(out.stderr)
    # an emptied metrics.csv (killed before its first flush) and a stale temp checkpoint: resume works
    (run_dir / "metrics.csv").write_text("")
    (run_dir / "checkpoints" / ".tmp_step_000000009999_1").mkdir()
    out = run_cli("train", "--resume", run_dir, "--steps", "5000", "--no-progress")
    assert out.returncode == 0, out.stderr
    assert not list((run_dir / "checkpoints").glob(".tmp_*"))


@pytest.mark.parametrize("algo, fail, extra", [
    ("ppo", "nan", ["--ppo.num_steps", "256"]),
    ("ppo", "nan_obs", ["--ppo.act_in_workers", "true", "--num-envs", "2", "--env.backend", "async"]),
    ("reinforce", "nan", []), ("grpo", "nan_obs", []),
    ("sac", "nan", ["--sac.learning_starts", "50", "--env.kwargs.base", "Pendulum-v1"]), ("td3", "nan_obs", ["--td3.act_in_workers", "true", "--num-envs", "2", "--env.backend", "async",
                                  "--env.kwargs.base", "Pendulum-v1"]),
])
def test_non_finite_rewards_and_observations_stop_the_run_in_one_line_naming_them(algo, fail, extra, tmp_path, run_cli):
    out = run_cli("train", "--algo", algo, "--env", "flaky_env:Flaky-v0", "--env.kwargs.fail", fail,
                  "--env.kwargs.at_step", "100", "--steps", "5000", *extra, "--run-dir", tmp_path / "n", "--no-progress")
    what = "reward" if fail == "nan" else "observation"
    assert out.returncode == 2 and f"non-finite {what} (nan)" in _one_line(out.stderr), out.stderr
    assert "Traceback" not in out.stderr


def test_too_many_minibatches_are_refused_before_training(tmp_path, run_cli):
    out = run_cli("train", "--algo", "ppo", "--env", "CartPole-v1", "--ppo.num_minibatches", "100000",
                  "--steps", "1000", "--run-dir", tmp_path / "m", "--no-progress")
    assert out.returncode == 2 and "'ppo.num_minibatches' is 100000" in _one_line(out.stderr)
    assert not (tmp_path / "m").exists()


def test_an_env_module_that_cannot_be_imported_is_one_line_naming_it(tmp_path, capsys):
    from drivelab.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", "ppo", "--env", "no_such_module:Flaky-v0", "--steps", "1", "--no-progress",
              "--run-dir", str(tmp_path / "run")])
    assert exit_info.value.code == 2 and "'no_such_module'" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "run").exists()


def test_divergence_stops_the_run_and_saves_no_non_finite_weights(tmp_path, run_cli):
    out = run_cli("train", "--algo", "sac", "--env", "Pendulum-v1", "--steps", "3000", "--sac.learning_starts", "200",
                  "--sac.actor_lr", "1e6", "--sac.critic_lr", "1e6", "--run-dir", tmp_path / "d", "--no-progress")
    assert out.returncode == 2 and "diverged" in _one_line(out.stderr)
    from safetensors.torch import load_file
    import torch

    for checkpoint in list_checkpoints(tmp_path / "d"):
        tensors = load_file(str(checkpoint / "tensors.safetensors"))
        assert all(torch.isfinite(t).all() for t in tensors.values() if t.is_floating_point())


# ---- bad input, generated: every case must end with exit code 2, one line, no traceback, and
# nothing written on disk (the run directory is not created)

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_text = st.text(alphabet="abcxyz-_!@ ", min_size=1, max_size=8)
BAD_VALUES = {
    "--seed": st.one_of(st.integers(max_value=-1), st.integers(min_value=2**63, max_value=2**80), _text),
    "--steps": st.one_of(st.integers(max_value=-1), _text),
    "--num-envs": st.one_of(st.integers(max_value=0), st.integers(min_value=10_000, max_value=10**6), _text),
    "--ppo.lr": st.one_of(st.floats(max_value=0.0, allow_nan=False), st.just("inf"), st.just(".nan"), _text),
    "--ppo.gamma": st.one_of(st.floats(min_value=1.001, max_value=1e9), st.floats(max_value=-0.001, min_value=-1e9)),
    "--ppo.hidden": st.one_of(st.lists(st.integers(max_value=0), min_size=1, max_size=3).map(str), st.just("[]")),
    "--ppo.num_minibatches": st.one_of(st.integers(max_value=0), st.integers(min_value=257)),
    "--ppo.clip_vloss": _text,
    "--env": _text.map(lambda t: f"No{t}Env-v9"),
    "--env.num_envs": st.integers(max_value=0),
    "--env.action_grid": st.one_of(_text, st.just("0x3"), st.just("3x")),
    "--env.backend": _text,
    "--env.kwargs.no_such_option": st.integers(),
    "--eval.every": st.integers(max_value=-1),
    "--eval.episodes": st.integers(max_value=0),
    # bad on every machine: no GPU has index 99, and a CPU-only torch refuses cuda outright
    "--device": st.one_of(st.just("cuda:99"), st.just("gpu"), _text),
    "--log_every": st.integers(max_value=0),
    "--checkpoint_every": st.integers(max_value=0),
    "--max_minutes": st.floats(max_value=0.0, allow_nan=False),
    "--torch_threads": st.integers(max_value=0),
    "--algo": _text.filter(lambda t: t not in ("ppo", "a2c", "sac", "td3", "ddpg", "grpo", "reinforce", "ppo_lag",
                                               "sac_lag")),
}
UNKNOWN = st.builds(lambda section, name: f"--{section}.{name}", st.sampled_from(["ppo", "env", "eval", "track"]),
                    st.text(alphabet="qwzjk", min_size=3, max_size=8))
CONFIG_FILES = st.sampled_from([b"\x00\xff\xfe binary", b"algo: [unclosed", b"- just\n- a list\n", b"ppo: 3\nalgo: ppo\n",
                                b"algo: ppo\nenv: {id: CartPole-v1, nonsense: 1}\n",
                                b"", b"# comments only\n", b"algo: ppo\nsteps: 5\nalgo: a2c\n"])  # empty; a key twice


@settings(max_examples=120, deadline=None, derandomize=True,  # the same examples on every run
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=st.one_of(st.sampled_from(sorted(BAD_VALUES)).flatmap(lambda flag: st.tuples(st.just(flag), BAD_VALUES[flag])),
                      st.tuples(UNKNOWN, st.just("1")),
                      st.tuples(st.just("--config"), CONFIG_FILES),
                      st.tuples(st.just("--run-dir"), st.sampled_from(["a-file", "a-user-folder", ""]))))
def test_generated_bad_input_is_one_line_and_writes_nothing(case, tmp_path_factory, capsys):
    from drivelab.cli import main

    tmp = tmp_path_factory.mktemp("fuzz")
    flag, value = case
    run_dir = tmp / "run"
    # 512 steps: one PPO iteration of the defaults, so no case is refused for its run length alone
    args = ["train", "--algo", "ppo", "--env", "CartPole-v1", "--steps", "512", "--no-progress", "--run-dir", str(run_dir)]
    if flag == "--config":
        (tmp / "bad.yaml").write_bytes(value)
        args += ["--config", str(tmp / "bad.yaml")]
    elif flag == "--run-dir":
        (tmp / "a-file").write_text("not a directory")
        (tmp / "a-user-folder").mkdir()
        (tmp / "a-user-folder" / "config.yaml").write_text("mine: 1\n")
        args[-1] = str(tmp / value) if value else ""
    else:
        args += [flag, str(value)]
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    captured = capsys.readouterr()
    assert exit_info.value.code == 2, (args, captured.err)
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("drivelab: error:") and "Traceback" not in captured.err, (args, captured.err)
    assert not run_dir.exists(), (args, "the run directory was created")
    if flag == "--run-dir":
        assert [p.name for p in (tmp / "a-user-folder").iterdir()] == ["config.yaml"], (args, "the user's folder changed")


@pytest.mark.parametrize("fail, in_workers", [("raise", False), ("die", False), ("hang", False),
                                              ("raise", True), ("die", True)])   # True: ppo.act_in_workers
def test_a_crashed_or_hung_env_worker_is_restarted_and_the_run_completes(fail, in_workers, tmp_path):
    from drivelab.api import build_config, train

    marker = tmp_path / "failed"
    cfg = build_config({"algo": "ppo", "steps": 1024, "seed": 0, "run_dir": str(tmp_path / "run"),
                        "env": {"id": "flaky_env:Flaky-v0", "num_envs": 2, "backend": "async", "step_timeout": 5,
                                "kwargs": {"fail": fail, "at_step": 100, "marker": str(marker)}},
                        "ppo": {"num_steps": 128, "act_in_workers": in_workers}})
    train(cfg, progress=False)
    assert marker.read_text() == fail   # it did fail
    with open(tmp_path / "run" / "metrics.csv") as f:
        rows = [line.split(",") for line in f.read().splitlines()[1:]]
    assert ["env/restarts", "1"] in [[r[2], r[3]] for r in rows]
    assert int(list_checkpoints(tmp_path / "run")[-1].name.split("_")[-1]) >= 1024


def test_an_env_that_keeps_failing_stops_the_run_with_its_error(tmp_path):
    from drivelab.envs.supervised import SupervisedVectorEnv
    from drivelab.errors import DrivelabError

    def broken():
        raise RuntimeError("no simulator today")

    class Stub:
        num_envs, metadata = 1, {}

        def __init__(self):
            self.closed = False

        def reset_async(self, seed=None, options=None):
            broken()

        def reset_wait(self, timeout=None):
            broken()

        def reset(self, seed=None, options=None):
            broken()

        def close(self, **kwargs):
            self.closed = True

    envs = SupervisedVectorEnv(Stub, step_timeout=1, max_restarts=0, restart_window=10)
    with pytest.raises(DrivelabError, match="no simulator today"):
        envs.reset(seed=[0])

