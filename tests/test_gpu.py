"""Every algorithm on CUDA, where there is one (``pytest -m gpu``); skipped on CPU-only machines,
CI among them. What a CPU can check of the same discipline is in tests/test_devices.py.

Each algorithm trains a short run with its networks on ``cuda`` (evaluating as it goes), resumes on
``cuda``, and its checkpoint then loads, acts and exports as a CPU policy: the tensors it saved
carry no device."""

import numpy as np
import pytest
import torch

import drivelab
from drivelab.cli import main
from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]

# Off-policy runs reach their first updates at 300 steps, before the first checkpoint at 400.
SHORT = {"reinforce": {}, "a2c": {"a2c": {"num_steps": 32}}, "ppo": {"ppo": {"num_steps": 64}},
         "grpo": {}, "ddpg": {"ddpg": {"learning_starts": 300}}, "td3": {"td3": {"learning_starts": 300}},
         "sac": {"sac": {"learning_starts": 300}}}


@pytest.mark.parametrize("algo", list(SHORT))
def test_every_algorithm_trains_evaluates_and_resumes_on_cuda_and_its_checkpoint_acts_on_the_cpu(algo, tmp_path):
    """Evaluation during training (checkpoints/best, its video) runs the networks on cuda too;
    the checkpoint then loads, acts and exports as a CPU policy."""
    run = tmp_path / algo
    drivelab.train(algo, "Pendulum-v1", steps=400, seed=0, num_envs=4, run_dir=run, progress=False, device="cuda",
                   eval={"every": 400, "episodes": 1, "final": True}, checkpoint_every=400, **SHORT[algo])
    assert (run / "checkpoints" / "best").is_dir() and list(run.glob("videos/*.mp4"))
    first = checkpoint_step(list_checkpoints(run)[-1])   # REINFORCE's whole episodes overshoot 400
    drivelab.train(run_dir=run, resume=True, steps=first + 400, progress=False)
    assert checkpoint_step(list_checkpoints(run)[-1]) >= first + 400
    policy = drivelab.load(run)
    assert all(p.device.type == "cpu" for p in policy.deployed.parameters())
    action, _ = policy.predict(np.zeros(3, np.float32))
    assert action.shape == (1,) and np.isfinite(action).all()
    with pytest.raises(SystemExit) as exit_:
        main(["export", str(run), "--format", "torchscript", "--out", str(tmp_path / "exported")])
    assert not exit_.value.code


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_the_cnn_path_trains_on_cuda(algo, tmp_path):
    fields = {"ppo": {"ppo": {"num_steps": 64}},
              "sac": {"sac": {"learning_starts": 100, "buffer_size": 300, "batch_size": 16}}}[algo]
    drivelab.train(algo, "CarRacing-v3", steps=200, seed=0, num_envs=1, run_dir=tmp_path / algo, progress=False,
                   device="cuda", eval={"every": 0}, **fields)
    assert drivelab.load(tmp_path / algo).predict(np.zeros((96, 96, 3), np.uint8))[0].shape == (3,)
