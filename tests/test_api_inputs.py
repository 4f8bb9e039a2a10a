"""The Python API checks its inputs as the CLI does (issue 79): a wrong observation, env, path,
algorithm or resume value is one line (:class:`DrivelabError`), never an error from deep inside
torch; ``drivelab.evaluate`` returns what ``drivelab eval --json`` prints; and a user's env class
whose ``__init__`` takes no argument trains, evaluates, resumes and exports from Python and from
the command line."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import drivelab
from drivelab.errors import DrivelabError

PENDULUM = Path(__file__).parent / "data" / "checkpoints_v0.3" / "sac_pendulum"  # observations (3,), actions (1,)


class Corridor(gym.Env):
    """A user's env with a no-argument ``__init__`` (no ``render_mode``): walk right (action 1)
    along a corridor of 5 cells to its end; each step costs 0.1, the end pays 1. Observation:
    (position / 4, time / 20)."""

    observation_space = gym.spaces.Box(0.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def __init__(self):
        self.position, self.t = 0, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.position, self.t = int(self.np_random.integers(0, 2)), 0
        return self._obs(), {}

    def step(self, action):
        self.position = max(0, self.position + (1 if int(action) == 1 else -1))
        self.t += 1
        reached = self.position >= 4
        return self._obs(), 1.0 if reached else -0.1, reached, self.t >= 20 and not reached, {}

    def _obs(self) -> np.ndarray:
        return np.array([self.position / 4, self.t / 20], np.float32)


def one_line(excinfo: pytest.ExceptionInfo) -> str:
    """The error's message, checked to be one line."""
    message = str(excinfo.value)
    assert "\n" not in message, message
    return message


# --- policy.act -----------------------------------------------------------------------------

@pytest.mark.parametrize("obs, says", [
    (np.zeros(5, np.float32), "got shape (5,)"),             # IndexError deep in torch before
    (np.zeros((2, 3, 4), np.float32), "got shape (2, 3, 4)"),
    (float("nan"), "got shape ()"),                          # a scalar is no observation of shape (3,)
    ("hello", "got str 'hello'"),                            # ValueError from numpy before
    (None, "got NoneType"),
    ({"x": 1.0}, "got dict"),
    ([[0.0, 1.0, 2.0], [0.0]], "got list"),                  # ragged
    (np.array([np.nan, 0.0, 0.0]), "NaN or inf"),            # returned [nan] before
    (np.array([[0.0, 0.0, 0.0], [np.inf, 0.0, 0.0]]), "NaN or inf"),
    (torch.tensor([0.0, float("nan"), 0.0]), "NaN or inf"),
])
def test_act_refuses_a_wrong_observation_in_one_line_naming_obs(obs, says):
    policy = drivelab.load(PENDULUM)
    with pytest.raises(DrivelabError) as excinfo:
        policy.act(obs)
    message = one_line(excinfo)
    assert message.startswith("obs: ") and says in message, message
    if "shape" in says:
        assert "(3,) (one observation) or (N, 3) (a batch)" in message


def test_act_takes_one_observation_or_a_batch_as_numpy_torch_or_lists():
    policy = drivelab.load(PENDULUM)
    obs = np.array([0.5, -0.5, 0.1], np.float32)
    single = policy.act(obs)
    assert single.shape == (1,)
    for same in (obs.astype(np.float64), torch.as_tensor(obs), obs.tolist()):   # cast, not refused
        np.testing.assert_allclose(policy.act(same), single, atol=1e-6)
    batch = np.stack([obs, -obs])
    assert policy.act(batch).shape == (2, 1) and policy.act(torch.as_tensor(batch)).shape == (2, 1)
    np.testing.assert_allclose(policy.act(batch)[0], single, atol=1e-6)


# --- evaluate, load, train: arguments --------------------------------------------------------

def test_evaluate_refuses_an_env_with_other_spaces_naming_both():
    policy = drivelab.load(PENDULUM)
    with pytest.raises(DrivelabError) as excinfo:   # a torch matrix-shape RuntimeError before
        drivelab.evaluate(policy, "CartPole-v1", episodes=1)
    message = one_line(excinfo)
    assert "CartPole-v1 has observations Box(4,)" in message and "takes Box(3,)" in message
    assert "Pendulum-v1" in message
    with pytest.raises(DrivelabError, match="has observations Box"):   # an env instance too
        drivelab.evaluate(policy, gym.make("CartPole-v1"), episodes=1)
    with pytest.raises(DrivelabError, match="policy: expected a policy from drivelab.load"):
        drivelab.evaluate(str(PENDULUM), "Pendulum-v1")
    for bad in ({"episodes": 0}, {"episodes": "3"}, {"num_envs": 2.5}, {"seed": -1}):
        with pytest.raises(DrivelabError, match=f"{next(iter(bad))}: expected an integer"):
            drivelab.evaluate(policy, **bad)


def test_evaluate_returns_the_dict_that_eval_json_prints(capsys):
    from drivelab.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["eval", str(PENDULUM), "--episodes", "2", "--json"])
    assert exit_.value.code in (0, None), capsys.readouterr().err
    printed = json.loads(capsys.readouterr().out)
    returned = drivelab.evaluate(drivelab.load(PENDULUM), episodes=2)
    assert returned == printed
    assert {"env", "checkpoint", "step", "return_mean", "episodes"} <= set(returned)


@pytest.mark.parametrize("path", [42, None, 1.5, ["runs/x"]])
def test_load_refuses_what_is_not_a_path(path):
    with pytest.raises(DrivelabError) as excinfo:   # TypeError from pathlib before
        drivelab.load(path)
    assert one_line(excinfo).startswith("path: expected a run or checkpoint directory")


def test_train_needs_an_algorithm(tmp_path):
    with pytest.raises(DrivelabError) as excinfo:   # trained REINFORCE before
        drivelab.train(None, "CartPole-v1", steps=64, run_dir=tmp_path / "r", progress=False)
    assert one_line(excinfo).startswith("algo: name the algorithm") and "ppo" in str(excinfo.value)
    with pytest.raises(DrivelabError, match="algo: expected an algorithm's name"):
        drivelab.train(3, "CartPole-v1", steps=64, run_dir=tmp_path / "r", progress=False)
    assert not (tmp_path / "r").exists()   # refused before anything was written


@pytest.mark.parametrize("resume, says", [
    ("maybe", "'maybe', which is no directory"),   # was truthy: resumed
    (3, "got int 3"),
    (Path("no/such/run"), "which is no directory"),
])
def test_train_accepts_only_the_resume_values_of_the_cli(resume, says, tmp_path):
    with pytest.raises(DrivelabError) as excinfo:
        drivelab.train("ppo", "CartPole-v1", steps=64, run_dir=tmp_path / "r", resume=resume, progress=False)
    message = one_line(excinfo)
    assert message.startswith("resume: expected True, False, 'auto' or a run directory") and says in message


def test_resume_true_needs_a_run_dir_and_a_resume_path_must_agree_with_it(tmp_path):
    with pytest.raises(DrivelabError, match="resume=True continues the run in run_dir"):
        drivelab.train("ppo", "CartPole-v1", steps=64, resume=True, progress=False)
    (tmp_path / "a").mkdir()
    with pytest.raises(DrivelabError, match="names another; give one of them"):
        drivelab.train(resume=tmp_path / "a", run_dir=tmp_path / "b", steps=64, progress=False)


# --- a user's env class with no __init__ arguments ---------------------------------------------

def test_a_no_argument_env_class_trains_evaluates_resumes_and_exports_from_python(tmp_path):
    run = tmp_path / "run"
    common = {"num_envs": 2, "progress": False, "ppo": {"num_steps": 64}}
    first = drivelab.train("ppo", Corridor, steps=256, seed=0, run_dir=run, **common)
    assert first.metrics["episode/length"] > 0
    assert "test_api_inputs:Corridor" in (run / "config.yaml").read_text()   # found again by eval, resume, export
    policy = drivelab.load(run)
    by_class = drivelab.evaluate(policy, Corridor, episodes=3)            # AttributeError 'rpartition' before
    by_default = drivelab.evaluate(policy, episodes=3)
    by_id = drivelab.evaluate(policy, "test_api_inputs:Corridor", episodes=3)
    assert by_class == by_default == by_id and by_class["env"] == "test_api_inputs:Corridor"
    assert by_class["episodes"] == 3 and by_class["step"] == 256
    env = drivelab.make_env(policy.env_config)
    obs, _ = env.reset(seed=0)
    assert int(policy.act(obs)) in (0, 1)
    drivelab.train(run_dir=run, resume=True, steps=384, **common)          # the run's saved config
    drivelab.train(resume=run, steps=512, **common)                        # as --resume RUN_DIR
    assert drivelab.evaluate(drivelab.load(run), Corridor, episodes=2)["step"] == 512
    pytest.importorskip("onnx")
    onnxruntime = pytest.importorskip("onnxruntime")
    drivelab.load(run).export(tmp_path / "onnx", "onnx")
    session = onnxruntime.InferenceSession(str(tmp_path / "onnx" / "policy.onnx"))
    batch = np.stack([obs, obs])
    np.testing.assert_array_equal(session.run(None, {"obs": batch})[0], drivelab.load(run).act(batch))


def test_a_no_argument_env_class_trains_evaluates_resumes_and_exports_from_the_cli(tmp_path, capsys):
    from drivelab.cli import main

    run = str(tmp_path / "run")
    common = ["--no-progress", "--num-envs", "2", "--ppo.num_steps", "64"]
    outputs = []
    for argv in (["train", "--algo", "ppo", "--env", "test_api_inputs:Corridor", "--steps", "256", "--run-dir", run,
                  *common],
                 ["train", "--resume", run, "--steps", "384", *common],
                 ["eval", run, "--episodes", "2", "--json"],
                 ["export", run, "--format", "torchscript", "--out", str(tmp_path / "ts")]):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        captured = capsys.readouterr()
        assert exit_.value.code in (0, None), (argv, captured.err)
        outputs.append(captured.out)
    evaluation = json.loads(outputs[2])
    assert evaluation["env"] == "test_api_inputs:Corridor" and evaluation["step"] == 384
    assert (tmp_path / "ts" / "policy.pt").is_file() and (tmp_path / "ts" / "policy.json").is_file()
