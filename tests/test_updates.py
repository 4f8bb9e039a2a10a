"""One update of each algorithm on a fixed tiny batch, pinned against a reference computation.

Every ``update`` is a module-level function, so it can be called here without envs or a run.
Optimisers are plain SGD, so the expected parameter change is exactly -lr * (gradient of the
reference loss), computed independently with torch.distributions and autograd on a copy.
"""

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch.distributions import Categorical

from drivelab.algos import a2c, ddpg, grpo, ppo, reinforce, sac, td3
from drivelab.errors import DrivelabError
from drivelab.training.learning.replay_buffer import ReplayBatch
from drivelab.training.learning.optim import fused_adam
from drivelab.training.learning.policy_nets import ActorCritic, Policy, limit_log_std
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, make_target
from drivelab.training.learning.optim import Optimizers
from drivelab.training.learning.precision import update_precision
from drivelab.training.learning.rollout_buffers import RolloutBatch

OBS = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
DISCRETE = gym.spaces.Discrete(2)
BOX = gym.spaces.Box(-2.0, 2.0, (2,), np.float32)
B = 6
LR = 0.1


def _obs(seed=0):
    return torch.as_tensor(np.random.default_rng(seed).uniform(-1, 1, (B, 3)), dtype=torch.float32)


def _params(module):
    return {name: p.detach().clone() for name, p in module.named_parameters()}


def _expected_after_sgd(module, loss_fn, lr=LR):
    """Parameters of ``module`` after one SGD step on ``loss_fn(copy)``, computed on a copy."""
    ref = copy.deepcopy(module)
    loss = loss_fn(ref)
    grads = torch.autograd.grad(loss, [p for p in ref.parameters()], allow_unused=True)
    return {name: p.detach() - lr * (g if g is not None else 0.0)
            for (name, p), g in zip(ref.named_parameters(), grads)}, loss.detach()


def _assert_params(module, expected, atol=1e-6):
    for name, p in module.named_parameters():
        torch.testing.assert_close(p.detach(), expected[name], atol=atol, rtol=1e-5, msg=name)


def test_reinforce_update_is_the_normalised_reward_to_go_policy_gradient():
    torch.manual_seed(0)
    policy = Policy(OBS, DISCRETE, [4])
    batch = reinforce.EpisodeBatch(obs=_obs(), actions=torch.tensor([0, 1, 1, 0, 1, 0]),
                                   returns=torch.tensor([3.0, 2.0, 1.0, 0.5, -1.0, 4.0]))
    hp = reinforce.Params(advantage="normalize", ent_coef=0.1)
    w = (batch.returns - batch.returns.mean()) / (batch.returns.std(unbiased=False) + 1e-8)

    def reference(p):
        dist = Categorical(logits=p.head(p.encoder(batch.obs)))
        return -(dist.log_prob(batch.actions) * w).mean() - 0.1 * dist.entropy().mean()

    expected, ref_loss = _expected_after_sgd(policy, reference)
    out = reinforce.update(policy, torch.optim.SGD(policy.parameters(), lr=LR), batch, hp)
    assert (out["loss/policy"] - 0.1 * out["loss/entropy"]).item() == pytest.approx(ref_loss.item(), rel=1e-5)
    _assert_params(policy, expected)


def _rollout_batch(agent, log_prob_offsets):
    obs, actions = _obs(1), torch.tensor([0, 1, 0, 1, 1, 0])
    with torch.no_grad():
        log_probs = agent.distribution(obs).log_prob(actions) + torch.tensor(log_prob_offsets)
        values = agent.value(obs) + 0.3
    advantages = torch.tensor([1.0, -0.5, 2.0, 0.0, -1.5, 0.7])
    return RolloutBatch(obs, actions, log_probs, values, advantages, returns=advantages + values)


def test_a2c_update_is_one_actor_critic_gradient_step():
    torch.manual_seed(0)
    agent = ActorCritic(OBS, DISCRETE, [4])
    batch = _rollout_batch(agent, [0.0] * B)
    hp = a2c.Params(ent_coef=0.01, vf_coef=0.5, max_grad_norm=1e9)

    def reference(a):
        dist = a.distribution(batch.obs)
        pg = -(dist.log_prob(batch.actions) * batch.advantages).mean()
        v = 0.5 * (a.value(batch.obs) - batch.returns).pow(2).mean()
        return pg + 0.5 * v - 0.01 * dist.entropy().mean()

    expected, ref_loss = _expected_after_sgd(agent, reference)
    out = a2c.update(agent, torch.optim.SGD(agent.parameters(), lr=LR), batch, hp)
    total = out["loss/policy"] + 0.5 * out["loss/value"] - 0.01 * out["loss/entropy"]
    assert total.item() == pytest.approx(ref_loss.item(), rel=1e-5)
    # the rollout's values were stored as V(s) + 0.3: no clipping in A2C, L_V = 0.5 * mean((V(s) - R)^2)
    assert out["loss/value"].item() == pytest.approx(0.5 * (batch.values - 0.3 - batch.returns).pow(2).mean().item(), rel=1e-5)
    _assert_params(agent, expected)


def test_ppo_update_clips_the_ratio_and_the_value_by_hand():
    torch.manual_seed(0)
    agent = ActorCritic(OBS, DISCRETE, [4])
    # log pi_old = log pi_theta + offset, so rho = exp(-offset): 1.65, 0.61, 1, 1.11, 0.82, 1.35
    offsets = [-0.5, 0.5, 0.0, -0.1, 0.2, -0.3]
    batch = _rollout_batch(agent, offsets)
    hp = ppo.Params(update_epochs=1, num_minibatches=1, clip_coef=0.2, ent_coef=0.01, vf_coef=0.5, max_grad_norm=1e9)

    def reference(a):
        dist = a.distribution(batch.obs)
        ratio = (dist.log_prob(batch.actions) - batch.log_probs).exp()
        adv = (batch.advantages - batch.advantages.mean()) / (batch.advantages.std() + 1e-8)
        pg = -torch.min(ratio * adv, ratio.clamp(0.8, 1.2) * adv).mean()
        v = a.value(batch.obs)
        v_clipped = batch.values + (v - batch.values).clamp(-0.2, 0.2)
        vl = 0.5 * torch.max((v - batch.returns) ** 2, (v_clipped - batch.returns) ** 2).mean()
        return pg + 0.5 * vl - 0.01 * dist.entropy().mean()

    expected, ref_loss = _expected_after_sgd(agent, reference)
    out = ppo.update(agent, torch.optim.SGD(agent.parameters(), lr=LR), batch, hp)
    total = out["loss/policy"] + 0.5 * out["loss/value"] - 0.01 * out["loss/entropy"]
    assert total.item() == pytest.approx(ref_loss.item(), rel=1e-5)
    # |rho - 1| > 0.2 for offsets -0.5, 0.5, -0.3 (rho 1.65, 0.61, 1.35): half the batch is clipped
    assert out["loss/clip_fraction"].item() == pytest.approx(0.5)
    rho = np.exp(-np.array(offsets))
    assert out["loss/approx_kl"].item() == pytest.approx(np.mean((rho - 1) - np.log(rho)), rel=1e-5)
    _assert_params(agent, expected)


def test_ppo_target_kl_stops_the_epochs_and_logs_how_many_ran():
    torch.manual_seed(0)
    agent = ActorCritic(OBS, DISCRETE, [4])
    # rho = exp(-offset) far from 1: the approximate KL is ~0.47 before any step
    batch = _rollout_batch(agent, [-1.0, 1.0, -0.8, 0.8, -1.0, 1.0])
    params = dict(update_epochs=5, num_minibatches=1, max_grad_norm=1e9)
    stopped = ppo.update(agent, torch.optim.SGD(agent.parameters(), lr=LR), batch, ppo.Params(target_kl=0.01, **params))
    assert stopped["loss/epochs"].item() == 1  # checked once per epoch, after its last minibatch
    full = ppo.update(agent, torch.optim.SGD(agent.parameters(), lr=LR), batch, ppo.Params(**params))
    assert full["loss/epochs"].item() == 5


def test_grpo_update_is_the_clipped_ratio_plus_the_kl_penalty():
    torch.manual_seed(0)
    agent = ActorCritic(OBS, DISCRETE, [4], critic=False)
    obs, actions = _obs(2), torch.tensor([1, 1, 0, 0, 1, 0])
    with torch.no_grad():
        old = agent.distribution(obs).log_prob(actions) + torch.tensor([0.4, -0.4, 0.0, 0.1, -0.25, 0.05])
    batch = grpo.GroupBatch(obs, actions, old, advantages=torch.tensor([1.0, 1.0, -1.0, -1.0, 0.5, -0.5]))
    hp = grpo.Params(update_epochs=1, num_minibatches=1, clip_coef=0.2, kl_coef=0.1, max_grad_norm=1e9)

    def reference(a):
        log_prob = a.distribution(obs).log_prob(actions)
        ratio = (log_prob - old).exp()
        pg = -torch.min(ratio * batch.advantages, ratio.clamp(0.8, 1.2) * batch.advantages).mean()
        kl = ((ratio - 1) - (log_prob - old)).mean()   # k3 estimate of KL(pi_old || pi_theta)
        return pg + 0.1 * kl

    expected, ref_loss = _expected_after_sgd(agent, reference)
    out = grpo.update(agent, torch.optim.SGD(agent.parameters(), lr=LR), batch, hp)
    assert out["loss/policy"].item() == pytest.approx(ref_loss.item(), rel=1e-5)
    _assert_params(agent, expected)


def _replay_batch():
    rng = np.random.default_rng(3)
    t = lambda x: torch.as_tensor(x, dtype=torch.float32)  # noqa: E731
    return ReplayBatch(obs=t(rng.uniform(-1, 1, (B, 3))), actions=t(rng.uniform(-1, 1, (B, 2))),
                       rewards=t([1.0, 0.0, -1.0, 0.5, 2.0, 0.0]), next_obs=t(rng.uniform(-1, 1, (B, 3))),
                       terminated=t([0, 0, 1, 0, 0, 1]), discount=t([0.9] * B))  # gamma 0.9, as the tests' Params


def _agent_and_target(stochastic, critics):
    torch.manual_seed(0)
    agent = OffPolicyAgent(OBS, BOX, [8], "relu", stochastic=stochastic, critics=critics)
    target = make_target(agent)
    with torch.no_grad():  # a target that trails the agent: the test tells them apart
        for p in agent.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return agent, target


def _sgd(agent, lrs=(0.05, 0.02)):
    return Optimizers(critic=torch.optim.SGD(agent.critic.parameters(), lr=lrs[0]),
                      actor=torch.optim.SGD(agent.actor.parameters(), lr=lrs[1]))


def _polyak(before, agent, tau):
    return {name: (1 - tau) * p + tau * dict(agent.named_parameters())[name].detach() for name, p in before.items()}


def test_ddpg_update_target_critic_actor_and_polyak():
    agent, target = _agent_and_target(stochastic=False, critics=1)
    batch, hp = _replay_batch(), ddpg.Params(gamma=0.9, tau=0.1)
    with torch.no_grad():  # y = r + gamma * (1 - terminated) * Q'(s', mu'(s'))
        y = batch.rewards + 0.9 * (1 - batch.terminated) * target.critic(batch.next_obs, target.actor(batch.next_obs))[0]
    critic_expected, ref_q = _expected_after_sgd(
        agent.critic, lambda c: (c(batch.obs, batch.actions)[0] - y).pow(2).mean(), lr=0.05)
    target_before, actor_before = _params(target), copy.deepcopy(agent.actor)
    out = ddpg.update(agent, target, _sgd(agent), batch, hp)
    assert out["loss/critic"].item() == pytest.approx(ref_q.item(), rel=1e-5)
    _assert_params(agent.critic, critic_expected)
    # the actor ascends the *updated* critic: loss -mean Q(s, mu(s))
    loss_pi = -agent.critic(batch.obs, actor_before(batch.obs)).mean()
    assert out["loss/actor"].item() == pytest.approx(loss_pi.item(), rel=1e-5)
    grads = torch.autograd.grad(loss_pi, list(actor_before.parameters()))
    for (name, p), g in zip(actor_before.named_parameters(), grads):
        torch.testing.assert_close(dict(agent.actor.named_parameters())[name].detach(), p.detach() - 0.02 * g)
    _assert_params(target, _polyak(target_before, agent, 0.1))


def test_td3_update_smooths_the_target_action_and_delays_the_actor():
    agent, target = _agent_and_target(stochastic=False, critics=2)
    batch, hp = _replay_batch(), td3.Params(gamma=0.9, tau=0.1, policy_noise=0.3, noise_clip=0.4)
    torch.manual_seed(7)
    with torch.no_grad():
        noise = (torch.randn(B, 2) * 0.3).clamp(-0.4, 0.4)
        next_action = (target.actor(batch.next_obs) + noise).clamp(-1, 1)
        y = batch.rewards + 0.9 * (1 - batch.terminated) * target.critic(batch.next_obs, next_action).min(dim=0).values
    assert noise.abs().max() <= 0.4 + 1e-7
    critic_expected, ref_q = _expected_after_sgd(
        agent.critic, lambda c: (c(batch.obs, batch.actions) - y).pow(2).mean(dim=1).sum(), lr=0.05)
    actor_before, target_before = _params(agent.actor), _params(target)
    opt = _sgd(agent)
    torch.manual_seed(7)
    out = td3.update(agent, target, opt, batch, hp, update_actor=False)       # a delayed step: critic only
    assert out["loss/critic"].item() == pytest.approx(ref_q.item(), rel=1e-5) and "loss/actor" not in out
    _assert_params(agent.critic, critic_expected)
    _assert_params(agent.actor, actor_before)
    _assert_params(target, target_before)
    out = td3.update(agent, target, opt, batch, hp, update_actor=True)        # the policy_delay-th step
    assert "loss/actor" in out
    assert any(not torch.equal(p.detach(), actor_before[n]) for n, p in agent.actor.named_parameters())
    _assert_params(target, _polyak(target_before, agent, 0.1))


def test_td3_crossq_update_one_joint_batch_normalised_pass_and_no_targets():
    # CrossQ: y = r + gamma * (1 - terminated) * min_e Q_e(s', a') from the same train-mode pass as
    # Q_e(s, a), over [(s, a); (s', a')]; the actor's step reads the running statistics.
    torch.manual_seed(0)
    agent = OffPolicyAgent(OBS, BOX, [8], "relu", stochastic=False, critics=2, critic_batch_norm=True)
    batch, hp = _replay_batch(), td3.Params(gamma=0.9, policy_noise=0.3, noise_clip=0.4, crossq=True)
    torch.manual_seed(7)
    with torch.no_grad():
        noise = (torch.randn(B, 2) * 0.3).clamp(-0.4, 0.4)
        next_action = (agent.actor(batch.next_obs) + noise).clamp(-1, 1)
    joint_obs, joint_actions = torch.cat([batch.obs, batch.next_obs]), torch.cat([batch.actions, next_action])

    def reference_loss(critic):
        q_both = critic(joint_obs, joint_actions)                                   # (2, 2B), train mode
        y = batch.rewards + 0.9 * (1 - batch.terminated) * q_both[:, B:].detach().min(dim=0).values
        return (q_both[:, :B] - y).pow(2).mean(dim=1).sum()

    critic_expected, ref_q = _expected_after_sgd(agent.critic, reference_loss, lr=0.05)
    actor_before = copy.deepcopy(agent.actor)
    torch.manual_seed(7)
    out = td3.update(agent, None, _sgd(agent), batch, hp, update_actor=True)
    assert out["loss/critic"].item() == pytest.approx(ref_q.item(), rel=1e-5)
    _assert_params(agent.critic, critic_expected)
    # the input norm moved once, toward the joint batch's mean (momentum 0.01): not toward (s, a)
    # alone, and not again in the actor's step
    first_norm = agent.critic.net[0]
    joint_mean = torch.cat([joint_obs, joint_actions], dim=1).mean(dim=0)
    torch.testing.assert_close(first_norm.running_mean[:, 0], 0.01 * joint_mean.expand(2, -1))
    # the actor ascends Q_1 of the updated critic, normalised with the running statistics
    agent.critic.eval()
    loss_pi = -agent.critic(batch.obs, actor_before(batch.obs))[0].mean()
    assert out["loss/actor"].item() == pytest.approx(loss_pi.item(), rel=1e-5)
    grads = torch.autograd.grad(loss_pi, list(actor_before.parameters()))
    for (name, p), g in zip(actor_before.named_parameters(), grads):
        torch.testing.assert_close(dict(agent.actor.named_parameters())[name].detach(), p.detach() - 0.02 * g)


def test_td3_pre_tanh_penalty_by_hand_and_on_a_saturated_actor():
    from drivelab.training.learning.losses import deterministic_actor_loss

    # The actor step with the penalty, by hand: -Q_1(s, tanh(u)) + lambda * mean(u^2), after the critic's step.
    agent, target = _agent_and_target(stochastic=False, critics=2)
    batch, hp = _replay_batch(), td3.Params(gamma=0.9, tau=0.1, pre_tanh_l2=0.5)
    opt = _sgd(agent, lrs=(0.0, 0.02))   # a frozen critic: the actor's step alone
    u_of = lambda actor: actor.net[:-1](batch.obs)          # noqa: E731
    expected, ref = _expected_after_sgd(
        agent.actor, lambda a: -agent.critic(batch.obs, torch.tanh(u_of(a)))[0].mean() + 0.5 * u_of(a).pow(2).mean(),
        lr=0.02)
    out = td3.update(agent, target, opt, batch, hp, update_actor=True)
    assert out["loss/actor"].item() == pytest.approx(ref.item(), rel=1e-5)
    _assert_params(agent.actor, expected)
    # Without the penalty it is exactly -E[Q]; at a saturated output only the penalty still has a gradient.
    u = torch.full((4, 2), -8.0, requires_grad=True)
    q = torch.tanh(u).sum(-1)                              # a critic that prefers larger actions
    assert torch.equal(deterministic_actor_loss(q, u), -q.mean())
    (grad_plain,) = torch.autograd.grad(deterministic_actor_loss(q, u), u, retain_graph=True)
    (grad_penalised,) = torch.autograd.grad(deterministic_actor_loss(q, u, 0.01), u)
    assert grad_plain.abs().max() < 1e-6                   # tanh'(-8) ~ 5e-7: stuck at the bound
    assert torch.all(grad_penalised < -1e-3)               # descent raises u, back towards 0


def test_sac_update_soft_target_actor_and_temperature():
    agent, target = _agent_and_target(stochastic=True, critics=2)
    batch, hp = _replay_batch(), sac.Params(gamma=0.9, tau=0.1, init_alpha=0.2)
    log_alpha = torch.nn.Parameter(torch.tensor(0.2).log())
    alpha, target_entropy = 0.2, -2.0
    torch.manual_seed(11)
    with torch.no_grad():  # y = r + gamma (1 - d) (min_e Q'_e(s', a') - alpha log pi(a'|s')), a' ~ pi(.|s')
        next_action, next_log_prob = agent.actor(batch.next_obs)
        next_q = target.critic(batch.next_obs, next_action).min(dim=0).values
        y = batch.rewards + 0.9 * (1 - batch.terminated) * (next_q - alpha * next_log_prob)
    critic_expected, ref_q = _expected_after_sgd(
        agent.critic, lambda c: (c(batch.obs, batch.actions) - y).pow(2).mean(dim=1).sum(), lr=0.05)
    opt = sac.Optimizers(*_sgd(agent), alpha=torch.optim.SGD([log_alpha], lr=0.5))
    target_before = _params(target)
    torch.manual_seed(11)
    out = sac.update(agent, target, log_alpha, opt, batch, hp, target_entropy)
    assert out["loss/critic"].item() == pytest.approx(ref_q.item(), rel=1e-5)
    _assert_params(agent.critic, critic_expected)
    # temperature: d/d log(alpha) of -mean(log alpha * (log pi + H)) is -(mean log pi + H), so one
    # SGD step moves log(alpha) by lr * (mean log pi + H) = lr * (H - entropy): down while the
    # policy's entropy is above its target
    entropy = out["charts/entropy"].item()
    assert log_alpha.item() == pytest.approx(np.log(0.2) + 0.5 * (target_entropy - entropy), rel=1e-5)
    assert out["loss/alpha"].item() == pytest.approx(-np.log(0.2) * (target_entropy - entropy), rel=1e-5)
    _assert_params(target, _polyak(target_before, agent, 0.1))


def test_the_off_policy_optimisers_are_a_fused_adam_that_steps_as_the_default_one():
    agent, _ = _agent_and_target(stochastic=True, critics=2)
    log_alpha = torch.nn.Parameter(torch.tensor(0.2).log())
    opt = sac.build_optimizers(agent, log_alpha, sac.Params())
    assert all(o.param_groups[0]["fused"] for o in opt)
    reference = copy.deepcopy(agent.critic)
    default = torch.optim.Adam(reference.parameters(), lr=opt.critic.param_groups[0]["lr"])
    batch = _replay_batch()
    for _ in range(20):   # the same losses: the two Adams differ only in rounding
        for critic, optimizer in ((agent.critic, opt.critic), (reference, default)):
            optimizer.zero_grad()
            critic(batch.obs, batch.actions).pow(2).mean().backward()
            optimizer.step()
    _assert_params(agent.critic, _params(reference))
    # off CPU and CUDA (here the meta device) torch has no fused Adam: the default one
    meta = torch.nn.Parameter(torch.zeros(3, device="meta"))
    assert fused_adam([meta], lr=1e-3).param_groups[0]["fused"] is None


@pytest.mark.parametrize("algo", ["ddpg", "td3", "sac"])
def test_the_actor_step_computes_no_weight_gradients_for_the_critics(algo):
    # The actor's step goes through the critics for dQ/da only (nets.frozen): each critic weight
    # gets its gradient once per update, from the critic's own step, and stays trainable after.
    agent, target = _agent_and_target(stochastic=algo == "sac", critics=1 if algo == "ddpg" else 2)
    computed = []
    for p in agent.critic.parameters():
        p.register_hook(lambda grad: computed.append(grad))
    batch, opt = _replay_batch(), _sgd(agent)
    if algo == "ddpg":
        out = ddpg.update(agent, target, opt, batch, ddpg.Params())
    elif algo == "td3":
        out = td3.update(agent, target, opt, batch, td3.Params(), update_actor=True)
    else:
        log_alpha = torch.nn.Parameter(torch.tensor(0.0))
        out = sac.update(agent, target, log_alpha, sac.Optimizers(*opt, alpha=torch.optim.SGD([log_alpha], lr=0.1)),
                         batch, sac.Params(), target_entropy=-2.0)
    assert "loss/actor" in out
    assert len(computed) == len(list(agent.critic.parameters()))
    assert all(p.requires_grad for p in agent.critic.parameters())
    # TD3's actor ascends Q_1 alone: the first member of the twin critics, computed by itself.
    q = agent.critic(batch.obs, batch.actions)
    torch.testing.assert_close(agent.critic(batch.obs, batch.actions, members=1), q[:1])


def test_log_std_bound_falls_linearly_and_projects_the_parameter():
    """The bound goes from log_std_init at step 0 to log_std_final at the last step; a log std
    below the bound is left alone, one above it is set to it; no schedule: untouched."""
    hp = ppo.Params(log_std_init=-0.5, log_std_final=-2.0)
    policy = Policy(OBS, BOX, (8,), log_std_init=-0.5)
    with torch.no_grad():
        policy.log_std.copy_(torch.tensor([-0.4, -1.5]))
    log = limit_log_std(policy, hp, step=500, total=1000)       # bound -1.25
    torch.testing.assert_close(policy.log_std.detach(), torch.tensor([-1.25, -1.5]))
    assert log["charts/policy_std"] == pytest.approx((np.exp(-1.25) + np.exp(-1.5)) / 2)
    limit_log_std(policy, hp, step=5000, total=1000)            # past the end: the final value
    torch.testing.assert_close(policy.log_std.detach(), torch.tensor([-2.0, -2.0]))
    free = Policy(OBS, BOX, (8,), log_std_init=0.3)
    limit_log_std(free, ppo.Params(), step=1000, total=1000)
    torch.testing.assert_close(free.log_std.detach(), torch.full((2,), 0.3))
    assert limit_log_std(Policy(OBS, DISCRETE, (8,)), hp, 0, 1000) == {}


@pytest.mark.parametrize("algo", ["td3", "sac"])
def test_bf16_updates_keep_the_output_layers_in_float32_and_follow_the_float32_update(algo):
    # bf16_updates runs the update under bfloat16 autocast (offpolicy.update_precision); the
    # output layers stay float32 (nets.in_float32), so Q near 300 keeps its sub-unit differences.
    agent, target = _agent_and_target(stochastic=algo == "sac", critics=2)
    with torch.no_grad():
        agent.critic.net[-1].bias.add_(300.0)
        target.critic.net[-1].bias.add_(300.0)
    batch = _replay_batch()
    with torch.no_grad():
        q32 = agent.critic(batch.obs, batch.actions)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            q16 = agent.critic(batch.obs, batch.actions)
            hidden = agent.critic.net[:-1](torch.cat([batch.obs, batch.actions], -1).unsqueeze(0))
    assert hidden.dtype == torch.bfloat16 and q16.dtype == torch.float32
    assert (q16 - q32).abs().max() < 0.05        # bfloat16 itself spaces values near 300 by 2
    assert (q32.bfloat16().float() - q32).abs().max() > 0.1

    results = []
    for bf16 in (False, True):
        a, t = copy.deepcopy(agent), copy.deepcopy(target)
        torch.manual_seed(11)
        with _precision(bf16):
            if algo == "td3":
                out = td3.update(a, t, _sgd(a), batch, td3.Params(gamma=0.9), update_actor=True)
            else:
                log_alpha = torch.nn.Parameter(torch.tensor(0.2).log())
                opt = sac.Optimizers(*_sgd(a), alpha=torch.optim.SGD([log_alpha], lr=0.5))
                out = sac.update(a, t, log_alpha, opt, batch, sac.Params(gamma=0.9), target_entropy=-2.0)
        assert all(p.dtype == torch.float32 and torch.isfinite(p).all() for p in a.parameters())
        results.append((out, a))
    (out32, a32), (out16, a16) = results
    for key in ("loss/critic", "loss/actor"):
        assert out16[key].dtype == torch.float32
        assert out16[key].item() == pytest.approx(out32[key].item(), rel=0.05, abs=0.05)
    for (name, p32), p16 in zip(a32.named_parameters(), a16.parameters()):
        torch.testing.assert_close(p16, p32, atol=0.02, rtol=0.02, msg=name)


def _precision(bf16):
    """The context the trainers open around an update (offpolicy.update_precision)."""
    return update_precision(ddpg.Params(bf16_updates=bf16), torch.device("cpu"))


def test_bf16_updates_turn_autocast_on_only_when_asked_and_refuse_crossq(monkeypatch):
    for bf16 in (False, True):
        with _precision(bf16):
            assert torch.is_autocast_enabled("cpu") == bf16
    # auto: bfloat16 only where the hardware computes it (timing.native_bf16: None is "cannot tell")
    for native in (True, False, None):
        monkeypatch.setattr("drivelab.training.learning.precision.native_bf16", lambda device, answer=native: answer)
        with _precision("auto"):
            assert torch.is_autocast_enabled("cpu") == (native is True)
    with pytest.raises(DrivelabError, match="'bf16_updates' must be true, false or auto"):
        sac.Params(bf16_updates="fast").validate()
    with pytest.raises(DrivelabError, match="td3.bf16_updates"):
        td3.Params(crossq=True, bf16_updates=True).validate()
