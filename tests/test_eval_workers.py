"""Evaluation inside the env workers (drivelab.training.collection.evaluation.run_episodes_in_workers):
the same episodes as evaluation stepped from this process, deterministic, replayed after a worker
failure; and the progress bar of `drivelab eval`."""

import dataclasses
from pathlib import Path

import gymnasium as gym
import pytest

from drivelab.cli import main
from drivelab.tools.baselines import RandomPolicy
from drivelab.tools.policies import load_policy
from drivelab.training.collection.evaluation import play, plays_in_workers

DATA = Path(__file__).parent / "data" / "checkpoints_v0.3"


def _same(a, b) -> None:
    assert a.returns.tolist() == b.returns.tolist()
    assert a.lengths.tolist() == b.lengths.tolist()
    assert a.metrics.keys() == b.metrics.keys()
    for name in a.metrics:
        assert a.metrics[name].tolist() == b.metrics[name].tolist(), name


@pytest.mark.parametrize("name", ["ppo_cartpole", "sac_pendulum"])
def test_workers_play_the_episodes_evaluation_plays_in_this_process(name, capsys):
    policy, cfg, _ = load_policy(DATA / name)
    # reward/native: an episode metric, as MetaDrive's driving metrics, to compare too
    env = dataclasses.replace(cfg.env.played(), reward={"native": {"weight": 0.5}})
    here = play(dataclasses.replace(env, backend="sync", num_envs=1), policy, 5, seed=3)
    assert "reward/native" in here.metrics
    workers = dataclasses.replace(env, backend="async", num_envs=2)
    assert plays_in_workers(workers, policy, deterministic=True)
    first = play(workers, policy, 5, seed=3, progress="policy")
    assert "5/5" in capsys.readouterr().err
    _same(first, here)  # a batch of one observation in each: the same actions, bit for bit
    _same(play(workers, policy, 5, seed=3), first)  # deterministic
    _same(play(dataclasses.replace(workers, num_envs=3), policy, 5, seed=3), first)
    # against a batch of two in this process: the same up to the float rounding of the batch
    batched = play(dataclasses.replace(env, backend="sync", num_envs=2), policy, 5, seed=3)
    assert batched.lengths.tolist() == first.lengths.tolist()
    assert batched.returns == pytest.approx(first.returns, rel=1e-6)


@pytest.mark.parametrize("fail", ["raise", "die"])
def test_a_worker_failure_replays_the_episodes_not_finished(fail, tmp_path, capsys):
    policy, cfg, _ = load_policy(DATA / "ppo_cartpole")
    clean = play(dataclasses.replace(cfg.env.played(), backend="async", num_envs=2), policy, 5)
    flaky = dataclasses.replace(cfg.env.played(), id="flaky_env:Flaky-v0", backend="async", num_envs=2,
                                kwargs={"fail": fail, "at_step": 60, "marker": str(tmp_path / "failed")})
    _same(play(flaky, policy, 5), clean)
    assert (tmp_path / "failed").is_file() and "restarting the envs" in capsys.readouterr().err


def test_videos_sampled_actions_the_random_baseline_and_sync_envs_play_in_this_process():
    policy, cfg, _ = load_policy(DATA / "ppo_cartpole")
    subprocess_envs = dataclasses.replace(cfg.env, backend="async")
    assert plays_in_workers(subprocess_envs, policy, deterministic=True)
    assert not plays_in_workers(subprocess_envs, policy, deterministic=True, recorder=object())
    assert not plays_in_workers(subprocess_envs, policy, deterministic=False)
    assert not plays_in_workers(subprocess_envs, RandomPolicy(gym.spaces.Discrete(2)), deterministic=True)
    assert not plays_in_workers(dataclasses.replace(cfg.env, backend="sync"), policy, deterministic=True)
    assert not plays_in_workers(subprocess_envs, type("Local", (), {"act": lambda self, o, d: o})(), True)


def test_drivelab_eval_shows_the_episodes_done_unless_no_progress(capsys):
    for flags, shown in (([], True), (["--no-progress"], False)):
        with pytest.raises(SystemExit) as exit_:
            main(["eval", str(DATA / "ppo_cartpole"), "--episodes", "6", "--num-envs", "2", "--json", *flags])
        assert exit_.value.code == 0
        err = capsys.readouterr().err
        assert ("6/6" in err) is shown, err
