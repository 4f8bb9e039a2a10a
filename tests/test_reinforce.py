import gymnasium as gym
import numpy as np
import torch

from drivelab.algos.reinforce import advantage_weights
from drivelab.training.learning.losses import policy_gradient_loss
from drivelab.training.learning.policy_nets import Policy


def test_policy_gradient_loss_value_and_gradient_by_hand():
    # A tabular softmax policy: d log softmax(z)_a / dz = onehot(a) - p.
    logits = torch.tensor([[0.2, -0.4, 1.0], [0.0, 0.0, 0.0]], requires_grad=True)
    actions = torch.tensor([2, 0])
    weights = torch.tensor([1.5, -2.0])
    log_prob = torch.distributions.Categorical(logits=logits).log_prob(actions)
    loss = policy_gradient_loss(log_prob, weights)
    loss.backward()

    p = torch.softmax(logits.detach(), -1)
    expected_loss = -(torch.log(p[0, 2]) * 1.5 + torch.log(p[1, 0]) * -2.0) / 2
    assert torch.allclose(loss, expected_loss)
    onehot = torch.nn.functional.one_hot(actions, 3).float()
    expected_grad = -(weights[:, None] * (onehot - p)) / 2
    assert torch.allclose(logits.grad, expected_grad, atol=1e-6)


def test_gradient_step_makes_rewarded_actions_likelier_and_punished_ones_rarer():
    torch.manual_seed(0)
    obs_space = gym.spaces.Box(-1, 1, (4,), np.float32)
    policy = Policy(obs_space, gym.spaces.Discrete(3), hidden=[16])
    obs = torch.randn(8, 4)
    good, bad = torch.zeros(8, dtype=torch.long), torch.ones(8, dtype=torch.long)
    before_good = policy.distribution(obs).log_prob(good).mean().item()
    before_bad = policy.distribution(obs).log_prob(bad).mean().item()
    optimizer = torch.optim.SGD(policy.parameters(), lr=0.5)
    dist = policy.distribution(torch.cat([obs, obs]))
    loss = policy_gradient_loss(dist.log_prob(torch.cat([good, bad])), torch.cat([torch.ones(8), -torch.ones(8)]))
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    assert policy.distribution(obs).log_prob(good).mean().item() > before_good
    assert policy.distribution(obs).log_prob(bad).mean().item() < before_bad


def test_gaussian_policy_gradient_moves_mean_toward_rewarded_action():
    torch.manual_seed(0)
    policy = Policy(gym.spaces.Box(-1, 1, (3,), np.float32), gym.spaces.Box(-1, 1, (2,), np.float32), hidden=[8])
    obs = torch.randn(16, 3)
    target = torch.full((16, 2), 0.5)
    optimizer = torch.optim.SGD(policy.parameters(), lr=0.1)
    before = (policy.distribution(obs).mean - target).abs().mean().item()
    for _ in range(20):
        loss = policy_gradient_loss(policy.distribution(obs).log_prob(target), torch.ones(16))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = (policy.distribution(obs).mean - target).abs().mean().item()
    assert after < 0.5 * before


def test_advantage_modes():
    r = np.array([1.0, 2.0, 3.0], np.float32)
    np.testing.assert_allclose(advantage_weights(r, "rtg"), r)
    np.testing.assert_allclose(advantage_weights(r, "mean"), [-1.0, 0.0, 1.0])
    assert abs(advantage_weights(r, "normalize").std() - 1.0) < 1e-5
