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
    from drivelab.training.checkpoint import load_checkpoint

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
