"""DDPG / TD3 / SAC: numerics of the shared pieces, checkpoints with the buffer, learning."""

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from drivelab.algos.sac import soft_td_target
from drivelab.algos.td3 import td_target
from drivelab.training.outputs.checkpoint import list_checkpoints
from drivelab.api import build_config
from drivelab.config import read_yaml
from drivelab.errors import DrivelabError
from drivelab.api import evaluate_checkpoint
from drivelab.tools.policies import load_policy
from drivelab.training.learning.offpolicy_nets import (EnsembleBatchNorm, EnsembleLinear, OffPolicyAgent,
                                                       polyak_update, squashed_gaussian_log_prob)
from drivelab.api import train

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def test_td_targets_bootstrap_through_truncation_but_not_termination():
    r = torch.tensor([1.0, 1.0])
    terminated = torch.tensor([1.0, 0.0])            # the second transition was truncated (time limit)
    next_q = torch.tensor([[5.0, 5.0], [3.0, 4.0]])  # (E=2, B)
    np.testing.assert_allclose(td_target(r, terminated, next_q, 0.9).numpy(), [1.0, 1.0 + 0.9 * 4.0])
    y = soft_td_target(r, terminated, next_q, torch.tensor([0.5, 0.5]), torch.tensor(0.2), 0.9)
    np.testing.assert_allclose(y.numpy(), [1.0, 1.0 + 0.9 * (4.0 - 0.2 * 0.5)], rtol=1e-6)


def test_tanh_log_prob_matches_the_change_of_variables():
    torch.manual_seed(0)
    mean, log_std = torch.randn(64, 2), 0.5 * torch.randn(64, 2)
    u = mean + log_std.exp() * torch.randn(64, 2)
    ours = squashed_gaussian_log_prob(u, mean, log_std)
    # p_A(a) = p_U(u) / |det da/du| with a = tanh(u): da/du = 1 - tanh(u)^2 per dimension
    gaussian = torch.distributions.Normal(mean, log_std.exp()).log_prob(u).sum(-1)
    by_hand = gaussian - torch.log(1 - torch.tanh(u) ** 2).sum(-1)
    torch.testing.assert_close(ours, by_hand, rtol=1e-4, atol=1e-4)
    # and it is a density on (-1, 1): integrate a 1-D case numerically
    grid = torch.linspace(-0.9999, 0.9999, 20001)
    u1 = torch.atanh(grid)[:, None]
    density = squashed_gaussian_log_prob(u1, torch.full_like(u1, 0.3), torch.full_like(u1, math.log(0.8))).exp()
    assert torch.trapezoid(density, grid).item() == pytest.approx(1.0, abs=2e-3)
    # it stays finite where tanh saturates
    assert torch.isfinite(squashed_gaussian_log_prob(torch.tensor([[30.0]]), torch.zeros(1, 1), torch.zeros(1, 1))).all()


def test_polyak_update():
    source, target = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    torch.nn.init.ones_(source.weight), torch.nn.init.zeros_(target.weight)
    polyak_update(target, source, 0.1)
    torch.testing.assert_close(target.weight, torch.full((2, 2), 0.1))
    polyak_update(target, source, 0.1)
    torch.testing.assert_close(target.weight, torch.full((2, 2), 0.19))


def test_ensemble_linear_equals_separate_layers():
    layer = EnsembleLinear(2, 3, 4)
    x = torch.randn(5, 3)
    out = layer(x.expand(2, 5, 3))
    for e in range(2):
        torch.testing.assert_close(out[e], x @ layer.weight[e] + layer.bias[e, 0])


def test_critic_layer_norm_normalises_each_critics_hidden_layers(tmp_path):
    agent = OffPolicyAgent(gym.spaces.Box(-1, 1, (3,)), gym.spaces.Box(-1, 1, (2,)), [16, 16], "relu",
                           stochastic=False, critics=2, critic_layer_norm=True)
    x = 10 * torch.randn(7, 5)                       # features and actions, far from unit scale
    hidden = agent.critic.net[:2](x.expand(2, 7, 5))  # first linear layer of both critics, then the norm
    torch.testing.assert_close(hidden.mean(-1), torch.zeros(2, 7), atol=1e-5, rtol=0)
    torch.testing.assert_close(hidden.var(-1, unbiased=False), torch.ones(2, 7), atol=1e-3, rtol=0)
    assert not list(agent.critic.net[1].parameters())  # no shared gain: the twins stay independent
    # the config field reaches the critics of a trained run, and its checkpoint loads for evaluation
    train(_pendulum(tmp_path / "ln", "td3", 300, critic_layer_norm=True), progress=False)
    result, _, _ = evaluate_checkpoint(tmp_path / "ln", episodes=1)
    assert math.isfinite(result.summary()["return_mean"])
    tensors = load_file(str(list_checkpoints(tmp_path / "ln")[-1] / "tensors.safetensors"))
    assert "module/policy/critic.net.3.weight" in tensors        # Linear, LayerNorm, ReLU, Linear...


def test_ensemble_batch_norm_normalises_each_member_over_the_batch():
    torch.manual_seed(0)
    norm = EnsembleBatchNorm(2, 3, momentum=0.1, eps=0.0)
    x = torch.randn(2, 50, 3) * torch.tensor([1.0, 5.0, 0.1]) + torch.tensor([[[2.0]], [[-7.0]]])
    out = norm(x)                                                    # train mode: this batch's statistics
    torch.testing.assert_close(out.mean(dim=1), torch.zeros(2, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(out.var(dim=1, unbiased=False), torch.ones(2, 3), atol=1e-4, rtol=0)
    torch.testing.assert_close(norm.running_mean, 0.1 * x.mean(dim=1, keepdim=True))
    torch.testing.assert_close(norm.running_var, 0.9 + 0.1 * x.var(dim=1, keepdim=True))
    norm.eval()                                                      # eval mode: the running statistics
    y = torch.randn(2, 4, 3)
    torch.testing.assert_close(norm(y), (y - norm.running_mean) / norm.running_var.sqrt())
    torch.testing.assert_close(norm(y[:1]), norm(y)[:1])             # a 1-member input uses member 0's
    with torch.no_grad():                                            # each member's own gain and bias
        norm.weight.copy_(torch.tensor([2.0, 3.0]).view(2, 1, 1))
        norm.bias.copy_(torch.tensor([-5.0, 1.0]).view(2, 1, 1))
    scale = torch.tensor([2.0, 3.0]).view(2, 1, 1)
    shift = torch.tensor([-5.0, 1.0]).view(2, 1, 1)
    torch.testing.assert_close(norm(y), (y - norm.running_mean) / norm.running_var.sqrt() * scale + shift)


def test_td3_crossq_trains_without_targets_and_its_checkpoint_evaluates(tmp_path):
    train(_pendulum(tmp_path / "cq", "td3", 300, crossq=True), progress=False)
    tensors = load_file(str(list_checkpoints(tmp_path / "cq")[-1] / "tensors.safetensors"))
    assert not any(k.startswith("module/target/") for k in tensors)
    assert "module/policy/critic.net.0.running_mean" in tensors      # batch norm, then the first linear
    result, _, _ = evaluate_checkpoint(tmp_path / "cq", episodes=1)
    assert math.isfinite(result.summary()["return_mean"])
    with pytest.raises(DrivelabError, match="crossq"):
        _pendulum(tmp_path / "both", "td3", 300, crossq=True, critic_layer_norm=True)


def test_discrete_actions_are_refused_clearly():
    with pytest.raises(DrivelabError, match="continuous"):
        OffPolicyAgent(gym.spaces.Box(-1, 1, (3,)), gym.spaces.Discrete(9), [8], "relu", stochastic=True)


def _pendulum(run_dir, algo, steps, **params):
    return build_config({"algo": algo, "steps": steps, "seed": 0, "run_dir": str(run_dir), "checkpoint_every": 300,
                         "env": {"id": "Pendulum-v1", "num_envs": 1},
                         algo: {"learning_starts": 200, "hidden": [32, 32], "batch_size": 32, **params}})


def test_resume_continues_with_the_same_replay_buffer(tmp_path):
    train(_pendulum(tmp_path / "r", "sac", 600), progress=False)
    first = load_file(str(list_checkpoints(tmp_path / "r")[-1] / "tensors.safetensors"))
    train(_pendulum(tmp_path / "r", "sac", 900), resume=True, progress=False)
    final = list_checkpoints(tmp_path / "r")[-1]
    assert final.name.endswith("900")
    second = load_file(str(final / "tensors.safetensors"))
    assert first["replay/obs"].shape[0] == 600 and second["replay/obs"].shape[0] == 900
    for name in ("obs", "next_obs", "actions", "rewards", "terminated", "truncated"):
        assert torch.equal(second[f"replay/{name}"][:600], first[f"replay/{name}"]), name
    assert second["replay/truncated"].sum() == 4 and second["replay/terminated"].sum() == 0  # 200-step episodes


def test_sac_average_policy_is_what_checkpoints_hold_as_the_policy_and_it_resumes(tmp_path):
    run_dir = tmp_path / "avg"
    train(_pendulum(run_dir, "sac", 600, average_policy=0.05, actor_every=2), progress=False)
    start = load_file(str(list_checkpoints(run_dir)[0] / "tensors.safetensors"))
    at_600 = load_file(str(list_checkpoints(run_dir)[-1] / "tensors.safetensors"))
    actor = [k for k in start if k.startswith("module/policy/actor.")]
    assert actor and all(k.replace("/policy/", "/learner/") in at_600 for k in actor)
    # the average starts as a copy of the agent, then trails it
    assert all(torch.equal(start[k], start[k.replace("/policy/", "/learner/")]) for k in actor)
    assert not all(torch.allclose(at_600[k], at_600[k.replace("/policy/", "/learner/")]) for k in actor)
    assert not all(torch.equal(at_600[k], start[k]) for k in actor)
    # what drivelab eval, export and the in-training evaluation load is the average, not the learner
    loaded, _, _ = load_policy(run_dir)
    for name, value in loaded.state_dict().items():
        if name.startswith("actor."):
            assert torch.equal(value, at_600[f"module/policy/{name}"]), name
    train(_pendulum(run_dir, "sac", 900, average_policy=0.05, actor_every=2), resume=True, progress=False)
    at_900 = load_file(str(list_checkpoints(run_dir)[-1] / "tensors.safetensors"))
    assert not all(torch.equal(at_900[k], at_600[k]) for k in actor)


def test_sac_trains_with_bf16_updates_and_saves_float32_weights(tmp_path, monkeypatch, capsys):
    # On hardware without bfloat16 arithmetic (here pretended) the run says so in one line and trains on.
    monkeypatch.setattr("drivelab.training.run.run.native_bf16", lambda device: False)
    run_dir = tmp_path / "bf16"
    train(_pendulum(run_dir, "sac", 600, bf16_updates=True), progress=False)
    warnings = [line for line in capsys.readouterr().err.splitlines() if "bf16_updates" in line]
    assert len(warnings) == 1 and "emulation" in warnings[0] and "--sac.bf16_updates auto or false" in warnings[0]
    start = load_file(str(list_checkpoints(run_dir)[0] / "tensors.safetensors"))
    end = load_file(str(list_checkpoints(run_dir)[-1] / "tensors.safetensors"))
    weights = [k for k in end if k.startswith(("module/policy/actor.", "module/policy/critic."))]
    assert weights and all(end[k].dtype == torch.float32 and torch.isfinite(end[k]).all() for k in weights)
    assert not all(torch.equal(end[k], start[k]) for k in weights)


@pytest.mark.parametrize("field, value", [("average_policy", 1.0), ("average_policy", -0.1), ("actor_every", 0)])
def test_sac_rejects_out_of_range_averaging_and_actor_delay(field, value, tmp_path):
    with pytest.raises(DrivelabError, match=field):
        build_config({"algo": "sac", "run_dir": str(tmp_path), "env": {"id": "Pendulum-v1"}, "sac": {field: value}})


def test_sac_learns_from_images_with_a_cnn(tmp_path):
    cfg = build_config({"algo": "sac", "steps": 150, "seed": 0, "run_dir": str(tmp_path / "img"),
                        "env": {"id": "CarRacing-v3", "num_envs": 1},
                        "sac": {"learning_starts": 100, "buffer_size": 1000, "batch_size": 8, "hidden": [32]}})
    train(cfg, progress=False)
    tensors = load_file(str(list_checkpoints(tmp_path / "img")[-1] / "tensors.safetensors"))
    assert tensors["replay/obs"].dtype == torch.uint8
    assert any(k.startswith("module/policy/encoder.convs") for k in tensors)


# The shipped Pendulum configs at a shorter budget, scored on 10 start states by the deterministic
# policy (one that has not learned scores about -1200). TD3 trains with its env workers acting
# (act_in_workers, chunks of 16 steps): the asynchronous collector must still learn. The budgets
# and thresholds leave a margin for the float32 rounding of different CPUs' kernels, which changes
# a seed's run; the runs behind them are in docs/history.md ("Pendulum test budgets").
@pytest.mark.slow
@pytest.mark.parametrize("algo, steps, threshold", [("sac", 6000, -250), ("td3", 12000, -400)])
def test_sac_and_td3_swing_up_the_pendulum(algo, steps, threshold, tmp_path):
    shipped = read_yaml(CONFIGS / f"{algo}_pendulum.yaml")
    if algo == "td3":
        shipped = {**shipped, "env": {**shipped["env"], "num_envs": 2, "backend": "async"},
                   "td3": {**shipped["td3"], "act_in_workers": True, "chunk_steps": 16}}
    cfg = build_config({**shipped, "steps": steps, "seed": 0, "run_dir": str(tmp_path / algo),
                        "eval": {"every": 0}})
    train(cfg, progress=False)
    result, _, _ = evaluate_checkpoint(tmp_path / algo, episodes=10)
    assert result.summary()["return_mean"] >= threshold, result.summary()


@pytest.mark.slow
def test_ddpg_improves_on_pendulum(tmp_path):
    shipped = read_yaml(CONFIGS / "ddpg_pendulum.yaml")
    cfg = build_config({**shipped, "steps": 8000, "seed": 0, "run_dir": str(tmp_path / "ddpg"),
                        "eval": {"every": 0}})
    train(cfg, progress=False)
    before, _, _ = evaluate_checkpoint(list_checkpoints(tmp_path / "ddpg")[0], episodes=10)
    after, _, _ = evaluate_checkpoint(tmp_path / "ddpg", episodes=10)
    assert after.summary()["return_mean"] > before.summary()["return_mean"] + 300, (before.summary(), after.summary())
