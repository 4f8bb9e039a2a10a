"""SAC-Lagrangian (drivelab.algos.sac_lag): the replay buffer's cost sums, the update pinned against a
reference computation, the stored costs of both collectors, a bit-exact resume with the PID
multiplier, and the constrained optimum of ``constrained_env:ThreeLanes-v0`` (see its docstring)."""

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from constrained_env import LANES, lane_of
from drivelab.algos import sac_lag
from drivelab.api import build_config, train
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, make_target
from drivelab.training.learning.replay_buffer import ReplayBatch, ReplayBuffer
from drivelab.training.outputs.checkpoint import list_checkpoints, resolve_checkpoint

VEC = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
ACT = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
THREE_LANES = "constrained_env:ThreeLanes-v0"


def _add(buffer, t, reward, cost, terminated=(False, False), truncated=(False, False)):
    """Add row t of 2 envs: obs (t, env, 0), reward/cost per env."""
    obs = np.array([[t, env, 0] for env in range(2)], np.float32)
    buffer.add(obs, np.zeros((2, 2)), np.array(reward, np.float32), obs + 1, np.array(terminated),
               np.array(truncated), costs=np.array(cost, np.float32))


# ---- replay buffer --------------------------------------------------------------------------

def test_n_step_cost_sums_match_a_hand_calculation_and_stop_where_the_rewards_stop():
    # 2 envs in lockstep, n = 3; rewards discounted by 0.5, costs by 0.25 (cost_gamma)
    buffer = ReplayBuffer(12, VEC, ACT, gamma=0.5, n_step=3, num_envs=2, costs=True, cost_gamma=0.25)
    _add(buffer, 0, [1, 10], [1, 4])
    _add(buffer, 1, [2, 20], [2, 8], terminated=(False, True))       # env 1's episode ends at t = 1
    _add(buffer, 2, [4, 40], [4, 16])
    _add(buffer, 3, [8, 80], [8, 32], truncated=(True, False))       # env 0's is cut at t = 3
    idx = np.array([0, 1, 2, 3, 4, 6])   # (t, env): (0,0) (0,1) (1,0) (1,1) (2,0) (3,0)
    sums, last, steps = buffer._n_step_sums(idx, [(buffer.rewards, 0.5), (buffer.costs, 0.25)])
    np.testing.assert_allclose(sums[0], [1 + 0.5 * 2 + 0.25 * 4, 10 + 0.5 * 20, 2 + 0.5 * 4 + 0.25 * 8, 20,
                                         4 + 0.5 * 8, 8])
    np.testing.assert_allclose(sums[1], [1 + 0.25 * 2 + 0.0625 * 4, 4 + 0.25 * 8, 2 + 0.25 * 4 + 0.0625 * 8, 8,
                                         4 + 0.25 * 8, 8])
    np.testing.assert_array_equal(steps, [3, 2, 3, 1, 2, 1])
    np.testing.assert_array_equal(last, [4, 3, 6, 3, 6, 6])
    # a sampled batch carries the cost sums and cost_gamma^m; the reward side is as without costs
    plain = ReplayBuffer(12, VEC, ACT, gamma=0.5, n_step=3, num_envs=2)
    for field in ("obs", "next_obs", "actions", "rewards", "terminated", "truncated"):
        getattr(plain, field)[:] = getattr(buffer, field)
    plain.pos, plain.size = buffer.pos, buffer.size
    batch, without = buffer.sample(32, np.random.default_rng(0)), plain.sample(32, np.random.default_rng(0))
    for a, b in zip(batch[:6], without[:6]):
        assert torch.equal(a, b)
    assert without.costs is None and without.cost_discount is None
    rows = np.random.default_rng(0).integers(0, buffer.size, size=32)
    sums, _, steps = buffer._n_step_sums(rows, [(buffer.rewards, 0.5), (buffer.costs, 0.25)])
    np.testing.assert_allclose(batch.costs.numpy(), sums[1])
    np.testing.assert_allclose(batch.cost_discount.numpy(), 0.25 ** steps)


def test_one_step_costs_and_the_checkpoint_keep_costs_only_when_asked():
    buffer = ReplayBuffer(8, VEC, ACT, gamma=0.9, costs=True, cost_gamma=0.5)
    _add(buffer, 0, [1, 2], [0.25, 1.0])
    batch = buffer.sample(16, np.random.default_rng(1))
    np.testing.assert_array_equal(batch.costs.numpy(), np.where(batch.rewards.numpy() == 1, 0.25, 1.0))
    np.testing.assert_allclose(batch.cost_discount.numpy(), 0.5)
    tensors, meta = buffer.state()
    again = ReplayBuffer(8, VEC, ACT, costs=True)
    again.load_state(tensors, meta)
    np.testing.assert_array_equal(again.costs, buffer.costs)
    plain_tensors, _ = ReplayBuffer(8, VEC, ACT).state()
    assert "replay/costs" in tensors and "replay/costs" not in plain_tensors   # old checkpoints still load
    assert ReplayBuffer.bytes_needed(8, VEC, 2, costs=True) == ReplayBuffer.bytes_needed(8, VEC, 2) + 8 * 4


# ---- the update -----------------------------------------------------------------------------

def _batch():
    rng = np.random.default_rng(3)
    t = lambda x: torch.as_tensor(x, dtype=torch.float32)  # noqa: E731
    return ReplayBatch(obs=t(rng.uniform(-1, 1, (6, 3))), actions=t(rng.uniform(-1, 1, (6, 2))),
                       rewards=t([1.0, 0.0, -1.0, 0.5, 2.0, 0.0]), next_obs=t(rng.uniform(-1, 1, (6, 3))),
                       terminated=t([0, 0, 1, 0, 0, 1]), discount=t([0.9, 0.9, 0.9, 0.9, 0.81, 0.9]),
                       costs=t([0.0, 1.0, 0.25, 0.0, 1.5, 1.0]), cost_discount=t([0.8, 0.8, 0.8, 0.8, 0.64, 0.8]))


def _after_sgd(module, loss_fn, lr):
    ref = copy.deepcopy(module)
    loss = loss_fn(ref)
    grads = torch.autograd.grad(loss, list(ref.parameters()))
    return {name: p.detach() - lr * g for (name, p), g in zip(ref.named_parameters(), grads)}, loss.detach()


def _assert_params(module, expected):
    for name, p in module.named_parameters():
        torch.testing.assert_close(p.detach(), expected[name], atol=1e-6, rtol=1e-5, msg=name)


def test_sac_lag_update_trains_the_cost_critic_and_the_actor_on_the_lagrangian():
    torch.manual_seed(0)
    agent = OffPolicyAgent(VEC, ACT, [8], "relu", stochastic=True, critics=2, cost_critics=1)
    target = make_target(agent)
    with torch.no_grad():  # a target that trails the agent
        for p in agent.parameters():
            p.add_(0.05 * torch.randn_like(p))
    batch, hp, lam, alpha = _batch(), sac_lag.Params(tau=0.1, init_alpha=0.2), 1.5, 0.2
    log_alpha = torch.nn.Parameter(torch.tensor(alpha).log())
    torch.manual_seed(11)
    with torch.no_grad():
        next_action, next_log_prob = agent.actor(batch.next_obs)       # the same a' for both targets
        next_q = target.critic(batch.next_obs, next_action).min(dim=0).values
        y = batch.rewards + batch.discount * (1 - batch.terminated) * (next_q - alpha * next_log_prob)
        # the cost target has no entropy term
        y_c = batch.costs + batch.cost_discount * (1 - batch.terminated) * target.cost_critic(batch.next_obs, next_action)[0]
    critic_expected, ref_q = _after_sgd(agent.critic, lambda c: (c(batch.obs, batch.actions) - y).pow(2).mean(dim=1).sum(), 0.05)
    cost_expected, ref_qc = _after_sgd(agent.cost_critic, lambda c: (c(batch.obs, batch.actions)[0] - y_c).pow(2).mean(), 0.05)
    before, target_before = copy.deepcopy(agent), {n: p.detach().clone() for n, p in target.named_parameters()}
    opt = sac_lag.Optimizers(critic=torch.optim.SGD([*agent.critic.parameters(), *agent.cost_critic.parameters()], lr=0.05),
                             actor=torch.optim.SGD(agent.actor.parameters(), lr=0.02),
                             alpha=torch.optim.SGD([log_alpha], lr=0.5))
    torch.manual_seed(11)
    out = sac_lag.update(agent, target, log_alpha, opt, batch, hp, -2.0, lam)
    assert out["loss/critic"].item() == pytest.approx(ref_q.item(), rel=1e-5)
    assert out["loss/cost_critic"].item() == pytest.approx(ref_qc.item(), rel=1e-5)
    _assert_params(agent.critic, critic_expected)
    _assert_params(agent.cost_critic, cost_expected)
    # the actor: E[alpha log pi - min Q + lam Q_c] through the *updated* critics, with the same noise
    # (the generator's state after the target's sample, which the reference replays)
    torch.manual_seed(11)
    before.actor(batch.next_obs)
    action, log_prob = before.actor(batch.obs)
    q_pi = agent.critic(batch.obs, action).min(dim=0).values
    loss_pi = (alpha * log_prob - q_pi + lam * agent.cost_critic(batch.obs, action)[0]).mean()
    assert out["loss/actor"].item() == pytest.approx(loss_pi.item(), rel=1e-5)
    grads = torch.autograd.grad(loss_pi, list(before.actor.parameters()))
    for (name, p), g in zip(before.actor.named_parameters(), grads):
        torch.testing.assert_close(dict(agent.actor.named_parameters())[name].detach(), p.detach() - 0.02 * g)
    assert out["charts/qc"].item() == pytest.approx(before.cost_critic(batch.obs, batch.actions).mean().item(), rel=1e-5)
    for name, p in target.named_parameters():  # Polyak, the cost critic's target too
        torch.testing.assert_close(p, 0.9 * target_before[name] + 0.1 * dict(agent.named_parameters())[name].detach())
    assert any(name.startswith("cost_critic.") for name in target_before)


def test_a_larger_multiplier_pushes_the_actor_toward_lower_cost():
    """d loss / d Q_c = lam / B: the actor's gradient on the cost term scales with lambda."""
    torch.manual_seed(0)
    agent = OffPolicyAgent(VEC, ACT, [8], "relu", stochastic=True, critics=2, cost_critics=1)
    log_prob, q_pi = torch.zeros(4), torch.zeros(4)
    qc_pi = torch.ones(4, requires_grad=True)
    for lam in (0.0, 2.0):
        loss = sac_lag.lagrangian_actor_loss(log_prob, q_pi, qc_pi, torch.tensor(0.1), lam)
        (grad,) = torch.autograd.grad(loss, qc_pi)
        torch.testing.assert_close(grad, torch.full((4,), lam / 4))
    assert sorted(sac_lag.build_optimizers(agent, torch.nn.Parameter(torch.zeros(())), sac_lag.Params())._fields) == \
        ["actor", "alpha", "critic"]


# ---- runs on ThreeLanes ---------------------------------------------------------------------

def _config(run_dir, steps, algo="sac_lag", seed=0, top=None, **params):
    section = {"learning_starts": 500, "hidden": [32, 32], "batch_size": 64, "gamma": 0.9, **params}
    if algo == "sac_lag":
        section = {"cost_limit": 1.0, "lagrange_every": 200, "lagrange_lr": 0.15, **section}
    return build_config({"algo": algo, "seed": seed, "steps": steps, "run_dir": str(run_dir), "log_every": 500,
                         "env": {"id": THREE_LANES, "num_envs": 1}, "eval": {"every": 0}, algo: section, **(top or {})})


def _replay(run_dir):
    tensors = load_file(str(list_checkpoints(run_dir)[-1] / "tensors.safetensors"))
    return {name.removeprefix("replay/"): value.numpy() for name, value in tensors.items() if name.startswith("replay/")}


def _check_costs(replay):
    """Every stored cost is the lane cost of the stored action (ThreeLanes' actions are its Box's)."""
    lanes = [lane_of(a) for a in replay["actions"][:, 0]]
    np.testing.assert_array_equal(replay["costs"], [LANES[lane][1] for lane in lanes])
    assert replay["costs"].max() == 1.0 and replay["costs"].min() == 0.0


def test_the_collectors_store_each_steps_cost(tmp_path):
    train(_config(tmp_path / "sync", 600, learning_starts=400), progress=False)
    _check_costs(_replay(tmp_path / "sync"))
    cfg = build_config({"algo": "sac_lag", "seed": 0, "steps": 600, "run_dir": str(tmp_path / "async"),
                        "eval": {"every": 0}, "env": {"id": THREE_LANES, "num_envs": 2, "backend": "async"},
                        "sac_lag": {"act_in_workers": True, "chunk_steps": 8, "learning_starts": 400, "hidden": [16],
                                    "batch_size": 16, "lagrange_every": 200}})
    train(cfg, progress=False)
    replay = _replay(tmp_path / "async")
    assert len(replay["costs"]) == 600
    _check_costs(replay)


def test_a_run_resumed_between_episodes_with_the_pid_multiplier_equals_the_uninterrupted_run(tmp_path):
    # ThreeLanes episodes last 4 steps: a checkpoint every 400 steps falls between episodes. The
    # multiplier moves every 200 steps, before and after the interruption.
    def config(run_dir, steps):
        return _config(run_dir, steps, top={"checkpoint_every": 400}, learning_starts=300, lagrange="pid", pid_kp=0.5,
                       pid_ki=0.1, pid_d_delay=2)

    train(config(tmp_path / "straight", 1200), progress=False)
    train(config(tmp_path / "split", 800), progress=False)       # "killed" at step 800
    train(config(tmp_path / "split", 1200), resume=True, progress=False)
    load = lambda run: load_file(str(resolve_checkpoint(tmp_path / run) / "tensors.safetensors"))  # noqa: E731
    a, b = load("straight"), load("split")
    assert a.keys() == b.keys() and "replay/costs" in a and "module/lagrange/value" in a
    for key in a:
        if key.startswith(("module/", "replay/")):
            assert torch.equal(a[key], b[key]), key
    assert a["module/lagrange/updates"].item() == 5 and a["module/lagrange/value"].item() > 0


@pytest.mark.slow
def test_sac_lag_drives_the_middle_lane_where_sac_takes_the_fast_one(tmp_path):
    import drivelab

    results = {}
    for algo in ("sac_lag", "sac"):
        run = train(_config(tmp_path / algo, 2500, algo=algo, seed=1), progress=False)
        policy = drivelab.load(run.run_dir)
        results[algo] = drivelab.evaluate(policy, THREE_LANES, episodes=2), run.metrics
    (lag, lag_metrics), (plain, _) = results["sac_lag"], results["sac"]
    # the constrained optimum: the middle lane every stretch (return 8, cost 1)
    assert lag["cost"] <= 1.25 and lag["return_mean"] >= 7.0, lag
    assert 0.4 < lag_metrics["charts/lagrange_multiplier"] < 5, lag_metrics
    # unconstrained: the fast lane (return 10, cost 4)
    assert plain["cost"] >= 3 and plain["return_mean"] >= 9, plain


@pytest.mark.parametrize("flag, value, named", [
    ("--sac_lag.cost_limit", "-1", "sac_lag.cost_limit"), ("--sac_lag.cost_limit", "nan", "cost_limit"),
    ("--sac_lag.cost_limit", "inf", "cost_limit"), ("--sac_lag.cost_limit", "abc", "cost_limit"),
    ("--sac_lag.lagrange", "pidd", "sac_lag.lagrange"), ("--sac_lag.lagrange_every", "0", "sac_lag.lagrange_every")])
def test_bad_constraint_settings_are_one_line_and_exit_2(tmp_path, capsys, flag, value, named):
    from drivelab.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", "sac_lag", "--env", THREE_LANES, "--steps", "100", "--no-progress",
              "--run-dir", str(tmp_path / "run"), flag, value])
    lines = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("drivelab: warning")]
    assert exit_info.value.code == 2 and len(lines) == 1 and named in lines[0], lines
    assert not (tmp_path / "run").exists()


def test_an_env_without_a_cost_is_one_line(tmp_path):
    from drivelab.errors import DrivelabError

    cfg = build_config({"algo": "sac_lag", "steps": 400, "run_dir": str(tmp_path / "run"), "eval": {"every": 0},
                        "env": {"id": "Pendulum-v1", "num_envs": 1}, "sac_lag": {"learning_starts": 100, "hidden": [8],
                                                                   "batch_size": 8, "lagrange_every": 200}})
    with pytest.raises(DrivelabError, match="reports a cost per step"):
        train(cfg, progress=False)
