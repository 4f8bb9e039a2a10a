"""Progress on long work: the training bar against the bound that ends the run first, the refusal
of an iteration far beyond ``steps``, and the bars of ``drivelab report`` and ``drivelab sweep``."""

import time

import pytest

import drivelab
from drivelab.api import build_config
from drivelab.config import fit_steps
from drivelab.errors import DrivelabError
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.run.metrics import BarView, RunMetrics, bar_view
from drivelab.training.run.timing import Timing

# ---- training: steps or max_minutes, whichever ends the run first ----------------------------


def test_the_bar_counts_steps_without_a_time_limit_or_before_a_rate_is_known():
    assert bar_view(step=500, steps=1000, elapsed=10.0, limit_s=None) == BarView(False, 500, 1000)
    assert bar_view(step=0, steps=1000, elapsed=10.0, limit_s=60.0) == BarView(False, 0, 1000)


def test_the_bar_shows_time_when_max_minutes_ends_the_run_before_steps():
    # 100 steps/s: 3,000,000 steps would take 8 hours, the limit is 10 minutes
    assert bar_view(step=6000, steps=3_000_000, elapsed=60.0, limit_s=600.0) == BarView(True, 60.0, 600.0)
    # past the limit (the last iteration ends after it): the bar is full, not beyond
    assert bar_view(step=60_100, steps=3_000_000, elapsed=601.0, limit_s=600.0) == BarView(True, 600.0, 600.0)


def test_the_bar_counts_steps_when_they_end_the_run_before_max_minutes():
    # 100 steps/s: the 10,000 steps take 100 s, well within the 600 s limit
    assert bar_view(step=1000, steps=10_000, elapsed=10.0, limit_s=600.0) == BarView(False, 1000, 10_000)


def test_a_resumed_run_predicts_from_the_steps_played_in_this_process():
    # 900 steps came from the checkpoint; 100 steps in 10 s: 1,000 steps left take 100 s > 60 s
    assert bar_view(step=1000, steps=2000, elapsed=10.0, limit_s=60.0, start_step=900).by_time
    # counting the resumed steps as played here would predict 10 s left, and steps
    assert not bar_view(step=1000, steps=2000, elapsed=10.0, limit_s=60.0).by_time


def test_the_total_follows_episodes_that_end_past_steps():
    assert bar_view(step=1040, steps=1000, elapsed=10.0, limit_s=None) == BarView(False, 1040, 1040)


def _metrics(tmp_path, **fields):
    cfg = build_config({"algo": "ppo", "run_dir": str(tmp_path / "run"), "env": {"id": "CartPole-v1", "num_envs": 2},
                        **fields})
    (tmp_path / "run").mkdir()
    return RunMetrics(cfg, tmp_path / "run", EpisodeTracker(2), Timing(), progress=True)


def test_a_run_ended_by_max_minutes_shows_minutes_and_the_step_count(tmp_path, capsys):
    metrics = _metrics(tmp_path, steps=3_000_000, max_minutes=1)
    metrics.start_time = time.perf_counter() - 30   # half the minute spent
    metrics.advance(3000)
    metrics.close()
    err = capsys.readouterr().err
    assert "00:30/01:00 of max_minutes [3,000 steps, 100 step/s" in err and "3000000" not in err.split("\r")[-1]


def test_a_run_ended_by_steps_keeps_its_bar_in_steps(tmp_path, capsys):
    metrics = _metrics(tmp_path, steps=1024, max_minutes=60)
    metrics.start_time = time.perf_counter() - 1
    metrics.advance(512)
    metrics.close()
    err = capsys.readouterr().err
    assert "512/1024" in err and "max_minutes" not in err


# ---- an iteration far beyond steps ------------------------------------------------------------


def test_num_envs_that_multiply_the_steps_asked_for_are_one_line(tmp_path, capsys):
    from drivelab.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", "ppo", "--env", "CartPole-v1", "--num-envs", "10000", "--steps", "500",
              "--no-progress", "--run-dir", str(tmp_path / "run")])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_info.value.code == 2 and len(lines) == 1, lines
    assert "env.num_envs x ppo.num_steps = 1,280,000" in lines[0] and "steps (500)" in lines[0]
    assert not (tmp_path / "run").exists()


def test_a_short_run_with_the_default_rollout_is_rounded_up_with_a_note(tmp_path, capsys):
    # steps=64 with PPO's defaults (4 envs x 128 steps): a smoke test, not a mistake
    cfg = build_config({"algo": "ppo", "steps": 64, "run_dir": str(tmp_path / "run"), "env": {"id": "CartPole-v1"}})
    fit_steps(cfg)
    assert cfg.steps == 512 and "steps 64 -> 512" in capsys.readouterr().out


def test_off_policy_iterations_name_num_envs(tmp_path):
    cfg = build_config({"algo": "sac", "steps": 5, "run_dir": str(tmp_path / "run"),
                        "env": {"id": "Pendulum-v1", "num_envs": 64}})
    with pytest.raises(DrivelabError, match=r"collects env\.num_envs = 64 env steps.*lower env\.num_envs,"):
        fit_steps(cfg)


# ---- drivelab report ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("runs") / "short"
    drivelab.train("ppo", "CartPole-v1", steps=256, seed=0, num_envs=2, run_dir=run_dir, progress=False,
                   ppo={"num_steps": 128}, eval={"every": 0})
    return run_dir


def test_the_report_counts_its_evaluations_on_stderr(short_run, tmp_path, capsys):
    from drivelab.tools.report import write_report

    write_report([short_run], tmp_path / "r.html", episodes=1, video=False)
    err = capsys.readouterr().err
    # the latest checkpoint and the random baseline (CartPole: no expert), each named while it runs
    assert "short: latest checkpoint" in err and "short: random baseline" in err and "2/2" in err
    write_report([short_run], tmp_path / "quiet.html", episodes=1, video=False, progress=False)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("command", ["report", "sweep"])
def test_no_progress_reaches_report_and_sweep(command, tmp_path, monkeypatch, capsys):
    from drivelab.cli import main
    from drivelab.tools import report, sweep

    heard = {}
    if command == "report":
        monkeypatch.setattr(report, "write_report", lambda *args, **kwargs: heard.update(kwargs) or tmp_path / "r.html")
        argv = ["report", str(tmp_path)]
    else:
        monkeypatch.setattr(sweep, "run_sweep", lambda *args, **kwargs: heard.update(kwargs) or {"settings": []})
        (tmp_path / "sweep.yaml").write_text("algo: ppo\nenv: {id: CartPole-v1}\n")
        argv = ["sweep", str(tmp_path / "sweep.yaml"), "--out", str(tmp_path / "out")]
    for flags, shown in (([], True), (["--no-progress"], False)):
        with pytest.raises(SystemExit) as exit_info:
            main([*argv, *flags])
        assert exit_info.value.code == 0 and heard["progress"] is shown


# ---- drivelab sweep: trials done / total ---------------------------------------------------------


def test_sweep_progress_counts_ended_trials_and_failures(capsys):
    pytest.importorskip("ray")
    from drivelab.tools.sweep import TrialProgress

    progress = TrialProgress(3)
    progress.bar.delay = 0        # shown at once here (a sweep shows it after a second)
    callback = progress.tune_callback()   # what Ray Tune calls in the driver process
    callback.on_trial_complete(iteration=1, trials=[], trial=None)
    callback.on_trial_error(iteration=2, trials=[], trial=None)
    progress.close()
    err = capsys.readouterr().err
    assert "sweep" in err and "2/3" in err and "1 failed" in err
    quiet = TrialProgress(3, progress=False)
    quiet.trial_ended()
    quiet.close()
    assert capsys.readouterr().err == ""
