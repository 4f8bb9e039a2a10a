import gymnasium as gym
import numpy as np
import pytest
import torch

from drivelab.training.buffers import ReplayBuffer
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
