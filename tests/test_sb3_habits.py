"""What a Stable-Baselines3 user reaches for first: the API in tab completion, and a policy's
``predict`` and ``save``/``load``."""

from pathlib import Path

import numpy as np

import drivelab

CHECKPOINT = Path(__file__).parent / "data" / "checkpoints_v0.3" / "sac_pendulum"


def test_the_api_shows_in_dir():
    assert {"train", "load", "evaluate", "make_env", "build_config", "__version__"} <= set(dir(drivelab))


def test_predict_returns_the_action_and_no_state_like_sb3():
    policy = drivelab.load(CHECKPOINT)
    obs = np.array([0.5, -0.5, 0.1], np.float32)
    action, state = policy.predict(obs, deterministic=True)
    assert state is None and action.shape == (1,)
    np.testing.assert_array_equal(action, policy.act(obs))
    batch, _ = policy.predict(np.stack([obs, obs]))
    assert batch.shape == (2, 1)


def test_save_writes_the_policy_alone_and_load_reads_it_back(tmp_path):
    policy = drivelab.load(CHECKPOINT)
    saved = policy.save(tmp_path / "pendulum_policy")
    again = drivelab.load(saved)
    obs = np.random.default_rng(0).uniform(-1, 1, size=(5, 3)).astype(np.float32)
    np.testing.assert_array_equal(policy.predict(obs)[0], again.predict(obs)[0])
    # without the optimiser state and the replay buffer the checkpoint holds
    assert (saved / "tensors.safetensors").stat().st_size < (CHECKPOINT / "tensors.safetensors").stat().st_size / 2
