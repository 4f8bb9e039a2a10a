import gymnasium as gym
import numpy as np
import pytest
import torch

from drivelab.training.learning.replay_buffer import ReplayBuffer
from drivelab.errors import DrivelabError

VEC = gym.spaces.Box(-1, 1, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)


def _add(buffer, start, n):
    obs = np.arange(start, start + n, dtype=np.float32)[:, None].repeat(3, 1)
    buffer.add(obs, np.zeros((n, 2)), np.arange(start, start + n), obs + 1,
               np.zeros(n, bool), np.ones(n, bool))


def test_wrap_around_overwrites_the_oldest_rows():
    buffer = ReplayBuffer(5, VEC, ACT)
    _add(buffer, 0, 3)
    assert (buffer.pos, len(buffer)) == (3, 3)
    _add(buffer, 3, 3)                       # rows 3, 4, then 0 (overwrites transition 0)
    assert (buffer.pos, len(buffer)) == (1, 5)
    np.testing.assert_array_equal(buffer.rewards, [5, 1, 2, 3, 4])
    np.testing.assert_array_equal(buffer.next_obs[:, 0], [6, 2, 3, 4, 5])


def test_images_are_stored_and_sampled_as_uint8():
    image = gym.spaces.Box(0, 255, (8, 8, 3), np.uint8)
    buffer = ReplayBuffer(10, image, ACT)
    frames = np.random.default_rng(0).integers(0, 256, (4, 8, 8, 3), dtype=np.uint8)
    buffer.add(frames, np.zeros((4, 2)), np.zeros(4), frames, np.zeros(4, bool), np.zeros(4, bool))
    assert buffer.obs.dtype == np.uint8 and buffer.obs.nbytes == 10 * 8 * 8 * 3
    batch = buffer.sample(6, np.random.default_rng(0))
    assert batch.obs.dtype == torch.uint8 and batch.obs.shape == (6, 8, 8, 3)


def test_sample_shapes_and_dtypes_and_terminated_is_kept_apart_from_truncated():
    buffer = ReplayBuffer(100, VEC, ACT)
    _add(buffer, 0, 10)                      # all truncated, none terminated
    batch = buffer.sample(32, np.random.default_rng(1))
    assert batch.obs.shape == (32, 3) and batch.actions.shape == (32, 2) and batch.rewards.shape == (32,)
    assert batch.actions.dtype == batch.rewards.dtype == batch.terminated.dtype == torch.float32
    assert batch.terminated.sum() == 0 and buffer.truncated[:10].all()
    assert batch.rewards.max() < 10          # only filled rows are sampled


def test_an_impossible_buffer_is_refused_up_front():
    with pytest.raises(DrivelabError, match="GiB.*buffer_size"):
        ReplayBuffer(10**12, VEC, ACT)


def test_state_round_trip():
    buffer = ReplayBuffer(8, VEC, ACT)
    _add(buffer, 0, 11)
    tensors, meta = buffer.state()
    again = ReplayBuffer(8, VEC, ACT)
    again.load_state(tensors, meta)
    for name in ("obs", "next_obs", "actions", "rewards", "terminated", "truncated"):
        np.testing.assert_array_equal(getattr(again, name), getattr(buffer, name))
    assert (again.pos, again.size) == (buffer.pos, buffer.size)
    with pytest.raises(DrivelabError, match="buffer_size"):
        ReplayBuffer(16, VEC, ACT).load_state(tensors, meta)


def _two_envs_in_lockstep(buffer):
    """4 steps of 2 envs, stored as the collectors store them (row 2t: env 0, row 2t + 1: env 1).
    Env 0 gets rewards 1, 2, 3, 4 and terminates at its 3rd step; env 1 gets 10, 20, 30, 40 and
    is truncated at its 2nd. obs = the row's number, next_obs = 100 + the row's number."""
    rewards = [(1, 10), (2, 20), (3, 30), (4, 40)]
    terminated = [(0, 0), (0, 0), (1, 0), (0, 0)]
    truncated = [(0, 0), (0, 1), (0, 0), (0, 0)]
    for t in range(4):
        rows = np.array([2 * t, 2 * t + 1], np.float32)
        buffer.add(rows[:, None].repeat(3, 1), np.zeros((2, 2)), np.array(rewards[t], np.float32),
                   100 + rows[:, None].repeat(3, 1), np.array(terminated[t], bool), np.array(truncated[t], bool))


def _every_row(buffer):
    """{obs row: (n-step reward, the row bootstrapped from, terminated, discount)} over many samples."""
    batch = buffer.sample(400, np.random.default_rng(0))
    return {int(o): (round(float(r), 4), int(n) - 100, int(d), round(float(g), 4))
            for o, r, n, d, g in zip(batch.obs[:, 0], batch.rewards, batch.next_obs[:, 0], batch.terminated, batch.discount)}


def test_n_step_returns_match_a_hand_calculation_and_stop_at_episode_ends_and_the_newest_row():
    buffer = ReplayBuffer(10, VEC, ACT, gamma=0.5, n_step=3, num_envs=2)
    _two_envs_in_lockstep(buffer)
    assert _every_row(buffer) == {
        0: (1 + 0.5 * 2 + 0.25 * 3, 4, 1, 0.125),  # three rewards; the third terminates
        1: (10 + 0.5 * 20, 3, 0, 0.25),            # stops at the truncation, bootstraps from its s'
        2: (2 + 0.5 * 3, 4, 1, 0.25),
        3: (20, 3, 0, 0.5),
        4: (3, 4, 1, 0.5),
        5: (30 + 0.5 * 40, 7, 0, 0.25),            # stops at the newest row of env 1
        6: (4, 6, 0, 0.5),
        7: (40, 7, 0, 0.5),
    }
    one_step = ReplayBuffer(10, VEC, ACT, gamma=0.5, num_envs=2)
    _two_envs_in_lockstep(one_step)
    assert all(r == one_step.rewards[row] and last == row and g == 0.5 for row, (r, last, _, g) in _every_row(one_step).items())


def test_n_step_returns_follow_each_env_across_the_ring_and_stop_where_an_episode_was_cut():
    buffer = ReplayBuffer(7, VEC, ACT, gamma=0.5, n_step=3, num_envs=2)  # capacity rounded down to 6
    _two_envs_in_lockstep(buffer)            # rows 6 and 7 overwrote rows 0 and 1
    assert buffer.capacity == 6
    rows = _every_row(buffer)
    assert set(rows) == {2, 3, 4, 5, 6, 7}
    assert rows[5] == (30 + 0.5 * 40, 7, 0, 0.25)     # row 5's successor wrapped to the ring's start
    buffer.cut_episodes()                    # e.g. a resume: both envs start new episodes
    buffer.add(np.full((2, 3), 8.0, np.float32), np.zeros((2, 2)), np.array([5, 50], np.float32),
               np.full((2, 3), 108.0, np.float32), np.zeros(2, bool), np.zeros(2, bool))
    rows = _every_row(buffer)
    assert rows[6] == (4, 6, 0, 0.5) and rows[5] == (30 + 0.5 * 40, 7, 0, 0.25)
