import numpy as np
import pytest

from drivelab.training.learning.returns import normalize, reward_to_go


def test_reward_to_go_single_episode_by_hand():
    rewards = np.array([1.0, 2.0, 3.0])
    dones = np.array([False, False, True])
    # R_2 = 3; R_1 = 2 + 0.5*3 = 3.5; R_0 = 1 + 0.5*3.5 = 2.75
    np.testing.assert_allclose(reward_to_go(rewards, dones, 0.5), [2.75, 3.5, 3.0])


def test_reward_to_go_undiscounted_is_suffix_sum():
    rewards = np.array([1.0, -1.0, 4.0, 2.0])
    dones = np.array([False, False, False, True])
    np.testing.assert_allclose(reward_to_go(rewards, dones, 1.0), [6.0, 5.0, 6.0, 2.0])


def test_reward_to_go_stops_at_episode_boundaries_per_env():
    # env 0: episode [1, 1] ends at t=1, new episode [10] ends at t=2
    # env 1: one episode [2, 2, 2]
    rewards = np.array([[1.0, 2.0], [1.0, 2.0], [10.0, 2.0]])
    dones = np.array([[False, False], [True, False], [True, True]])
    out = reward_to_go(rewards, dones, 0.9)
    np.testing.assert_allclose(out[:, 0], [1 + 0.9 * 1, 1, 10], rtol=1e-6)
    np.testing.assert_allclose(out[:, 1], [2 + 0.9 * 2 + 0.81 * 2, 2 + 0.9 * 2, 2], rtol=1e-6)
    assert out.dtype == np.float32 and out.shape == (3, 2)


def test_normalize_has_zero_mean_unit_std():
    x = np.array([1.0, 2.0, 3.0, 10.0])
    y = normalize(x)
    assert abs(y.mean()) < 1e-7
    assert y.std() == pytest.approx(1.0, rel=1e-6)
