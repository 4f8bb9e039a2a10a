"""Reference policies (drivelab.tools.baselines): the MetaDrive expert and the lane keeper run inside
env subprocesses, exactly like evaluation of a checkpoint; errors are one-line DrivelabErrors."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode

import drivelab  # noqa: F401  (registers the ids)
from drivelab.tools.baselines import (BASELINES, ExpertActionObservation, LaneKeepingObservation, ObservationIsAction,
                                RandomPolicy, baseline)
from drivelab.envs.wrappers import DiscreteActionGrid
from drivelab.envs import worker_start_method
from drivelab.errors import DrivelabError
from processes import METADRIVE_ID

HORIZON = 100


# Module-level env factories: the workers import this module to rebuild them.
def expert_env() -> gym.Env:
    return ExpertActionObservation(gym.make("MetaDrive-validation-v0", horizon=HORIZON))


def sampled_expert_env() -> gym.Env:
    return ExpertActionObservation(gym.make("MetaDrive-validation-v0", horizon=HORIZON), deterministic=False)


def lane_keeping_env() -> gym.Env:
    return LaneKeepingObservation(gym.make("MetaDrive-validation-v0", horizon=HORIZON, traffic_density=0.0))


def _metadrive_files() -> set[str]:
    import metadrive

    root = Path(metadrive.__file__).parent
    return {str(p.relative_to(root)) for p in root.rglob("*") if "__pycache__" not in p.parts}


def _play(env_fn, policy, seeds: list[int], context: str | None = None) -> tuple[list[dict], np.ndarray]:
    """One episode per seed, in parallel subprocesses; returns each env's last info and every action.
    The subprocesses start as drivelab's env workers do (``context`` None: from the test session's
    fork server on Linux, which has imported MetaDrive) or with ``context``."""
    context = context or worker_start_method(METADRIVE_ID)
    envs = AsyncVectorEnv([env_fn] * len(seeds), context=context, autoreset_mode=AutoresetMode.DISABLED)
    try:
        obs, _ = envs.reset(seed=seeds)
        actions, last = [], [None] * len(seeds)
        done = np.zeros(len(seeds), bool)
        while not done.all():
            action = policy.to_env(policy.act(torch.as_tensor(obs), deterministic=True))
            actions.append(action[~done])
            obs, _, terminated, truncated, info = envs.step(action)
            for i in np.flatnonzero((terminated | truncated) & ~done):
                last[i] = {key: info[key][i] for key in ("route_completion", "crash", "out_of_road", "success")}
            done |= terminated | truncated
    finally:
        envs.close()
    return last, np.concatenate(actions)


def test_metadrive_expert_drives_offline_in_spawned_subprocesses(monkeypatch):
    # Any download attempt in a worker would go to a closed port and fail the reset.
    for var in ("http_proxy", "https_proxy", "HTTP_PROXY", "HTTPS_PROXY"):
        monkeypatch.setenv(var, "http://127.0.0.1:9")
    before = _metadrive_files()
    wrapper, policy = baseline("metadrive-expert", gym.spaces.Box(-1.0, 1.0, (2,), np.float32))
    assert wrapper.func is ExpertActionObservation and wrapper.keywords == {"deterministic": True}
    last, actions = _play(expert_env, policy, seeds=[0, 1], context="spawn")   # spawned: they see the proxies
    assert actions.shape[1] == 2 and actions.dtype == np.float32
    assert np.all(actions >= -1.0) and np.all(actions <= 1.0)
    assert actions[:, 1].mean() > 0.1                     # the expert accelerates
    for info in last:
        assert info["route_completion"] > 0.05            # and the car moves along its route
    assert _metadrive_files() == before                   # nothing downloaded into site-packages


def test_sampled_expert_repeats_with_its_seed_and_differs_from_the_mean():
    sampled, _ = baseline("metadrive-expert", gym.spaces.Box(-1.0, 1.0, (2,), np.float32), deterministic=False)
    assert sampled.keywords == {"deterministic": False}
    policy = ObservationIsAction(gym.spaces.Box(-1.0, 1.0, (2,), np.float32))
    _, twins = _play(sampled_expert_env, policy, seeds=[3, 3])     # rows alternate env 0, env 1
    _, mean = _play(expert_env, policy, seeds=[3])
    n = min(20, len(mean))
    np.testing.assert_array_equal(twins[0:2 * n:2], twins[1:2 * n:2])  # same seed, same samples
    assert np.abs(twins[0:2 * n:2] - mean[:n]).max() > 0.05           # but not the mean action


def test_lane_keeping_follows_the_lane_in_a_subprocess():
    wrapper, policy = baseline("lane-keeping", gym.spaces.Box(-1.0, 1.0, (2,), np.float32))
    assert wrapper is LaneKeepingObservation
    last, actions = _play(lane_keeping_env, policy, seeds=[0])
    assert np.all(np.abs(actions) <= 1.0) and np.allclose(actions[:, 1], 0.5)
    assert last[0]["route_completion"] > 0.05 and not last[0]["out_of_road"]


def test_unknown_baseline_is_a_one_line_error_with_a_suggestion():
    message = "unknown baseline 'metadrive_expert' \\(did you mean metadrive-expert\\?\\)"
    with pytest.raises(DrivelabError, match=message):
        baseline("metadrive_expert", gym.spaces.Box(-1.0, 1.0, (2,), np.float32))
    assert BASELINES == ("random", "lane-keeping", "metadrive-expert")


def test_expert_and_lane_keeping_refuse_other_action_spaces_and_envs():
    for name in ("metadrive-expert", "lane-keeping"):
        with pytest.raises(DrivelabError, match=f"the {name} baseline needs a Box\\(2,\\)"):
            baseline(name, gym.spaces.Discrete(9))
    # Building MetaDrive without resetting it starts no engine, so this stays in-process.
    env = DiscreteActionGrid(gym.make("MetaDrive-validation-v0"), 3, 3)
    try:
        with pytest.raises(DrivelabError, match="needs a Box\\(2,\\) \\[steering, throttle\\] action space"):
            ExpertActionObservation(env)
        with pytest.raises(DrivelabError, match="needs a Box\\(2,\\)"):
            LaneKeepingObservation(env)
    finally:
        env.close()
    with pytest.raises(DrivelabError, match="needs a MetaDrive env, got CartPole-v1"):
        ExpertActionObservation(gym.make("CartPole-v1"))
    lander = LaneKeepingObservation(gym.make("LunarLander-v3", continuous=True))  # Box(2,) but no lane geometry
    with pytest.raises(DrivelabError, match="needs 'cte' and 'heading_error' in info"):
        lander.reset(seed=0)
    lander.close()


def test_random_policy_shapes_bounds_and_seeding():
    box = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    obs = torch.zeros(5, 259)
    policy = RandomPolicy(box, seed=3)
    action = policy.act(obs)
    assert action.shape == (5, 2)
    assert not torch.equal(action[0], action[1])          # one sample per row
    env_action = policy.to_env(action)
    assert env_action.shape == (5, 2) and env_action.dtype == np.float32
    assert np.all(np.abs(env_action) <= 1.0)
    assert torch.equal(RandomPolicy(box, seed=3).act(obs), action)   # seeded
    assert not torch.equal(RandomPolicy(box, seed=4).act(obs), action)

    wrapper, discrete = baseline("random", gym.spaces.Discrete(9), seed=0)
    assert wrapper is None
    picks = discrete.to_env(discrete.act(torch.zeros(7, 4)))
    assert picks.shape == (7,) and picks.dtype.kind == "i" and np.all((0 <= picks) & (picks < 9))


def test_observation_is_action_passes_actions_through_clipped():
    policy = ObservationIsAction(gym.spaces.Box(-1.0, 1.0, (2,), np.float32))
    obs = torch.tensor([[0.3, -0.2], [1.7, -3.0]], dtype=torch.float64)
    action = policy.act(obs)
    assert action.dtype == torch.float32 and action.shape == (2, 2)
    np.testing.assert_allclose(policy.to_env(action), [[0.3, -0.2], [1.0, -1.0]], rtol=1e-6)
    assert policy.to_env(action).dtype == np.float32


def test_cli_evaluates_the_expert_with_the_checkpoint_protocol(run_cli):
    out = run_cli("eval", "--policy", "metadrive-expert", "--env", "MetaDrive-validation-v0", "--episodes", "2",
                  "--env-kwarg", f"horizon={HORIZON}", "--json")
    assert out.returncode == 0, out.stderr
    import json

    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["episodes"] == 2 and result["policy"] == "metadrive-expert"
    for key in ("return_mean", "success_rate", "crash_rate", "out_of_road_rate", "route_completion"):
        assert key in result
    assert result["route_completion"] > 0.05 and result["return_mean"] > 0
    missing = run_cli("eval", "no/such/run", "--policy", "random")
    assert missing.returncode == 2 and "no/such/run" in missing.stderr and "Traceback" not in missing.stderr


def test_eval_table_says_whether_actions_were_sampled():
    from drivelab.tools.tables import format_evaluations

    row = {"policy": "metadrive-expert", "env": "MetaDrive-validation-v0", "return_mean": 1.0, "return_std": 0.0,
           "success_rate": 0.5}
    assert format_evaluations([row, row], 2, 0).splitlines()[0].endswith(", deterministic")
    assert format_evaluations([row, row], 2, 0, sampled=True).splitlines()[0].endswith(", sampled actions")
