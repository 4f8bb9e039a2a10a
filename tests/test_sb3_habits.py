"""What a Stable-Baselines3 user reaches for first: the API in tab completion, and a policy's
``predict`` and ``save``/``load``."""

from pathlib import Path

import numpy as np
import pytest

import drivelab
from drivelab.errors import DrivelabError

CHECKPOINT = Path(__file__).parent / "data" / "checkpoints_v0.3" / "sac_pendulum"


def test_the_api_shows_in_dir():
    assert {"train", "load", "evaluate", "make_env", "build_config", "__version__"} <= set(dir(drivelab))


def test_predict_returns_the_action_and_no_state_like_sb3():
    policy = drivelab.load(CHECKPOINT)
    obs = np.array([0.5, -0.5, 0.1], np.float32)
    action, state = policy.predict(obs, deterministic=True)
    assert state is None and action.shape == (1,)
    np.testing.assert_array_equal(action, policy.act(obs))
    batch, _ = policy.predict(np.stack([obs, obs]))
    assert batch.shape == (2, 1)


def test_save_writes_the_policy_alone_and_load_reads_it_back(tmp_path):
    policy = drivelab.load(CHECKPOINT)
    saved = policy.save(tmp_path / "pendulum_policy")
    again = drivelab.load(saved)
    obs = np.random.default_rng(0).uniform(-1, 1, size=(5, 3)).astype(np.float32)
    np.testing.assert_array_equal(policy.predict(obs)[0], again.predict(obs)[0])
    # without the optimiser state and the replay buffer the checkpoint holds
    assert (saved / "tensors.safetensors").stat().st_size < (CHECKPOINT / "tensors.safetensors").stat().st_size / 2


def test_a_callback_hears_logs_evaluations_and_checkpoints_and_stops_the_run(tmp_path):
    from drivelab.api import RunEvent
    from drivelab.training.outputs.checkpoint import load_checkpoint

    heard: list[RunEvent] = []

    def stop_after_first_evaluation(event: RunEvent) -> bool:
        heard.append(event)
        return event.kind != "eval"

    result = drivelab.train("ppo", "CartPole-v1", steps=4096, seed=0, num_envs=2, run_dir=tmp_path / "run",
                            progress=False, callback=stop_after_first_evaluation, log_every=256, checkpoint_every=10**6,
                            ppo={"num_steps": 128}, eval={"every": 512, "episodes": 2})
    kinds = [event.kind for event in heard]
    assert kinds[0] == "checkpoint" and heard[0].step == 0          # the step-0 checkpoint
    assert "log" in kinds and "episode/return" in next(e for e in heard if e.kind == "log").metrics
    evaluation = next(e for e in heard if e.kind == "eval")
    assert evaluation.step == 512 and "return_mean" in evaluation.metrics
    assert kinds[-1] == "checkpoint" and heard[-1].step == 512       # stopped there, with a checkpoint
    assert load_checkpoint(result.run_dir).step == 512 and heard[-1].path.is_dir()


def test_an_unregistered_env_class_trains_evaluates_resumes_and_exports_from_the_cli(tmp_path, capsys):
    from drivelab.cli import main

    run = str(tmp_path / "run")
    common = ["--no-progress", "--ppo.num_steps", "64"]
    for argv in (["train", "--algo", "ppo", "--env", "flaky_env:TallyEnv", "--steps", "256", "--run-dir", run, *common],
                 ["train", "--resume", run, "--steps", "384", *common],
                 ["eval", run, "--episodes", "2", "--json"],
                 ["export", run, "--format", "torchscript", "--out", str(tmp_path / "x")]):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code in (0, None), (argv, capsys.readouterr().err)
    assert "flaky_env:TallyEnv" in (tmp_path / "run" / "config.yaml").read_text()
    assert (tmp_path / "x" / "policy.json").is_file()


def test_the_api_trains_on_an_env_class_and_a_factory(tmp_path):
    import flaky_env

    for name, env in (("class", flaky_env.TallyEnv), ("factory", flaky_env.make_tally)):
        result = drivelab.train("ppo", env, steps=128, seed=0, run_dir=tmp_path / name, progress=False,
                                ppo={"num_steps": 64})
        assert result.metrics["episode/length"] > 0, name


def test_an_env_instance_or_a_main_module_class_is_refused_in_one_line():
    import flaky_env

    with pytest.raises(DrivelabError, match="not an instance"):
        drivelab.train("ppo", flaky_env.TallyEnv(), steps=64)
    main_class = type("Corridor", (flaky_env.TallyEnv,), {"__module__": "__main__"})
    with pytest.raises(DrivelabError, match="defined in __main__"):
        drivelab.train("ppo", main_class, steps=64)


@pytest.mark.parametrize("algo, overrides", [
    ("ppo", {"ppo": {"num_steps": 64}}),                                              # rollouts of 64 x 2
    ("td3", {"td3": {"act_in_workers": True, "chunk_steps": 8, "learning_starts": 20}, "env.backend": "async"}),
    ("reinforce", {"reinforce": {"batch_steps": 100}}),                               # whole episodes
])
def test_steps_ends_the_run_where_its_config_progress_and_report_say(tmp_path, capsys, algo, overrides):
    from drivelab.training.outputs.checkpoint import load_checkpoint
    from drivelab.training.outputs.plots import read_metrics

    result = drivelab.train(algo, "flaky_env:Tally-v0", steps=301, seed=0, num_envs=2, run_dir=tmp_path / "run",
                            progress=False, log_every=50, **overrides)
    stated = int(yaml_field(result.run_dir / "config.yaml", "steps"))
    trained = load_checkpoint(result.run_dir).step
    logged = max(int(steps[-1]) for steps, _, _ in read_metrics(result.run_dir).values())
    out, err = capsys.readouterr()
    if algo == "reinforce":
        # the last batch asks for the 1 step left; its 2 episodes in flight end (<= 11 steps each)
        assert stated == 301 and 301 <= trained <= 301 + 2 * 11 and logged == trained
        assert trained == 301 or f"{trained:,} env steps trained" in err
    else:
        assert stated == trained == logged == (384 if algo == "ppo" else 302)
        assert f"steps 301 -> {stated}" in out


def yaml_field(path: Path, field: str):
    import yaml

    return yaml.safe_load(path.read_text())[field]


def test_reward_terms_shape_any_env_and_a_module_function_term_is_the_users_own(tmp_path):
    from drivelab.config import EnvConfig
    from drivelab.envs import make_env

    reward = {"native": {"weight": 0.5}, "flaky_env:late_step_bonus": {"weight": 3.0, "after": 1}}
    env = make_env(EnvConfig(id="flaky_env:Tally-v0", reward=reward))
    env.reset(seed=0)
    rewards = [env.step(np.array([0.0], np.float32))[1] for _ in range(3)]
    assert rewards == [0.5 * 0.0, 0.5 * 10.0 + 3.0, 0.5 * 20.0 + 3.0]   # native: 10 t; bonus once obs t > 1
    env.close()
    # in subprocess env workers and through training, as a config names it
    result = drivelab.train("ppo", {"id": "flaky_env:Tally-v0", "reward": reward, "backend": "async", "num_envs": 2},
                            steps=128, seed=0, run_dir=tmp_path / "run", progress=False, ppo={"num_steps": 64})
    assert result.metrics["episode/reward/flaky_env:late_step_bonus"] > 0
    with pytest.raises(DrivelabError, match="reward term 'cte' needs info\\['cte'\\]"):
        bad = make_env(EnvConfig(id="CartPole-v1", reward={"cte": {}}))
        bad.reset(seed=0)
        bad.step(0)
    with pytest.raises(DrivelabError, match="has no 'missing'"):
        make_env(EnvConfig(id="CartPole-v1", reward={"flaky_env:missing": {}}))


def test_the_custom_env_example_trains_and_evaluates(tmp_path):
    import subprocess
    import sys

    example = Path(__file__).resolve().parent.parent / "examples" / "custom_env.py"
    done = subprocess.run([sys.executable, str(example), "--steps", "4000", "--run-dir", str(tmp_path / "toy")],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "steps on the lane on average" in done.stdout
    assert "custom_env:LaneKeepingToy" in (tmp_path / "toy" / "config.yaml").read_text()


def test_a_short_sac_run_fits_its_heat_up_and_learns_with_one_line_saying_so(tmp_path, capsys):
    from drivelab.training.outputs.plots import read_metrics

    # SAC's learning_starts (5000) would outlast a 300-step run: it becomes a tenth of the run
    result = drivelab.train("sac", "Pendulum-v1", steps=300, seed=0, run_dir=tmp_path / "run", progress=False,
                            log_every=100, sac={"batch_size": 32, "hidden": [32]})
    err = capsys.readouterr().err
    assert "sac.learning_starts (5000) is not below steps (300)" in err and err.count("\n") == 1
    assert "loss/critic" in read_metrics(result.run_dir) and "learning_starts: 30" in \
        (result.run_dir / "config.yaml").read_text()
