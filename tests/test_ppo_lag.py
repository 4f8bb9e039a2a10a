"""PPO-Lagrangian: the cost's GAE and the Lagrangian advantage by hand, the update pinned against a
reference loss, the collector's costs on both paths, exact resume of the multiplier, and learning
on ThreeLanes (tests/constrained_env.py), whose constrained optimum is known."""

import copy
import csv

import gymnasium as gym
import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from drivelab.algos import ppo, ppo_lag
from drivelab.api import build_config, evaluate, load, train
from drivelab.envs import env_spaces
from drivelab.errors import DrivelabError
from drivelab.training.collection.rollout import RolloutCollector
from drivelab.training.learning.losses import lagrangian_advantages, standardize
from drivelab.training.learning.policy_nets import ActorCritic
from drivelab.training.learning.rollout_buffers import RolloutBatch, RolloutBuffer
from drivelab.training.outputs.checkpoint import checkpoint_step, resolve_checkpoint
from drivelab.training.run import Run

THREE_LANES = "constrained_env:ThreeLanes-v0"
OBS = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
DISCRETE = gym.spaces.Discrete(2)
LR = 0.1


def test_cost_gae_by_hand_bootstraps_a_truncation_from_the_final_cost_value():
    # one env, three steps: truncated at step 0 (V_c(final obs) = 4), then terminated at step 2;
    # gamma_c = lam = 0.5. The reward side is left at zeros.
    buf = RolloutBuffer(3, 1, OBS, DISCRETE, torch.device("cpu"), costs=True)
    buf.costs[:, 0] = [1.0, 0.0, 2.0]
    buf.cost_values[:, 0] = torch.tensor([0.5, 1.0, 1.5])
    buf.cost_next_values[:, 0] = [4.0, 1.5, 9.9]          # 9.9 is ignored: terminated
    buf.terminated[:, 0] = [False, False, True]
    buf.dones[:, 0] = [True, False, True]
    batch = buf.batch(gamma=0.9, gae_lambda=0.5, cost_gamma=0.5)
    d0 = 1.0 + 0.5 * 4.0 - 0.5                              # 2.5: the truncation bootstraps from V_c(final obs)
    d1 = 0.0 + 0.5 * 1.5 - 1.0                              # -0.25
    d2 = 2.0 - 1.5                                          # 0.5
    a2, a1 = d2, d1 + 0.25 * d2
    a0 = d0                                                 # the trace stops at the episode end
    torch.testing.assert_close(batch.cost_advantages, torch.tensor([a0, a1, a2]))
    torch.testing.assert_close(batch.cost_returns, torch.tensor([a0 + 0.5, a1 + 1.0, a2 + 1.5]))
    torch.testing.assert_close(batch.cost_values, torch.tensor([0.5, 1.0, 1.5]))


def test_a_buffer_without_costs_makes_the_batch_it_always_made():
    buf = RolloutBuffer(2, 1, OBS, DISCRETE, torch.device("cpu"))
    assert buf.costs is None and buf.cost_values is None
    batch = buf.batch(0.9, 0.5)
    assert batch.cost_values is batch.cost_advantages is batch.cost_returns is None


def test_the_lagrangian_advantage_by_hand():
    # lam = 1: ([2, -2] - [1, 1]) / 2
    a = lagrangian_advantages(torch.tensor([2.0, -2.0]), torch.tensor([1.0, 1.0]), lam=1.0)
    torch.testing.assert_close(a, torch.tensor([0.5, -1.5]))
    # lam = 0 is the reward's advantage; a large lam tends to minus the cost's
    torch.testing.assert_close(lagrangian_advantages(torch.tensor([3.0]), torch.tensor([5.0]), 0.0), torch.tensor([3.0]))
    torch.testing.assert_close(lagrangian_advantages(torch.tensor([3.0]), torch.tensor([5.0]), 999.0),
                               torch.tensor([(3.0 - 999.0 * 5.0) / 1000.0]))
    # a minibatch without cost standardises to zeros, not NaN
    assert torch.equal(standardize(torch.zeros(4)), torch.zeros(4))


def _rollout_batch(agent, log_prob_offsets):
    obs = torch.as_tensor(np.random.default_rng(1).uniform(-1, 1, (6, 3)), dtype=torch.float32)
    actions = torch.tensor([0, 1, 0, 1, 1, 0])
    with torch.no_grad():
        log_probs = agent.distribution(obs).log_prob(actions) + torch.tensor(log_prob_offsets)
        values, cost_values = agent.value(obs) + 0.3, agent.cost_value(obs) - 0.4
    advantages = torch.tensor([1.0, -0.5, 2.0, 0.0, -1.5, 0.7])
    cost_advantages = torch.tensor([0.0, 1.0, 0.0, 0.5, 2.0, 0.0])
    return RolloutBatch(obs, actions, log_probs, values, advantages, advantages + values,
                        cost_values, cost_advantages, cost_advantages + cost_values)


def test_ppo_lag_update_is_the_clipped_lagrangian_surrogate_plus_both_value_losses_by_hand():
    torch.manual_seed(0)
    agent = ActorCritic(OBS, DISCRETE, [4], cost_critic=True)
    batch = _rollout_batch(agent, [-0.5, 0.5, 0.0, -0.1, 0.2, -0.3])
    hp = ppo_lag.Params(update_epochs=1, num_minibatches=1, clip_coef=0.2, ent_coef=0.01, vf_coef=0.5, max_grad_norm=1e9)
    lam = 2.0

    def reference(a):
        dist = a.distribution(batch.obs)
        ratio = (dist.log_prob(batch.actions) - batch.log_probs).exp()
        adv_r = (batch.advantages - batch.advantages.mean()) / (batch.advantages.std() + 1e-8)
        adv_c = (batch.cost_advantages - batch.cost_advantages.mean()) / (batch.cost_advantages.std() + 1e-8)
        adv = (adv_r - lam * adv_c) / (1 + lam)
        pg = -torch.min(ratio * adv, ratio.clamp(0.8, 1.2) * adv).mean()

        def clipped_value_loss(v, old, target):
            v_clipped = old + (v - old).clamp(-0.2, 0.2)
            return 0.5 * torch.max((v - target) ** 2, (v_clipped - target) ** 2).mean()

        vl = clipped_value_loss(a.value(batch.obs), batch.values, batch.returns)
        cl = clipped_value_loss(a.cost_value(batch.obs), batch.cost_values, batch.cost_returns)
        return pg + 0.5 * (vl + cl) - 0.01 * dist.entropy().mean()

    ref = copy.deepcopy(agent)
    ref_loss = reference(ref)
    grads = torch.autograd.grad(ref_loss, list(ref.parameters()))
    expected = {name: p.detach() - LR * g for (name, p), g in zip(ref.named_parameters(), grads)}
    out = ppo_lag.update(agent, torch.optim.SGD(agent.parameters(), lr=LR), batch, hp, lam)
    total = out["loss/policy"] + 0.5 * (out["loss/value"] + out["loss/cost_value"]) - 0.01 * out["loss/entropy"]
    assert total.item() == pytest.approx(ref_loss.item(), rel=1e-5)
    assert out["charts/cost_value_mean"].item() == pytest.approx(batch.cost_values.mean().item())
    for name, p in agent.named_parameters():
        torch.testing.assert_close(p.detach(), expected[name], atol=1e-6, rtol=1e-5, msg=name)
    assert any(name.startswith("cost_critic.") for name in expected)   # the cost critic learned too


def test_with_lambda_zero_and_no_cost_the_actor_and_critic_take_ppos_step():
    torch.manual_seed(0)
    agent = ActorCritic(OBS, DISCRETE, [4], cost_critic=True)
    batch = _rollout_batch(agent, [-0.5, 0.5, 0.0, -0.1, 0.2, -0.3])
    batch = batch._replace(cost_advantages=torch.zeros(6))
    twin = copy.deepcopy(agent)
    params = {"update_epochs": 2, "num_minibatches": 2, "max_grad_norm": 1e9}
    torch.manual_seed(1)
    ppo_lag.update(agent, torch.optim.SGD(agent.parameters(), lr=LR), batch, ppo_lag.Params(**params), lam=0.0)
    torch.manual_seed(1)   # the same minibatches
    ppo.update(twin, torch.optim.SGD(twin.parameters(), lr=LR), batch, ppo.Params(**params))
    for (name, p), q in zip(agent.named_parameters(), twin.parameters()):
        if not name.startswith("cost_critic."):
            torch.testing.assert_close(p, q, msg=name)


def test_a_cost_critic_leaves_the_other_networks_and_their_initial_weights_as_they_were():
    torch.manual_seed(0)
    plain = ActorCritic(OBS, DISCRETE, [4])
    torch.manual_seed(0)
    with_cost = ActorCritic(OBS, DISCRETE, [4], cost_critic=True)
    for name, p in plain.state_dict().items():
        assert torch.equal(p, with_cost.state_dict()[name]), name
    assert plain.cost_critic is None and {k for k in with_cost.state_dict() if k.startswith("cost_critic.")}


class _HandCostCritic(torch.nn.Module):
    """V_c(s) = 10 (k + 1) on ThreeLanes' one-hot observation of stretch k: computable by hand."""

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return obs @ torch.tensor([[10.0], [20.0], [30.0], [40.0]])


def hand_cost_agent(obs_space, act_space) -> ActorCritic:
    """A small actor-critic with the hand-made cost critic (a policy factory for the env workers too)."""
    agent = ActorCritic(obs_space, act_space, [8], cost_critic=True)
    agent.cost_critic = _HandCostCritic()
    return agent


@pytest.mark.parametrize("in_workers", [False, True], ids=["trainer-steps", "act-in-workers"])
def test_collector_stores_step_costs_and_bootstraps_the_cost_value_on_truncation(in_workers, tmp_path):
    # ThreeLanes cut after 2 of its 4 stretches: every episode is truncated at its second step
    cfg = build_config({"algo": "ppo_lag", "run_dir": str(tmp_path), "seed": 0,
                        "env": {"id": THREE_LANES, "num_envs": 2, "kwargs": {"max_episode_steps": 2},
                                "backend": "async" if in_workers else "sync"}})
    obs_space, act_space = env_spaces(cfg.env)
    agent = hand_cost_agent(obs_space, act_space)
    run = Run(cfg, progress=False)
    collector = RolloutCollector(cfg.env, run, num_steps=5, gamma=0.99, gae_lambda=0.95, scale_rewards=False,
                                 policy_factory=hand_cost_agent if in_workers else None, cost_gamma=0.5)
    buf = collector.buffer
    try:
        batch = collector.collect(agent)
    finally:
        collector.close()
        run.close()
    lane_cost = {1.25: 0.0, 2.0: 0.25, 2.5: 1.0}          # ThreeLanes: reward -> cost of the lane taken
    np.testing.assert_array_equal(buf.costs, np.vectorize(lane_cost.get)(buf.rewards))
    assert buf.dones[[1, 3]].all() and not buf.terminated.any() and not buf.dones[[0, 2, 4]].any()
    stretch = buf.obs.argmax(-1).numpy()                   # 0, 1, 0, 1, 0 in each env
    np.testing.assert_array_equal(stretch, [[0, 0], [1, 1], [0, 0], [1, 1], [0, 0]])
    np.testing.assert_allclose(buf.cost_values.numpy(), 10.0 * (stretch + 1))
    # inside an episode V_c of the next row; on the truncated step V_c(final obs: stretch 2) = 30,
    # never the next episode's first row (10); after the rollout V_c(stretch 1) = 20
    np.testing.assert_allclose(buf.cost_next_values, [[20, 20], [30, 30], [20, 20], [30, 30], [20, 20]])
    delta = buf.costs + 0.5 * buf.cost_next_values - buf.cost_values.numpy()
    np.testing.assert_allclose(batch.cost_advantages.reshape(5, 2)[[1, 3, 4]], delta[[1, 3, 4]], rtol=1e-6)
    assert run.episodes.cost_episodes == 4 and run.episodes.cost_total == pytest.approx(buf.costs[:4].sum())


def _config(run_dir, steps, algo="ppo_lag", **extra):
    data = {"algo": algo, "seed": 0, "steps": steps, "run_dir": str(run_dir), "log_every": 2048,
            "env": {"id": THREE_LANES, "num_envs": 8},
            algo: {"num_steps": 64, "hidden": [32], "lr": 3e-3}}
    if algo == "ppo_lag":
        data[algo].update(cost_limit=1.0, lagrange_lr=0.1)
    data.update(extra)
    return build_config(data)


def _metrics(run_dir):
    with open(run_dir / "metrics.csv") as f:
        return [(r["step"], r["name"], r["value"]) for r in csv.DictReader(f) if not r["name"].startswith("perf/")]


@pytest.mark.parametrize("lagrange", ["gradient", "pid"])
def test_a_resumed_run_continues_the_multiplier_and_the_weights_exactly(lagrange, tmp_path):
    # rollouts of 64 steps per env, a multiple of ThreeLanes' 4: no episode straddles the checkpoint
    def config(run_dir):
        return _config(run_dir, 4096, checkpoint_every=2048, ppo_lag={
            "num_steps": 64, "hidden": [32], "lr": 3e-3, "cost_limit": 1.0, "lagrange": lagrange, "pid_ema": 0.5})

    straight, split = tmp_path / "straight", tmp_path / "split"
    train(config(straight), progress=False)
    train(config(split), progress=False, callback=lambda event: event.step < 2048)   # "killed" at step 2048
    assert checkpoint_step(resolve_checkpoint(split)) == 2048
    train(run_dir=split, resume=True, steps=4096, progress=False)
    a, b = (load_file(str(resolve_checkpoint(d) / "tensors.safetensors")) for d in (straight, split))
    a, b = ({k: v for k, v in t.items() if k.startswith("module/")} for t in (a, b))
    assert a.keys() == b.keys() and "module/lagrange/value" in a and "module/policy/cost_critic.0.net.0.weight" in a
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert a["module/lagrange/value"].dtype == torch.float64 and a["module/lagrange/value"].item() > 0
    # the same history, but for the stopped process's extra log at step 2048
    assert [r for r in _metrics(split) if r[0] != "2048"] == [r for r in _metrics(straight) if r[0] != "2048"]


def test_ppo_lag_refuses_an_env_without_a_cost(tmp_path):
    with pytest.raises(DrivelabError, match="ppo_lag needs an env that reports a cost"):
        train(build_config({"algo": "ppo_lag", "steps": 512, "run_dir": str(tmp_path),
                            "env": {"id": "CartPole-v1", "num_envs": 2}, "ppo_lag": {"num_steps": 128}}), progress=False)


@pytest.mark.parametrize("field, value", [("cost_limit", -1.0), ("cost_limit", float("nan")), ("lagrange", "pidd")])
def test_bad_constraint_fields_are_one_line_naming_the_field(field, value, tmp_path):
    with pytest.raises(DrivelabError, match=f"ppo_lag.{field}"):
        build_config({"algo": "ppo_lag", "run_dir": str(tmp_path), "env": {"id": THREE_LANES}, "ppo_lag": {field: value}})


def test_ppo_lag_keeps_to_the_middle_lane_where_ppo_takes_the_fast_one(tmp_path):
    # ThreeLanes with cost_limit 1: the constrained optimum is the middle lane (return 8, cost 1);
    # unconstrained, the fast lane (return 10, cost 4). One budget for both.
    results = {}
    for algo in ("ppo_lag", "ppo"):
        train(_config(tmp_path / algo, 20_000, algo=algo), progress=False)
        results[algo] = evaluate(load(tmp_path / algo), THREE_LANES, episodes=2)   # deterministic: both alike
    assert results["ppo_lag"]["cost"] <= 1.25 and results["ppo_lag"]["return_mean"] >= 7.0, results["ppo_lag"]
    assert results["ppo"]["cost"] >= 3.0 and results["ppo"]["return_mean"] >= 9.0, results["ppo"]
    last = {name: float(value) for _, name, value in _metrics(tmp_path / "ppo_lag")}
    assert 0.4 < last["charts/lagrange_multiplier"] < 5.0, last
    assert last["episode/cost"] <= 1.5, last           # the last training window keeps near the limit
