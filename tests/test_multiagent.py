"""Multi-agent MetaDrive: the PettingZoo view, the batch of agent slots, per-car GAE, IPPO's run.

The batch interface is checked on a scripted scene (tests/scripted_scene.py) whose every
observation and reward names its agent and step, so a misaligned row shows at once.
"""

import json
import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from drivelab.cli import main
from drivelab.envs.multiagent import SCENES, AgentSlots, MultiAgentDrive
from drivelab.envs.registration import MULTIAGENT_SCENES
from drivelab.training.collection.agents import agent_advantages, mean_field
from drivelab.training.outputs.checkpoint import load_checkpoint
from flaky_env import importable_env
from processes import run_drivelab
from scripted_scene import ScriptedScene


def _cli(capsys, *args):
    with pytest.raises(SystemExit) as stop:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return stop.value.code, out, err


def test_every_registered_scene_id_names_a_scene():
    """The ids (drivelab.envs.registration, imported without MetaDrive) and the scenes agree."""
    assert sorted(MULTIAGENT_SCENES.values()) == sorted(SCENES)


def test_a_metadrive_scene_passes_pettingzoo_parallel_api_test():
    env = MultiAgentDrive("Intersection", num_agents=4, horizon=40)
    try:
        with warnings.catch_warnings():
            # every car may leave before the bound of names is used up: said as a warning by the test
            warnings.filterwarnings("ignore", message="No agents present")
            parallel_api_test(env, num_cycles=400)
    finally:
        env.close()


def test_slots_keep_each_agent_aligned_across_crashes_arrivals_and_respawns():
    scene = ScriptedScene()
    env = AgentSlots(scene, num_agents=2)
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(obs, [[0, 0, 0], [1, 0, 0]])     # a0 in slot 0, a1 in slot 1
    actions = np.array([[0.1, 0.2], [0.3, 0.4]], np.float32)
    # step 1: a0 crashes, a2 takes its slot at once
    obs, _, terminated, truncated, info = env.step(actions)
    assert not terminated and not truncated
    np.testing.assert_array_equal(scene.actions_seen[0]["a1"], actions[1])
    np.testing.assert_array_equal(info["acted"], [True, True])
    np.testing.assert_array_equal(info["agent_reward"], [1, 11])
    np.testing.assert_array_equal(info["agent_terminated"], [True, False])
    np.testing.assert_array_equal(info["crash"], [True, False])
    np.testing.assert_array_equal(info["agent_cost"], [1, 0])
    np.testing.assert_array_equal(info["agent_final_obs"][0], [0, 1, 0])  # a0's last observation
    np.testing.assert_array_equal(obs, [[2, 1, 1], [1, 1, 0]])            # the row is a2's now
    np.testing.assert_array_equal(info["position"], [[10, 0], [5, 0]])       # where a2 and a1 stand
    np.testing.assert_array_equal(info["agent_final_position"][0], [0, 0])  # where a0 ended
    # step 2: a1's step limit (truncated), its slot is left empty
    obs, _, _, _, info = env.step(actions)
    np.testing.assert_array_equal(scene.actions_seen[1]["a2"], actions[0])
    np.testing.assert_array_equal(info["agent_reward"], [22, 12])
    np.testing.assert_array_equal(info["agent_truncated"], [False, True])
    np.testing.assert_array_equal(info["timeout"], [False, True])
    np.testing.assert_array_equal(info["agent_final_obs"][1], [1, 2, 0])
    np.testing.assert_array_equal(info["alive"], [True, False])
    np.testing.assert_array_equal(obs[1], [0, 0, 0])
    # step 3: the empty slot's action goes nowhere; a3 arrives into it
    obs, _, _, _, info = env.step(actions)
    assert set(scene.actions_seen[2]) == {"a2"}
    np.testing.assert_array_equal(info["acted"], [True, False])
    np.testing.assert_array_equal(info["agent_reward"], [23, 0])
    np.testing.assert_array_equal(obs, [[2, 3, 1], [3, 3, 3]])
    # step 4: a2 arrives at its destination
    obs, _, _, _, info = env.step(actions)
    np.testing.assert_array_equal(info["success"], [True, False])
    np.testing.assert_array_equal(info["agent_reward"], [24, 34])
    assert not info["scene_end"]
    # step 5: the last car ends: the scene begins anew with its first two cars
    obs, _, _, _, info = env.step(actions)
    np.testing.assert_array_equal(info["acted"], [False, True])
    np.testing.assert_array_equal(info["agent_terminated"], [False, True])
    assert info["scene_end"]
    np.testing.assert_array_equal(obs, [[0, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(info["alive"], [True, True])


def test_gae_per_car_matches_a_hand_computation():
    """Two slots over 3 steps. Slot 0: car A goes on, then is truncated at t=1 (bootstrap from its
    last observation's value 5); car B arrives at t=2 and is still driving after the rollout (value 7).
    Slot 1: car C is terminated at t=0, the slot is empty at t=1, car D drives at t=2 (next value 2)."""
    g, lam = 0.9, 0.5
    rewards = np.array([[1.0, 2.0], [1.0, 99.0], [3.0, 1.0]])
    values = np.array([[4.0, 1.0], [3.0, 50.0], [6.0, 1.5]])
    next_values = np.array([[3.0, 0.0], [5.0, 0.0], [7.0, 2.0]])  # A: V(s1); A's final obs; after the rollout
    acted = np.array([[True, True], [True, False], [True, True]])
    terminated = np.array([[False, True], [False, False], [False, False]])
    truncated = np.array([[False, False], [True, False], [False, False]])
    adv, ret = agent_advantages(rewards, values, next_values, acted, terminated, truncated, g, lam)
    d_a1 = 1.0 + g * 5.0 - 3.0                 # truncated: bootstrap, trace stops
    d_a0 = 1.0 + g * 3.0 - 4.0
    d_b2 = 3.0 + g * 7.0 - 6.0
    d_c0 = 2.0 - 1.0                           # terminated: no future
    d_d2 = 1.0 + g * 2.0 - 1.5
    expected = np.array([[d_a0 + g * lam * d_a1, d_c0], [d_a1, 0.0], [d_b2, d_d2]])
    np.testing.assert_allclose(adv, expected, rtol=1e-6)
    np.testing.assert_allclose(ret, np.where(acted, expected + values, 0.0), rtol=1e-6)


def test_the_mean_field_critic_input_averages_the_neighbours_within_the_radius():
    """One scene of three slots: cars at x = 0, 4 and 20 m (radius 5), and a car that ended at x = 3."""
    obs = np.array([[[1.0, 0.0], [3.0, 2.0], [9.0, 9.0]]], np.float32)
    positions = np.array([[[0.0, 0.0], [4.0, 0.0], [20.0, 0.0]]])
    alive = np.array([[True, True, True]])
    joint = mean_field(obs, positions, alive, obs, positions, radius=5.0)
    np.testing.assert_allclose(joint, [[1, 0, 3, 2], [3, 2, 1, 0], [9, 9, 0, 0]])  # the far car has no neighbour
    ended = np.array([[[7.0, 7.0], [0.0, 0.0], [0.0, 0.0]]], np.float32)
    ended_at = np.array([[[3.0, 0.0], [np.nan, np.nan], [np.nan, np.nan]]])
    joint = mean_field(obs, positions, alive, ended, ended_at, radius=5.0)
    np.testing.assert_allclose(joint[0], [7, 7, 2, 1])                  # the mean of the cars at 0 and 4 m
    np.testing.assert_allclose(joint[1:, 2:], 0)                         # no position: no neighbours


IPPO = ["--algo", "ippo", "--env", "MultiAgentIntersection-v0", "--env.kwargs", '{"num_agents": 4, "horizon": 60}',
        "--num-envs", "2", "--ippo.num_steps", "32", "--ippo.hidden", "[32,32]", "--eval.every", "0", "--seed", "1",
        "--no-progress"]


def test_ippo_trains_on_a_scene_and_eval_prints_the_cars_metrics(tmp_path, capsys):
    run_dir = tmp_path / "ma"
    code, _, err = _cli(capsys, "train", *IPPO, "--steps", "192", "--run-dir", run_dir)
    assert code == 0, err
    logged = (run_dir / "metrics.csv").read_text()
    assert "episode/success_rate" in logged and "charts/live_agents" in logged
    code, out, err = _cli(capsys, "eval", run_dir, "--episodes", "1", "--json", "--no-progress",
                          "--env-kwarg", "horizon=40")
    assert code == 0, err
    row = json.loads(out)
    assert row["episodes"] == 1 and row["agent_episodes"] >= 4
    for key in ("success_rate", "crash_rate", "out_of_road_rate", "crashes_per_episode", "efficiency", "live_agents"):
        assert key in row and np.isfinite(row[key]), key


def test_a_killed_multiagent_run_resumes_to_its_end(tmp_path):
    run_dir = tmp_path / "ma"
    args = [*IPPO, "--steps", "256", "--checkpoint_every", "64", "--run-dir", str(run_dir), "--resume-if-exists"]
    env = {**importable_env(), "DRIVELAB_KILL_AT": "mid-checkpoint:3", "DRIVELAB_KILL_MARKER": str(tmp_path / "k")}
    killed = run_drivelab("train", *args, env=env, timeout=300)
    assert killed.returncode == -9 and load_checkpoint(run_dir).step == 64, killed.stderr
    done = run_drivelab("train", *args, env=importable_env(), timeout=300)
    assert done.returncode == 0, done.stderr
    assert load_checkpoint(run_dir).step == 256


@pytest.mark.parametrize("args, names", [
    (["--env", "MultiAgentIntersektion-v0"], "MultiAgentIntersection-v0"),
    (["--env", "MultiAgentIntersection-v0", "--env.kwargs.num_agents", "0"], "num_agents"),
    (["--env", "MultiAgentIntersection-v0", "--env.kwargs.num_agents", "49"], "1 to 48"),
    (["--env", "MultiAgentRoundabout-v0", "--env.action_grid", "3x3"], "env.action_grid"),
    (["--env", "MultiAgentIntersection-v0", "--algo", "ppo"], "ippo"),
    (["--env", "CartPole-v1"], "single-agent"),
    (["--env", "MultiAgentIntersection-v0", "--eval.every", "1000"], "eval.every"),
])
def test_bad_multiagent_input_is_one_line_with_exit_code_2(args, names, tmp_path, capsys):
    code, _, err = _cli(capsys, "train", "--algo", "ippo", *args, "--steps", "64", "--run-dir", tmp_path / "r")
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and names in lines[0], err
