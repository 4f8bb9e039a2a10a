"""Smaller frictions of the command line (issue 79): what --help lists, the flag a typo suggests,
a light --help, a clear word for a missing best checkpoint, shell-quoted next commands, what "±"
means in a table, and the exit status of a run stopped by SIGTERM."""

import json
import os
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from drivelab import cli
from drivelab.config import TrainConfig, field_paths
from drivelab.errors import DrivelabError, Terminated
from drivelab.tools.drivers import DRIVERS_DIR, format_card, read_card
from drivelab.tools.tables import format_evaluation, format_evaluations


@pytest.fixture
def run_main(capsys):
    """``drivelab ARGS`` in this process: (exit status, stdout, stderr). The CLI installs its
    SIGINT and SIGTERM handlers; the test session gets its own back afterwards."""
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def _run(*args: str) -> tuple[int, str, str]:
        with pytest.raises(SystemExit) as stop:
            cli.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return stop.value.code, out, err

    yield _run
    for sig, handler in handlers.items():
        signal.signal(sig, handler)


def test_train_help_lists_every_config_field_with_its_default_and_meaning(run_main):
    code, out, _ = run_main("train", "--help")
    assert code == 0
    # every field of the run's config (but the hyperparameters: --algo ALGO --help) has a line
    # that starts with its dotted name: the list is made from the dataclasses, not kept by hand
    sections = {"env", "eval", "track", "algo_params"}
    for path in field_paths(TrainConfig):
        if path not in sections:
            assert f"\n  {path} " in out, path
    lines = {line.split()[0]: line for line in out.splitlines() if line.startswith("  ") and line.split()}
    assert lines["checkpoint_every"].split()[1:3] == ["int", "50000"]
    assert "evaluations" in lines["eval.every"] and "parallel" in lines["env.num_envs"]
    assert "gym.make" in lines["env.kwargs"] and "cuda" in lines["device"]
    assert "drivelab train --algo ALGO --help" in out


def test_train_help_with_an_algorithm_adds_its_hyperparameters(run_main):
    code, out, _ = run_main("train", "--algo", "ppo", "--help")
    assert code == 0 and "\n  max_minutes " in out and "\n  clip_coef " in out


@pytest.mark.parametrize("flag, suggestion", [
    ("--num_envs", "--num-envs or --env.num_envs"),   # a named flag's field, typed with _
    ("--env.num_env", "--num-envs or --env.num_envs"),
    ("--eval.evry", "--eval.every"),
    ("--checkpoint_evry", "--checkpoint_every"),
    ("--run_dirr", "--run-dir"),                      # run_dir's own flag, not the same field twice
    ("--ppo.gama", "--ppo.gamma"),                    # the algorithm's section
])
def test_a_mistyped_flag_suggests_a_flag_that_works(flag, suggestion, run_main, tmp_path):
    code, _, err = run_main("train", "--algo", "ppo", "--run-dir", tmp_path / "run", flag, "2")
    assert code == 2
    assert err.strip() == f"drivelab: error: unknown option {flag} (did you mean {suggestion}?)"
    assert not (tmp_path / "run").exists()


def test_a_flag_like_nothing_says_where_the_fields_are_listed(run_main, tmp_path):
    code, _, err = run_main("train", "--algo", "sac", "--run-dir", tmp_path / "run", "--sac.zzz", "2")
    assert code == 2 and "unknown option --sac.zzz; drivelab train --algo sac --help" in err


def test_a_config_file_names_the_field_by_its_dotted_path(tmp_path):
    from drivelab.api import train_config

    config = tmp_path / "c.yaml"
    config.write_text("algo: ppo\nnum_envs: 2\nenv: {id: CartPole-v1, num_env: 3}\n")
    with pytest.raises(DrivelabError, match=r"unknown field\(s\) num_envs, env.num_env \(did you mean env.num_envs\?\)"):
        train_config({}, config)


def test_help_and_version_import_neither_torch_nor_a_simulator():
    script = """
import sys
from drivelab.cli import main
for argv in (["--version"], ["--help"], ["train", "--help"], ["eval", "--help"]):
    try:
        main(argv)
    except SystemExit as stop:
        assert stop.code == 0, (argv, stop.code)
print(sorted(name for name in ("torch", "metadrive", "ray") if name in sys.modules))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout


def _run_without_best(run: Path, eval_every: int) -> None:
    """A run directory with one checkpoint (its state.json: what resolving ``best`` reads) and no
    checkpoints/best, as a run trained with eval.every as given leaves it before an evaluation."""
    step = run / "checkpoints" / f"step_{1000:012d}"
    step.mkdir(parents=True)
    (step / "state.json").write_text(json.dumps({"step": 1000, "config": {"eval": {"every": eval_every}}}))


@pytest.mark.parametrize("best", ["best", "checkpoints/best"])
def test_loading_best_of_a_run_without_evaluation_says_why_and_what_to_do(best, tmp_path):
    import drivelab

    run = tmp_path / "run"
    _run_without_best(run, eval_every=0)
    with pytest.raises(DrivelabError) as error:
        drivelab.load(run / best)
    message = str(error.value)
    assert "\n" not in message and "not found" not in message
    assert "no evaluation ran" in message and "eval.every > 0" in message and f"latest checkpoint ({run})" in message


def test_best_before_the_first_evaluation_and_outside_a_run(tmp_path):
    import drivelab

    _run_without_best(tmp_path / "run", eval_every=5000)
    with pytest.raises(DrivelabError, match=r"no evaluation has run yet .*\(eval.every 5000\).*latest checkpoint"):
        drivelab.load(tmp_path / "run" / "best")
    with pytest.raises(DrivelabError, match="not found"):
        drivelab.load(tmp_path / "nothing" / "best")


def test_the_commands_drivelab_prints_are_shell_quoted(run_main, tmp_path, monkeypatch):
    from drivelab import api

    run = tmp_path / "my runs" / "cart pole"

    def trained(cfg, **kwargs):  # the training itself is not what this test is about
        return api.TrainResult(Path(cfg.run_dir), {})

    monkeypatch.setattr(api, "train", trained)
    code, out, _ = run_main("train", "--algo", "reinforce", "--run-dir", run, "--steps", "100")
    assert code == 0
    evaluate = next(line for line in out.splitlines() if "evaluate:" in line)
    command = evaluate.split("evaluate: ")[1].split("    watch:")[0]
    assert shlex.split(command) == ["drivelab", "eval", str(run), "--episodes", "10"]
    assert shlex.split(evaluate.split("watch: ")[1]) == ["tensorboard", "--logdir", str(run / "tb")]
    monkeypatch.undo()

    # a directory that holds a run: the hint to resume it pastes as one argument too
    _run_without_best(run, eval_every=0)
    code, _, err = run_main("train", "--algo", "reinforce", "--run-dir", run, "--steps", "100")
    assert code == 2 and f"use --resume {shlex.quote(str(run))} " in err


def test_tables_and_cards_say_what_plus_minus_means():
    row = {"return_mean": 10.0, "return_std": 2.0, "length_mean": 50.0, "episodes": 5, "env": "CartPole-v1",
           "policy": "random"}
    assert "return (mean ± std)" in format_evaluations([row, row], 5, 0)
    assert "return (mean ± std)" in format_evaluation(row, "CartPole-v1", "the random baseline")
    card = format_card(read_card(DRIVERS_DIR / "drivelab-driver"))   # the shipped driver's
    assert "mean ± 95% CI" in card and "return (mean ± std)" not in card


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["SIGTERM", "SIGINT"])
def test_a_signal_ends_a_command_with_128_plus_its_number(sig, status, run_main, monkeypatch):
    """The CLI's own handlers, with a real signal: SIGTERM is raised as Terminated (a
    KeyboardInterrupt, so a run checkpoints as on Ctrl-C) and exits 143; Ctrl-C exits 130."""
    def signalled() -> int:
        os.kill(os.getpid(), sig)
        return 0

    monkeypatch.setattr(cli, "cmd_envs", signalled)
    code, _, err = run_main("envs")
    assert code == status
    assert err.strip() == ("drivelab: terminated" if sig == signal.SIGTERM else "drivelab: interrupted")
    assert issubclass(Terminated, KeyboardInterrupt)


def test_run_is_the_command_in_this_process_and_a_failure_raises(capsys):
    """``cli.run`` (what the notebooks call) returns after a command that succeeds and raises,
    naming the command, where ``drivelab`` would exit with an error status."""
    cli.run("configs")
    assert "ppo_metadrive_demo" in capsys.readouterr().out
    with pytest.raises(RuntimeError, match=r"drivelab eval /no/such/run failed \(exit status [12]\)"):
        cli.run("eval", Path("/no/such/run"))
    assert "/no/such/run" in capsys.readouterr().err
