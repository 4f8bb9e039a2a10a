"""Off-policy training with the env workers acting (``act_in_workers``): the workers play chunks
with a copy of the actor while the learner updates (drivelab.training.collection.replay.ReplayCollector).

The replay buffer of the final checkpoint is read back and checked transition by transition on
``flaky_env:Tally-v0``, whose observations name the episode and the step within it.
"""

import csv

import numpy as np
import torch
from safetensors.torch import load_file

from drivelab.api import build_config, train
from drivelab.training.outputs.checkpoint import list_checkpoints, load_checkpoint
from flaky_env import importable_env
from processes import run_drivelab


def _tally(run_dir, algo="td3", steps=480, **env_kwargs):
    return build_config({
        "algo": algo, "steps": steps, "seed": 3, "run_dir": str(run_dir), "checkpoint_every": 10**6,
        "eval": {"every": 0}, "log_every": 16,
        "env": {"id": "flaky_env:Tally-v0", "num_envs": 2, "backend": "async", "kwargs": env_kwargs},
        algo: {"act_in_workers": True, "chunk_steps": 8, "learning_starts": 96, "utd": 0.25, "hidden": [16],
               "batch_size": 16}})


def _replay(run_dir) -> dict[str, np.ndarray]:
    tensors = load_file(str(list_checkpoints(run_dir)[-1] / "tensors.safetensors"))
    return {name.removeprefix("replay/"): value.numpy() for name, value in tensors.items() if name.startswith("replay/")}


def _check_streams(replay: dict[str, np.ndarray], num_envs: int) -> list[int]:
    """Check each env's stream of transitions (rows i, i + N, ...); returns the rows where a
    stream was cut (a worker restart, a resume): the episode had not ended, the buffer marked the
    row truncated (so that n-step returns stop there) and the stream goes on with a new episode."""
    obs, next_obs, actions, rewards = replay["obs"], replay["next_obs"], replay["actions"][:, 0], replay["rewards"]
    done = replay["terminated"] | replay["truncated"]
    # (s, a, r): the reward is 10 t + a for the action stored with s
    np.testing.assert_allclose(rewards, 10 * obs[:, 1] + actions, rtol=1e-6, atol=1e-5)
    # s': the same episode, one step on; terminated exactly where an even episode ended, truncated
    # where an odd one did, or where the episode was cut
    np.testing.assert_array_equal(next_obs[:, 0], obs[:, 0])
    np.testing.assert_array_equal(next_obs[:, 1], obs[:, 1] + 1)
    ended = next_obs[:, 1] == obs[:, 2]
    cut = replay["truncated"] & ~ended
    np.testing.assert_array_equal(replay["terminated"], ended & (obs[:, 0] % 2 == 0))
    np.testing.assert_array_equal(replay["truncated"], ended & (obs[:, 0] % 2 == 1) | cut)
    # every (episode, t) stored once
    assert len({(e, t) for e, t in obs[:, :2].tolist()}) == len(obs)
    for env in range(num_envs):
        stream_obs, stream_next, stream_done = obs[env::num_envs], next_obs[env::num_envs], done[env::num_envs]
        assert stream_obs[0, 1] == 0  # the first transition starts an episode
        for k in range(len(stream_obs) - 1):
            if stream_done[k]:
                assert stream_obs[k + 1, 1] == 0, (env, k)          # a new episode follows an ended or cut one
            else:
                np.testing.assert_array_equal(stream_next[k], stream_obs[k + 1])  # the episode goes on
    return np.flatnonzero(cut).tolist()


def test_workers_deliver_every_transition_once_in_order(tmp_path):
    cfg = _tally(tmp_path / "run")
    train(cfg, progress=False)
    replay = _replay(tmp_path / "run")
    assert len(replay["rewards"]) == 480
    assert replay["terminated"].any() and replay["truncated"].any()
    assert _check_streams(replay, num_envs=2) == []
    with open(tmp_path / "run" / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f)]
    lags = [float(r["value"]) for r in rows if r["name"] == "charts/policy_lag"]
    # two chunks of 2 x 8 steps in flight (chunks_in_flight) while the learner takes 0.25 gradient
    # steps per step stored: an actor at most 8 updates old
    assert lags and max(lags) == 8.0
    assert any(r["name"] == "loss/critic" for r in rows)


def test_a_worker_restart_drops_its_chunk_and_nothing_else(tmp_path):
    cfg = _tally(tmp_path / "run", at_step=100, marker=str(tmp_path / "crashed"))
    train(cfg, progress=False)
    assert (tmp_path / "crashed").exists()
    replay = _replay(tmp_path / "run")
    # the chunk in flight when a worker raised is dropped: both envs' streams cut once, side by side
    cuts = _check_streams(replay, num_envs=2)
    assert len(cuts) == 2 and cuts[1] == cuts[0] + 1 and cuts[0] % 2 == 0, cuts
    assert len(replay["rewards"]) == 480


def test_acting_in_workers_is_reproducible_for_a_seed(tmp_path):
    for name in ("a", "b"):
        train(_tally(tmp_path / name, algo="sac", steps=320), progress=False)
    a, b = (load_file(str(list_checkpoints(tmp_path / name)[-1] / "tensors.safetensors")) for name in ("a", "b"))
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_a_killed_asynchronous_run_resumes(tmp_path):
    run_dir = tmp_path / "run"
    args = ["--algo", "td3", "--env", "flaky_env:Tally-v0", "--num-envs", "2", "--env.backend", "async",
            "--td3.act_in_workers", "true", "--td3.chunk_steps", "8", "--td3.learning_starts", "96", "--td3.utd", "0.25",
            "--td3.hidden", "[16]", "--td3.batch_size", "16", "--steps", "480", "--checkpoint_every", "160",
            "--eval.every", "0", "--seed", "3", "--no-progress", "--resume-if-exists", "--run-dir", str(run_dir)]
    env = {**importable_env(), "DRIVELAB_KILL_AT": "mid-checkpoint:3", "DRIVELAB_KILL_MARKER": str(tmp_path / "killed")}
    killed = run_drivelab("train", *args, env=env, timeout=300)
    assert killed.returncode == -9 and (tmp_path / "killed").exists(), killed.stderr
    assert load_checkpoint(run_dir).step == 160      # killed while writing the step-320 checkpoint
    again = run_drivelab("train", *args, env=importable_env(), timeout=300)
    assert again.returncode == 0, again.stderr
    replay = _replay(run_dir)
    assert load_checkpoint(run_dir).step == 480 and len(replay["rewards"]) == 480
    # the episodes in flight at the step-160 checkpoint restart on resume: those streams are cut
    # there once (an env that had just ended its episode at step 160 has nothing to cut)
    in_flight = [row for row in (158, 159) if replay["next_obs"][row, 1] < replay["obs"][row, 2]]
    assert _check_streams(replay, num_envs=2) == in_flight

# Learning with the workers acting: tests/test_offpolicy.py::test_sac_and_td3_swing_up_the_pendulum[td3].
