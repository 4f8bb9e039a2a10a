"""The Python API (drivelab.train / load / evaluate) and exported policies (ONNX, TorchScript)."""

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

import drivelab
from drivelab.config import EnvConfig
from drivelab.tools.export import DeployedPolicy
from drivelab.training.learning.policy_nets import ActorCritic


def test_notebook_style_train_load_act_evaluate(tmp_path):
    result = drivelab.train("ppo", "CartPole-v1", steps=4096, seed=0, num_envs=4, run_dir=tmp_path / "nb",
                            ppo={"num_steps": 256}, progress=False)
    policy = drivelab.load(result.run_dir)
    env = drivelab.make_env("CartPole-v1")
    obs, _ = env.reset(seed=0)
    action = policy.act(obs)
    summary = drivelab.evaluate(policy, "CartPole-v1", episodes=3)
    assert action in (0, 1) and policy.act(np.stack([obs, obs])).shape == (2,)
    assert summary["episodes"] == 3 and "return_mean" in summary and "episode/return" in result.metrics


def _export_both(policy, out):
    import onnxruntime

    policy.export(out / "onnx", "onnx")
    policy.export(out / "ts", "torchscript")
    session = onnxruntime.InferenceSession(str(out / "onnx" / "policy.onnx"))
    scripted = torch.jit.load(str(out / "ts" / "policy.pt"))
    return (lambda x: session.run(None, {"obs": x})[0]), (lambda x: scripted(torch.as_tensor(x)).numpy())


@pytest.mark.parametrize("algo, env, params", [
    ("ppo", "CartPole-v1", {"ppo": {"num_steps": 128, "normalize_obs": True}}),      # discrete, obs normalisation
    ("sac", "Pendulum-v1", {"sac": {"learning_starts": 200, "hidden": [32, 32], "batch_size": 32}}),  # tanh-squashed
])
def test_exported_policies_match_the_python_policy(algo, env, params, tmp_path):
    result = drivelab.train(algo, env, steps=600 if algo == "sac" else 2048, seed=0, run_dir=tmp_path / "r",
                            progress=False, **params)
    policy = drivelab.load(result.run_dir)
    run_onnx, run_ts = _export_both(policy, tmp_path)
    space = policy.observation_space
    obs = np.random.default_rng(0).uniform(-3, 3, (1000, *space.shape)).astype(space.dtype)
    expected = policy.act(obs)
    np.testing.assert_allclose(run_onnx(obs), expected, atol=1e-5)
    np.testing.assert_allclose(run_ts(obs), expected, atol=1e-5)
    np.testing.assert_allclose(run_onnx(obs[:1])[0], policy.act(obs[0]), atol=1e-5)   # a single observation
    meta = json.loads((tmp_path / "onnx" / "policy.json").read_text())
    assert meta["algo"] == algo and meta["input"]["shape"] == list(space.shape) and meta["drivelab_version"]
    if algo == "sac":  # actions within the env's bounds: the tanh squashing and scaling are in the graph
        assert np.all(np.abs(expected) <= 2.0 + 1e-6)
    # the exported policy, played alone, scores what drivelab's evaluation scores on the same seeds
    env_ = gym.make(env)
    returns = []
    for k in range(3):
        o, _ = env_.reset(seed=k)
        total, done = 0.0, False
        while not done:
            o, r, terminated, truncated, _ = env_.step(run_onnx(o[None].astype(space.dtype))[0])
            total, done = total + r, terminated or truncated
        returns.append(total)
    assert np.mean(returns) == pytest.approx(drivelab.evaluate(policy, env, episodes=3)["return_mean"], abs=1e-3)


def test_the_action_grid_is_inside_the_deployed_policy():
    torch.manual_seed(0)
    obs_space = gym.spaces.Box(-1, 1, (5,), np.float32)
    network = ActorCritic(obs_space, gym.spaces.Discrete(9), [8])
    deployed = DeployedPolicy(network, EnvConfig(id="MetaDrive-validation-v0", action_grid="3x3"))
    obs = torch.randn(50, 5)
    index = network.deterministic_action(obs)
    # notebook 000's numbering: 0 = full throttle + left, 1 = full throttle + straight, ..., 8 = brake + right
    table = np.array([[s, t] for t in (1.0, 0.0, -1.0) for s in (0.6, 0.0, -0.6)], np.float32)
    np.testing.assert_array_equal(deployed(obs).numpy(), table[index.numpy()])
    throttle = DeployedPolicy(ActorCritic(obs_space, gym.spaces.Box(-1, 1, (1,), np.float32), [8]),
                              EnvConfig(id="MetaDrive-validation-v0", fixed_throttle=0.3))
    out = throttle(obs)
    assert out.shape == (50, 2) and torch.all(out[:, 1] == 0.3)


@pytest.mark.parametrize("algo, env", [("reinforce", "CartPole-v1"), ("a2c", "CartPole-v1"), ("ppo", "CartPole-v1"),
                                       ("grpo", "CartPole-v1"), ("ddpg", "Pendulum-v1"), ("td3", "Pendulum-v1"),
                                       ("sac", "Pendulum-v1")])
def test_every_algorithm_runs_with_its_defaults(algo, env, tmp_path):
    result = drivelab.train(algo, env, steps=64, run_dir=tmp_path / algo, progress=False)
    assert result.metrics["perf/steps_per_s"] > 0 and drivelab.load(result.run_dir).act(
        drivelab.make_env(env).observation_space.sample()) is not None
