"""A2C / PPO / GRPO: numerics of the shared building blocks, GRPO's group resets, learning."""

import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

from drivelab.algos import grpo
from drivelab.api import build_config, evaluate_checkpoint, train
from drivelab.envs import env_spaces, make_vector_env
from drivelab.errors import DrivelabError
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.learning.losses import approx_kl, clipped_surrogate_loss, value_loss
from drivelab.training.learning.policy_nets import ActorCritic
from drivelab.training.learning.normalize import RunningMeanStd
from drivelab.training.learning.returns import gae, group_relative_advantages, group_relative_step_advantages
from drivelab.training.learning.rollout_buffers import EpisodeStorage
from drivelab.training.collection.rollout import RolloutCollector
from drivelab.training.run import Run


def test_gae_by_hand():
    # one env, three steps, terminated at the end; gamma = lam = 0.5
    r, v = np.array([[1.0], [0.0], [2.0]]), np.array([[0.5], [1.0], [1.5]])
    next_v = np.array([[1.0], [1.5], [9.9]])           # 9.9 is ignored: terminated
    term = done = np.array([[False], [False], [True]])
    adv, ret = gae(r, v, next_v, term, done, 0.5, 0.5)
    d2 = 2.0 - 1.5                                      # 0.5
    d1 = 0.0 + 0.5 * 1.5 - 1.0                          # -0.25
    d0 = 1.0 + 0.5 * 1.0 - 0.5                          # 1.0
    a2, a1 = d2, d1 + 0.25 * d2
    a0 = d0 + 0.25 * a1
    np.testing.assert_allclose(adv[:, 0], [a0, a1, a2], rtol=1e-6)
    np.testing.assert_allclose(ret, adv + v, rtol=1e-6)


def test_gae_lambda_one_is_monte_carlo_return_minus_value():
    r = np.array([[1.0], [2.0], [3.0]])
    v = np.array([[0.3], [0.2], [0.1]])
    adv, _ = gae(r, v, np.r_[v[1:], [[0.0]]], *([np.array([[False], [False], [True]])] * 2), gamma=0.9, lam=1.0)
    mc = [1 + 0.9 * 2 + 0.81 * 3, 2 + 0.9 * 3, 3]
    np.testing.assert_allclose(adv[:, 0], np.array(mc) - v[:, 0], rtol=1e-6)


def test_truncation_bootstraps_from_the_final_observation_but_termination_does_not():
    r, v = np.array([[1.0], [1.0]]), np.array([[0.0], [0.0]])
    next_v = np.array([[10.0], [0.0]])                  # V(final obs) of step 0 is 10
    ended = np.array([[True], [False]])
    truncated_adv, _ = gae(r, v, next_v, terminated=np.array([[False], [False]]), dones=ended, gamma=0.9, lam=0.95)
    terminated_adv, _ = gae(r, v, next_v, terminated=ended, dones=ended, gamma=0.9, lam=0.95)
    assert truncated_adv[0, 0] == pytest.approx(1.0 + 0.9 * 10.0)
    assert terminated_adv[0, 0] == pytest.approx(1.0)
    # the next episode's first step never leaks into the previous episode's advantage
    assert truncated_adv[1, 0] == terminated_adv[1, 0] == pytest.approx(1.0)


class _HandCritic(torch.nn.Module):
    """V(s) = 100 x + 7 (x: the cart position): a critic we can compute by hand."""

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return 100.0 * obs[:, :1] + 7.0


def hand_critic_agent(obs_space, act_space) -> ActorCritic:
    """A small actor with the hand-made critic (a policy factory for the env workers too)."""
    agent = ActorCritic(obs_space, act_space, [8])
    agent.critic = _HandCritic()
    return agent


@pytest.mark.parametrize("in_workers", [False, True], ids=["trainer-steps", "act-in-workers"])
def test_collector_uses_the_value_of_the_final_observation_on_truncation(in_workers, tmp_path):
    cfg = build_config({"algo": "ppo", "run_dir": str(tmp_path), "seed": 0,
                        "env": {"id": "CartPole-v1", "num_envs": 2, "kwargs": {"max_episode_steps": 4},
                                "backend": "async" if in_workers else "auto"}})
    obs_space, act_space = env_spaces(cfg.env)
    agent = hand_critic_agent(obs_space, act_space)
    run = Run(cfg, progress=False)
    collector = RolloutCollector(cfg.env, run, num_steps=6, gamma=0.99, gae_lambda=0.95, scale_rewards=False,
                                 policy_factory=hand_critic_agent if in_workers else None)
    buf = collector.buffer
    try:
        collector.collect(agent)
    finally:
        collector.close()
        run.close()
    # CartPole does not fall within 4 steps: every episode is truncated at its 4th step (row 3).
    assert buf.dones[3].all() and not buf.terminated.any()
    for i in range(2):
        # the next row is a new episode's first observation, whose value must NOT be used ...
        assert buf.next_values[3, i] != pytest.approx(100.0 * buf.obs[4, i, 0].item() + 7.0)
        # ... inside an episode it is the next row's value
        assert buf.next_values[2, i] == pytest.approx(100.0 * buf.obs[3, i, 0].item() + 7.0, rel=1e-5)
        # ... and on the truncated step it is V(final obs). CartPole integrates x' = x + 0.02 * x_dot
        # (explicit Euler), so the final cart position follows from row 3's observation.
        final_x = buf.obs[3, i, 0].item() + 0.02 * buf.obs[3, i, 1].item()
        assert buf.next_values[3, i] == pytest.approx(100.0 * final_x + 7.0, rel=1e-4)
    # the stored values and log-probs are those of the agent's weights for the stored observations
    with torch.no_grad():
        dist, values = agent.distribution_and_value(buf.obs.flatten(0, 1))
        torch.testing.assert_close(values, buf.values.flatten())
        torch.testing.assert_close(dist.log_prob(buf.actions.flatten()), buf.log_probs.flatten())
    assert list(run.episodes.lengths) == [4, 4]   # one truncated episode per env, counted once


def _in_workers(run_dir, algo="ppo", steps=20_000, **env):
    cfg = build_config({"algo": algo, "steps": steps, "seed": 3, "run_dir": str(run_dir),
                        "env": {"id": "CartPole-v1", "num_envs": 2, "backend": "async", **env},
                        algo: {"act_in_workers": True, "num_steps": 256 if algo == "ppo" else 5}})
    train(cfg, progress=False)
    import csv

    with open(run_dir / "metrics.csv") as f:
        return [(row["step"], row["value"]) for row in csv.DictReader(f) if row["name"] == "episode/return"]


def test_ppo_acting_in_the_env_workers_learns_and_repeats_itself(tmp_path):
    first = _in_workers(tmp_path / "first")
    assert first == _in_workers(tmp_path / "second")   # same seed, same episodes, whatever the timing
    assert float(first[-1][1]) >= 100, first[-3:]        # CartPole's random policy: ~22
    assert _in_workers(tmp_path / "a2c", algo="a2c", steps=2_000)   # A2C's short rollouts log episodes too
    with pytest.raises(DrivelabError, match="'ppo.act_in_workers' needs subprocess envs"):
        _in_workers(tmp_path / "sync", backend="sync")


def _grouped_rollout(run_dir, pick_last: bool):
    cfg = build_config({"algo": "ppo", "run_dir": str(run_dir), "seed": 0,
                        "env": {"id": "CartPole-v1", "num_envs": 3, "backend": "async", "step_groups": 2}})
    run = Run(cfg, progress=False)                       # seeds torch: the same initial weights
    obs_space, act_space = env_spaces(cfg.env)
    agent = ActorCritic(obs_space, act_space, [8])
    collector = RolloutCollector(cfg.env, run, num_steps=40, gamma=0.99, gae_lambda=0.95, scale_rewards=False)
    if pick_last:  # serve the groups in the opposite order to the one the pipes suggest
        collector.envs.wait_any = lambda in_flight: in_flight[-1]
    try:
        return collector.envs.slices, collector.collect(agent), list(run.episodes.returns)
    finally:
        collector.close()
        run.close()


def test_step_groups_fill_the_same_rollout_whichever_group_answers_first(tmp_path):
    slices, first, first_returns = _grouped_rollout(tmp_path / "first", pick_last=False)
    _, last, last_returns = _grouped_rollout(tmp_path / "last", pick_last=True)
    assert slices == [slice(0, 2), slice(2, 3)]
    for name in first._fields:
        torch.testing.assert_close(getattr(first, name), getattr(last, name), msg=name)
    assert sorted(first_returns) == sorted(last_returns) and first_returns  # the same episodes ended


def test_episode_tracker_steps_a_group_of_envs():
    tracker = EpisodeTracker(num_envs=3)
    tracker.step(np.array([1.0, 1.0, 1.0]), np.zeros(3, bool), {})
    ended = tracker.step(np.array([2.0]), np.array([True]), {}, first_env=2)   # env 2 alone
    assert [(e.env, e.ret, e.length) for e in ended] == [(2, 3.0, 2)]
    np.testing.assert_array_equal(tracker.running_length, [1, 1, 0])


def test_group_relative_advantages_by_hand():
    adv = group_relative_advantages(np.array([[1.0, 2.0, 3.0], [5.0, 5.0, 5.0]]))
    np.testing.assert_allclose(adv[0], [-1.2247449, 0.0, 1.2247449], rtol=1e-6)
    np.testing.assert_allclose(adv[1], 0.0)  # no difference within the group, no signal


def test_group_relative_step_advantages_compare_members_alive_at_the_same_step():
    rtg = np.array([[3.0, 1.0, 2.0], [1.0, 0.0, 5.0], [0.5, 0.0, 0.0]])
    alive = np.array([[True, True, True], [True, False, True], [True, False, False]])
    adv = group_relative_step_advantages(rtg, alive)
    np.testing.assert_allclose(adv[0], [1.2247449, -1.2247449, 0.0], rtol=1e-6)
    np.testing.assert_allclose(adv[1], [-1.0, 0.0, 1.0], rtol=1e-6)
    np.testing.assert_allclose(adv[2], 0.0)  # one member alive: nothing to compare


def test_grpo_members_of_a_group_start_from_the_same_state_and_wait_masked(tmp_path):
    cfg = build_config({"algo": "grpo", "run_dir": str(tmp_path), "seed": 1,
                        "env": {"id": "CartPole-v1", "num_envs": 6}, "grpo": {"group_size": 3, "batch_steps": 300}})
    obs_space, act_space = env_spaces(cfg.env)
    envs = make_vector_env(cfg.env, autoreset_mode=AutoresetMode.DISABLED)
    run = Run(cfg, progress=False)
    torch.manual_seed(0)
    agent = grpo.build_policy(cfg, obs_space, act_space)
    storage = EpisodeStorage(8, 6, obs_space, act_space)
    try:
        rounds, steps, length = grpo.collect_group_rounds(envs, agent, storage, cfg.algo_params, run, cfg.algo_params.batch_steps)
    finally:
        envs.close()
        run.close()
    assert steps >= 300 and steps == storage.recorded[:length].sum()
    assert len({r.seed for r in rounds}) == len(rounds) >= 4
    for index, rnd in enumerate(rounds):
        cols = slice(3 * rnd.group, 3 * rnd.group + 3)
        start_obs = storage.obs[rnd.start, cols]
        np.testing.assert_array_equal(start_obs, np.broadcast_to(start_obs[0], start_obs.shape))
        mine = storage.tag[:length, cols] == index
        for g in range(3):  # each member's episode is one contiguous block from the round's start
            rows = np.flatnonzero(mine[:, g])
            assert rows[0] == rnd.start and np.array_equal(rows, np.arange(rows[0], rows[-1] + 1))
            assert storage.dones[rows[-1], 3 * rnd.group + g]  # ... that ends with the episode
    starts = {tuple(storage.obs[r.start, 3 * r.group]) for r in rounds}
    assert len(starts) == len(rounds), "each round starts from a new state"
    advantages = grpo.group_advantages(storage, rounds, length, cfg.algo_params)
    assert np.all(advantages[~storage.recorded[:length]] == 0)


def test_ppo_losses_by_hand():
    log_old = torch.zeros(2)
    log_new = torch.log(torch.tensor([1.5, 0.5]))
    loss, ratio = clipped_surrogate_loss(log_new, log_old, torch.tensor([1.0, -1.0]), clip_coef=0.2)
    # min(1.5*1, 1.2*1) = 1.2 ; min(0.5*-1, 0.8*-1) = -0.8 ; loss = -(1.2 - 0.8)/2
    assert loss.item() == pytest.approx(-0.2)
    np.testing.assert_allclose(ratio.numpy(), [1.5, 0.5], rtol=1e-6)
    v = value_loss(torch.tensor([2.0]), torch.tensor([0.0]), torch.tensor([1.0]), clip_coef=0.5)
    assert v.item() == pytest.approx(0.5 * max((2 - 1) ** 2, (0.5 - 1) ** 2))
    assert approx_kl(torch.zeros(5)).item() == 0.0 and approx_kl(torch.tensor([0.3, -0.3])).item() > 0


def test_running_mean_std_matches_numpy():
    data = np.random.default_rng(0).normal(3.0, 2.0, size=(1000, 4))
    rms = RunningMeanStd((4,))
    for chunk in np.split(data, 10):
        rms.update(torch.as_tensor(chunk))
    np.testing.assert_allclose(rms.mean.numpy(), data.mean(0), rtol=1e-4)
    np.testing.assert_allclose(rms.var.numpy(), data.var(0), rtol=1e-3)


def test_ppo_with_normalisation_checkpoints_its_statistics_and_resumes(tmp_path):
    data = {"algo": "ppo", "steps": 1024, "seed": 0, "run_dir": str(tmp_path / "r"), "checkpoint_every": 512,
            "env": {"id": "CartPole-v1", "num_envs": 2},
            "ppo": {"num_steps": 256, "normalize_obs": True, "normalize_reward": True}}
    train(build_config(data), progress=False)
    train(build_config({**data, "steps": 2048}), resume=True, progress=False)
    result, _, ckpt = evaluate_checkpoint(tmp_path / "r", episodes=2)
    assert ckpt.name.endswith("2048")
    from safetensors.torch import load_file

    tensors = load_file(str(ckpt / "tensors.safetensors"))
    assert tensors["module/policy/obs_rms.count"] > 2000 and "module/reward_rms/var" in tensors


@pytest.mark.slow
@pytest.mark.parametrize("algo, steps, params", [
    ("ppo", 100_000, {}),
    ("a2c", 100_000, {}),
    ("grpo", 100_000, {"group_size": 8}),
])
def test_on_policy_algorithms_solve_cartpole(algo, steps, params, tmp_path):
    cfg = build_config({"algo": algo, "steps": steps, "seed": 0, "run_dir": str(tmp_path / algo),
                        "env": {"id": "CartPole-v1", "num_envs": 8}, algo: params})
    train(cfg, progress=False)
    result, _, _ = evaluate_checkpoint(tmp_path / algo, episodes=20)
    assert result.summary()["return_mean"] >= 195, result.summary()


def test_grpo_needs_whole_groups(tmp_path):
    with pytest.raises(DrivelabError, match="multiple of 'grpo.group_size'"):  # checked with the config now
        train(build_config({"algo": "grpo", "run_dir": str(tmp_path), "env": {"num_envs": 6}, "grpo": {"group_size": 4}}),
              progress=False)


@pytest.mark.parametrize("algo, params, grid", [
    ("ppo", {"num_steps": 40, "num_minibatches": 2, "update_epochs": 1}, None),   # continuous actions
    ("ppo", {"num_steps": 40, "num_minibatches": 2, "update_epochs": 1, "act_in_workers": True}, "3x3"),
    ("grpo", {"group_size": 2, "batch_steps": 40, "update_epochs": 1}, "3x3"),     # same-scenario groups
])
def test_on_policy_algorithms_run_on_metadrive_in_subprocesses(algo, params, grid, tmp_path):
    cfg = build_config({"algo": algo, "steps": 80, "seed": 0, "run_dir": str(tmp_path / algo),
                        "env": {"id": "MetaDrive-10env-v0", "num_envs": 2, "action_grid": grid,
                                "kwargs": {"horizon": 30, "traffic_density": 0.0}}, algo: params})
    train(cfg, progress=False)
    import csv

    with open(tmp_path / algo / "metrics.csv") as f:
        names = {row["name"] for row in csv.DictReader(f)}
    assert {"episode/return", "episode/route_completion", "episode/out_of_road_rate"} <= names
