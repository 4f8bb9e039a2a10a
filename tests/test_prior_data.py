"""Prior data (RLPD's symmetric sampling): demonstrations recorded by ``drivelab demos``, mixed
into every replay batch at ``prior_share``, carried by checkpoints, refused in one line when they
do not fit the env."""

from __future__ import annotations

import json
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import drivelab.algos.sac as sac
from drivelab.api import build_config, load, train
from drivelab.errors import DrivelabError
from drivelab.tools.demonstrations import record_demonstrations, to_unit_actions
from drivelab.training.outputs.demonstrations import load_demonstrations, read_about, save_demonstrations
from drivelab.training.outputs.checkpoint import list_checkpoints

MARK = 5.0   # a reward Pendulum never pays (its rewards are <= 0): marks a prior row in a batch


def _pendulum(run_dir, steps, **params):
    return build_config({"algo": "sac", "steps": steps, "seed": 0, "run_dir": str(run_dir), "checkpoint_every": 300,
                         "env": {"id": "Pendulum-v1", "num_envs": 1},
                         "sac": {"learning_starts": 200, "hidden": [32, 32], "batch_size": 32, **params}})


def _marked_demonstrations(path, rows=50, obs_dim=3, with_costs=False):
    """A demonstration file of ``rows`` Pendulum-shaped transitions whose rewards are all MARK."""
    rng = np.random.default_rng(0)
    obs_space = gym.spaces.Box(-8.0, 8.0, (obs_dim,), np.float32)
    data = {"obs": rng.normal(size=(rows, obs_dim)).astype(np.float32),
            "next_obs": rng.normal(size=(rows, obs_dim)).astype(np.float32),
            "actions": rng.uniform(-1, 1, (rows, 1)).astype(np.float32), "rewards": np.full(rows, MARK, np.float32),
            "terminated": np.zeros(rows, bool), "truncated": np.zeros(rows, bool)}
    if with_costs:
        data["costs"] = np.zeros(rows, np.float32)
    return save_demonstrations(path, data, obs_space, gym.spaces.Box(-2.0, 2.0, (1,), np.float32),
                               env="Pendulum-v1", policy="test", env_steps=rows)


@pytest.mark.parametrize("share", [0.5, 0.25])
def test_every_batch_holds_the_configured_share_of_prior_transitions(share, tmp_path, monkeypatch):
    demos = _marked_demonstrations(tmp_path / "demos.safetensors")
    shares, real_update = [], sac.update

    def spy(agent, target, log_alpha, opt, batch, *args, **kwargs):
        shares.append(((batch.rewards == MARK).sum().item(), len(batch.rewards)))
        assert torch.all(batch.rewards[-int(round(share * 32)):] == MARK)   # the prior rows are the batch's last
        return real_update(agent, target, log_alpha, opt, batch, *args, **kwargs)

    monkeypatch.setattr(sac, "update", spy)
    result = train(_pendulum(tmp_path / "run", 300, prior_data=str(demos), prior_share=share), progress=False)
    assert len(shares) >= 100 and set(shares) == {(round(share * 32), 32)}   # utd 1 after the heat-up
    assert result.metrics["prior/transitions"] == 50 and result.metrics["prior/env_steps"] == 50


def test_prior_data_survive_a_checkpoint_and_the_resumed_run_is_exact(tmp_path):
    demos = _marked_demonstrations(tmp_path / "demos.safetensors")
    train(_pendulum(tmp_path / "straight", 600, prior_data=str(demos)), progress=False)
    # stopped at 400 steps, between two of Pendulum's 200-step episodes (an episode in flight restarts)
    train(_pendulum(tmp_path / "resumed", 400, prior_data=str(demos)), progress=False)
    saved = load_file(str(list_checkpoints(tmp_path / "resumed")[-1] / "tensors.safetensors"))
    assert torch.all(saved["prior/rewards"] == MARK) and saved["prior/obs"].shape == (50, 3)
    demos.unlink()   # the resumed run takes its prior data from the checkpoint
    train(_pendulum(tmp_path / "resumed", 600, prior_data=str(demos)), resume=True, progress=False)
    a = load_file(str(list_checkpoints(tmp_path / "straight")[-1] / "tensors.safetensors"))
    b = load_file(str(list_checkpoints(tmp_path / "resumed")[-1] / "tensors.safetensors"))
    weights = [k for k in a if k.startswith("module/")]
    assert weights and all(torch.equal(a[k], b[k]) for k in weights)


def test_demonstrations_of_another_observation_layout_are_refused_in_one_line(tmp_path):
    demos = _marked_demonstrations(tmp_path / "wide.safetensors", obs_dim=4)
    with pytest.raises(DrivelabError, match=r"prior_data: .*wide.safetensors holds observations of shape \[4\], "
                                            r"the env has \[3\]"):
        train(_pendulum(tmp_path / "run", 300, prior_data=str(demos)), progress=False)
    done = subprocess.run([sys.executable, "-m", "drivelab", "train", "--algo", "sac", "--env", "Pendulum-v1",
                           "--steps", "300", "--sac.learning_starts", "100", "--run-dir", str(tmp_path / "cli"),
                           "--sac.prior_data", str(demos),
                           "--no-progress"], capture_output=True, text=True)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "wide.safetensors holds observations" in lines[0], done.stderr


def test_files_that_are_not_demonstrations_or_lack_costs_are_refused(tmp_path):
    space = gym.spaces.Box(-8.0, 8.0, (3,), np.float32)
    action = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)
    with pytest.raises(DrivelabError, match="no such file"):
        load_demonstrations(tmp_path / "missing.safetensors", space, action)
    (tmp_path / "junk.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(DrivelabError, match="is not a demonstration file"):
        load_demonstrations(tmp_path / "junk.safetensors", space, action)
    demos = _marked_demonstrations(tmp_path / "no_costs.safetensors")
    with pytest.raises(DrivelabError, match="lacks costs"):
        load_demonstrations(demos, space, action, costs=True)
    rows, _ = load_demonstrations(_marked_demonstrations(tmp_path / "costs.safetensors", with_costs=True), space, action,
                                  costs=True)
    assert len(rows["costs"]) == 50
    with pytest.raises(DrivelabError, match="prior_share"):
        _pendulum(tmp_path / "r", 300, prior_share=1.0)


def test_drivelab_demos_records_a_policys_transitions_in_the_learners_units(tmp_path):
    train(_pendulum(tmp_path / "teacher", 300), progress=False)
    out = tmp_path / "demos.safetensors"
    done = subprocess.run([sys.executable, "-m", "drivelab", "demos", str(tmp_path / "teacher"), "--steps", "450",
                           "--out", str(out), "--no-progress"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    about, rows = read_about(out), load_file(str(out))
    assert about["env"] == "Pendulum-v1" and about["env_steps"] == 450 and about["obs_shape"] == [3]
    assert about["episodes"] == 2                        # Pendulum's 200-step episodes, truncated
    assert rows["truncated"].sum() == 2 and rows["terminated"].sum() == 0
    # s' of a step is the next step's s inside an episode; the actions are the policy's, in [-1, 1] units
    inside = ~rows["truncated"][:-1]
    assert torch.equal(rows["next_obs"][:-1][inside], rows["obs"][1:][inside])
    policy = load(tmp_path / "teacher")
    expected = to_unit_actions(policy.act(rows["obs"][:5].numpy()).astype(np.float64), gym.spaces.Box(-2.0, 2.0, (1,)))
    np.testing.assert_allclose(rows["actions"][:5].numpy(), expected, atol=1e-6)
    assert json.loads(json.dumps(about))   # JSON metadata, readable without drivelab
    # and a learner reads the file
    train(_pendulum(tmp_path / "student", 300, prior_data=str(out)), progress=False)


def test_demonstrations_are_refused_for_a_policy_that_does_not_fit_the_env(tmp_path):
    train(_pendulum(tmp_path / "teacher", 300), progress=False)
    from drivelab.envs.config import EnvConfig

    with pytest.raises(DrivelabError, match="MountainCarContinuous-v0 has observations"):
        record_demonstrations(load(tmp_path / "teacher"), EnvConfig(id="MountainCarContinuous-v0"), 10,
                              tmp_path / "x.safetensors", progress=False)
