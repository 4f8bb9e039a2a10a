"""Environment layer: registration, MetaDrive offline adapter, action grid, vector envs."""

import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import drivelab  # noqa: F401  (registers the ids)
from drivelab.config import EnvConfig
from drivelab.envs import make_env, make_vector_env, metadrive_ids
from drivelab.envs.metadrive import assets_installed, held_in_simulator
from drivelab.envs.registration import TASKS
from drivelab.envs.wrappers import ActionRepeat, DiscreteActionGrid, ScenarioReplay
from drivelab.errors import DrivelabError


def _metadrive_files() -> set[str]:
    import metadrive

    root = Path(metadrive.__file__).parent
    return {str(p.relative_to(root)) for p in root.rglob("*") if "__pycache__" not in p.parts}


def test_metadrive_ids_are_registered_with_their_historical_meaning():
    assert set(metadrive_ids()) <= set(gym.registry)
    expected = {"MetaDrive-validation-v0": (0, 1000), "MetaDrive-10env-v0": (1000, 10),
                "MetaDrive-100envs-v0": (1000, 100), "MetaDrive-1000envs-v0": (1000, 1000),
                "SafeMetaDrive-validation-v0": (0, 1000), "SafeMetaDrive-100envs-v0": (1000, 100)}
    for env_id, (start, count) in expected.items():
        kwargs = gym.spec(env_id).kwargs
        assert (kwargs["start_seed"], kwargs["num_scenarios"]) == (start, count), env_id


def test_a_metadrive_id_works_offline_with_state_observations_and_time_limit_truncation(fresh_process):
    fresh_process(_check_metadrive_id)  # it draws the pygame top-down view: see conftest.run_in_fresh_process


def _check_metadrive_id():
    before = _metadrive_files()
    env = gym.make("MetaDrive-validation-v0", config={"use_render": False, "horizon": 25, "traffic_density": 0.0})
    try:
        assert env.observation_space.shape == (259,) and isinstance(env.observation_space, gym.spaces.Box)
        assert env.action_space.shape == (2,) and isinstance(env.action_space, gym.spaces.Box)
        obs, info = env.reset(seed=7)
        assert obs.shape == (259,) and info["scenario"] == 7
        for t in range(25):
            obs, reward, terminated, truncated, info = env.step(np.zeros(2, np.float32))  # stand still
            if terminated or truncated:
                break
        assert t == 24 and truncated and not terminated, "the step limit is a truncation, not a termination"
        assert set(info) >= {"success", "crash", "out_of_road", "route_completion", "cost", "speed", "ahead_m"}
        assert 0.0 < info["ahead_m"] <= 50.0
        assert info["timeout"] and not info["success"], "a car that stood still until the step limit timed out"
        frame = env.unwrapped.render_mode is None and env.unwrapped.metadrive.render(
            mode="topdown", window=False, screen_size=(64, 64))
        assert frame.shape == (64, 64, 3)
    finally:
        env.close()
    assert _metadrive_files() == before, "nothing may be written into MetaDrive's installation"


def test_a_metadrive_video_frame_follows_the_car_heading_up(fresh_process):
    fresh_process(_check_video_frame)


def _check_video_frame():
    from drivelab.training.outputs.video import overlay

    env = make_env(EnvConfig(id="MetaDrive-validation-v0"), render_mode="rgb_array")
    try:
        env.reset(seed=3)
        for t in range(60):  # straight on, then into a left bend: the view turns with the car
            env.step(np.array([0.0 if t < 30 else 0.3, 0.5], np.float32))
            if t in (29, 59):
                frame = overlay(env.render(), ["episode 0  step 1  return 0.0", "speed 20 km/h"])
                ego = np.array(env.unwrapped.metadrive.agent.top_down_color)
                rows, cols = np.nonzero((np.abs(frame.astype(float) - ego) <= 3).all(axis=-1))
                height, width = frame.shape[:2]
                assert frame.shape == (400, 400, 3) and len(rows) > 50, "the ego car is drawn"
                assert height / 3 <= rows.mean() <= 2 * height / 3 and width / 3 <= cols.mean() <= 2 * width / 3, \
                    f"ego car at ({rows.mean():.0f}, {cols.mean():.0f}), outside the central third"
                assert np.ptp(rows) > 1.5 * np.ptp(cols), "the car points up the frame"
    finally:
        env.close()


def test_seed_selects_scenario_within_the_split():
    env = gym.make("MetaDrive-10env-v0", traffic_density=0.0)
    try:
        assert env.reset(seed=3)[1]["scenario"] == 1003
        assert env.reset(seed=13)[1]["scenario"] == 1003
        first = env.reset(seed=5)[0]
        again = env.reset(seed=5)[0]
        np.testing.assert_array_equal(first, again)
    finally:
        env.close()


@pytest.mark.skipif(assets_installed(), reason="MetaDrive's 3D assets are installed here")
@pytest.mark.parametrize("config", [{"use_render": True}, {"image_observation": True}])
def test_features_that_need_3d_assets_fail_with_one_clear_line(config):
    with pytest.raises(DrivelabError) as err:
        make_env(EnvConfig(id="MetaDrive-validation-v0", kwargs={"config": config}))
    message = str(err.value)
    assert "asset" in message and "pull_asset" in message and "\n" not in message


def test_unknown_env_and_bad_kwargs_are_clear_errors():
    with pytest.raises(DrivelabError, match="unknown env id 'CartPole-v9'.*CartPole-v1"):
        make_env(EnvConfig(id="CartPole-v9"))
    with pytest.raises(DrivelabError, match="MetaDrive rejected its config"):
        make_env(EnvConfig(id="MetaDrive-validation-v0", kwargs={"no_such_option": 1}))
    with pytest.raises(DrivelabError, match="CartPole-v1"):
        make_env(EnvConfig(id="CartPole-v1", kwargs={"no_such_option": 1}))


def test_module_env_ids_import_their_module_first():
    """Gymnasium's "module:EnvId": the module (tests/flaky_env.py) registers the id when imported."""
    env = make_env(EnvConfig(id="flaky_env:Flaky-v0"))
    assert env.action_space == gym.spaces.Discrete(2)
    env.close()
    with pytest.raises(DrivelabError, match="unknown env id 'flaky_env:Flakey-v0'.*Flaky-v0"):
        make_env(EnvConfig(id="flaky_env:Flakey-v0"))
    with pytest.raises(DrivelabError) as err:
        make_env(EnvConfig(id="no_such_module:Flaky-v0"))
    assert "could not import module 'no_such_module'" in str(err.value) and "\n" not in str(err.value)
    assert not any("Flaky" in env_id for env_id in TASKS)   # `drivelab envs` lists no test fixture


def test_action_grid_table_is_steering_then_throttle():
    env = DiscreteActionGrid(_BoxEnv(), 3, 3, max_steering=0.6)
    assert env.action_space == gym.spaces.Discrete(9)
    np.testing.assert_allclose(env.action(1), [0.0, 1.0])     # full throttle, straight
    np.testing.assert_allclose(env.action(0), [0.6, 1.0])     # full throttle, left
    np.testing.assert_allclose(env.action(4), [0.0, 0.0])     # coast
    np.testing.assert_allclose(env.action(8), [-0.6, -1.0])   # brake, right
    fixed = DiscreteActionGrid(_BoxEnv(), 5, 1)
    np.testing.assert_allclose(fixed.table[:, 1], 1.0)         # one throttle bin = fixed throttle
    np.testing.assert_allclose(fixed.table[:, 0], [0.6, 0.3, 0.0, -0.3, -0.6])


class _BoxEnv(gym.Env):
    observation_space = gym.spaces.Box(-1, 1, (1,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (2,), np.float32)


class _Countdown(gym.Env):
    """Reward t at step t; terminates at step `end`; logs the actions it receives."""
    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def __init__(self, end: int = 5):
        self.end, self.t, self.actions = end, 0, []

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        self.t += 1
        self.actions.append(float(action[0]))
        return np.full(1, self.t, np.float32), float(self.t), self.t == self.end, False, {"t": self.t}


def test_action_repeat_holds_the_action_sums_rewards_and_stops_at_the_episode_end():
    inner = _Countdown(end=5)
    env = ActionRepeat(inner, 2)
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(np.array([0.5], np.float32))
    assert inner.actions == [0.5, 0.5] and reward == 1.0 + 2.0 and obs[0] == 2.0 and info == {"t": 2}
    assert not terminated
    env.step(np.array([-0.5], np.float32))                                  # steps 3 and 4
    obs, reward, terminated, truncated, info = env.step(np.array([0.25], np.float32))
    assert terminated and reward == 5.0 and info == {"t": 5}                # the end at step 5 stops the repeat
    assert inner.actions == [0.5, 0.5, -0.5, -0.5, 0.25]
    with pytest.raises(DrivelabError, match="env.action_repeat"):
        EnvConfig(id="CartPole-v1", action_repeat=0).validate()


class _Scenarios(gym.Env):
    """One-step episodes on scenarios 0..99 (drawn like drivelab's MetaDrive adapter draws them);
    the episode succeeds unless the scenario is in ``hard``."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, hard: set[int]):
        self.hard = hard
        self.scenario = -1

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        options = options or {}
        self.scenario = int(options["scenario"]) if "scenario" in options else int(self.np_random.integers(100))
        return np.zeros(1, np.float32), {"scenario": self.scenario}

    def step(self, action):
        success = self.scenario not in self.hard
        return np.zeros(1, np.float32), 0.0, success, not success, {"scenario": self.scenario, "success": success}


def _play_episodes(env: gym.Env, episodes: int, seed: int) -> list[tuple[int, bool]]:
    """(scenario, replayed) of each episode; the first reset is seeded, the others are not (as in a worker)."""
    played = []
    for episode in range(episodes):
        _, info = env.reset(seed=seed if episode == 0 else None)
        _, _, _, _, end_info = env.step(np.zeros(1, np.float32))
        assert end_info["replayed"] == info["replayed"]
        played.append((info["scenario"], info["replayed"]))
    return played


def test_scenario_replay_replays_the_scenarios_still_failed_and_evaluation_never_does():
    hard = {3, 14, 15, 92}
    env = ScenarioReplay(_Scenarios(hard), replay_prob=0.5)
    played = _play_episodes(env, 600, seed=7)
    replays = [scenario for scenario, replayed in played if replayed]
    assert 0.4 < len(replays) / len(played) < 0.6
    # only failed scenarios come back, and every one of them does; a success leaves the table
    assert set(replays) == hard and set(env.failed) == hard
    # ... and a scenario the agent has learned to drive stops being replayed
    env.unwrapped.hard = {3}
    later = [scenario for scenario, replayed in _play_episodes(env, 200, seed=8) if replayed]
    assert set(later) <= hard and later.count(3) > 80
    assert all(later.count(learned) <= 1 for learned in hard - {3})  # once more, then it succeeds
    assert set(env.failed) == {3}
    # the same seed plays the same scenarios; a scenario asked for by name is never replaced
    assert _play_episodes(ScenarioReplay(_Scenarios(hard), 0.5), 600, seed=7) == played
    _, info = env.reset(options={"scenario": 42})
    assert info == {"scenario": 42, "replayed": False}
    # training only: evaluation and the held-out report play every scenario as drawn
    cfg = EnvConfig(id="MetaDrive-1000envs-v0", scenario_replay=0.5)
    cfg.validate()
    assert cfg.played().scenario_replay == 0.0 and cfg.on("MetaDrive-validation-v0").scenario_replay == 0.0
    built = make_env(cfg)  # builds the wrapper (the only one this config asks for); no engine starts before a reset
    try:
        assert isinstance(built, ScenarioReplay)
    finally:
        built.close()
    with pytest.raises(DrivelabError, match="env.scenario_replay.*not a MetaDrive env"):
        EnvConfig(id="CartPole-v1", scenario_replay=0.5).validate()
    with pytest.raises(DrivelabError, match=r"env.scenario_replay' must be in \[0, 1\)"):
        EnvConfig(id="MetaDrive-1000envs-v0", scenario_replay=1.0).validate()


def _drive_straight(cfg: EnvConfig, decisions: int) -> tuple[gym.Env, list[np.ndarray]]:
    env = make_env(cfg)
    try:
        env.reset(seed=3)
        positions = []
        for _ in range(decisions):
            env.step(np.array([0.0, 1.0], np.float32))
            positions.append(np.array(env.unwrapped.metadrive.agent.position))
        return env, positions
    finally:
        env.close()


def test_simulator_repeat_holds_the_action_in_metadrive_and_evaluation_plays_the_published_env():
    cfg = EnvConfig(id="MetaDrive-validation-v0", action_repeat=2, simulator_repeat=True,
                    kwargs={"traffic_density": 0.0, "horizon": 41})
    held, held_path = _drive_straight(cfg, 8)
    config = held.unwrapped.metadrive.config
    assert (config["decision_repeat"], config["horizon"]) == (10, 20)  # 0.2 s per env step, the same time limit
    assert not isinstance(held, ActionRepeat)
    played = cfg.played()
    assert not played.simulator_repeat and cfg.on("MetaDrive-1000envs-v0").simulator_repeat is False
    wrapped, wrapped_path = _drive_straight(played, 8)
    assert isinstance(wrapped, ActionRepeat) and wrapped.unwrapped.metadrive.config["decision_repeat"] == 5
    # Without traffic both run the same physics steps under the same throttle: the car is where
    # the wrapper's car is after every decision, 0.2 s apart.
    assert np.linalg.norm(held_path[-1] - held_path[0]) > 1.0
    np.testing.assert_allclose(np.array(held_path), np.array(wrapped_path), atol=1e-3)
    # MetaDrive's step and time limit as given in a nested config too; no limit stays none
    assert held_in_simulator({"config": {"decision_repeat": 4, "horizon": 300}}, 3) == {
        "config": {"decision_repeat": 4, "horizon": 300}, "decision_repeat": 12, "horizon": 100}
    assert held_in_simulator({"horizon": None}, 2) == {"horizon": None, "decision_repeat": 10}
    with pytest.raises(DrivelabError, match="env.simulator_repeat.*not a MetaDrive env"):
        EnvConfig(id="CartPole-v1", action_repeat=2, simulator_repeat=True).validate()


def test_full_throttle_straight_drives_forward_along_the_lane():
    env = make_env(EnvConfig(id="MetaDrive-validation-v0", kwargs={"traffic_density": 0.0}, action_grid="3x3"))
    try:
        env.reset(seed=0)
        agent = env.unwrapped.metadrive.agent
        lane = agent.lane
        start_long, start_lat = lane.local_coordinates(agent.position)
        for _ in range(40):
            _, _, terminated, truncated, info = env.step(1)
            assert not (terminated or truncated)
        long, lat = lane.local_coordinates(agent.position)
        assert long - start_long > 15.0, "the car must move forward along its lane"
        assert abs(lat - start_lat) < 0.5, "and stay in it"
        assert info["speed"] > 5.0 and not info["out_of_road"]

        env.reset(seed=0)
        lane = env.unwrapped.metadrive.agent.lane
        start_long, _ = lane.local_coordinates(env.unwrapped.metadrive.agent.position)
        for _ in range(40):
            env.step(7)  # full brake, straight: the car does not move forward
        long, _ = lane.local_coordinates(env.unwrapped.metadrive.agent.position)
        assert long - start_long < 1.0
    finally:
        env.close()


def test_metadrive_vector_env_runs_in_subprocesses():
    cfg = EnvConfig(id="MetaDrive-10env-v0", num_envs=2, action_grid="3x3", kwargs={"horizon": 30})
    envs = make_vector_env(cfg, autoreset_mode=AutoresetMode.DISABLED)
    try:
        # subprocess envs, under drivelab's supervisor (drivelab.envs.supervised)
        assert type(envs).__name__ == "SupervisedVectorEnv" and type(envs.envs).__name__ == "AsyncVectorEnv"
        obs, _ = envs.reset(seed=[0, 1])
        assert obs.shape == (2, 259)
        obs, reward, terminated, truncated, info = envs.step(np.array([1, 1]))
        assert reward.shape == (2,) and "route_completion" in info
    finally:
        envs.close()
    with pytest.raises(DrivelabError, match="one instance per process"):
        make_vector_env(EnvConfig(id="MetaDrive-10env-v0", backend="sync"))


class _ReportsProbeVariable(gym.Wrapper):
    """Puts the worker's DRIVELAB_PROBE environment variable into the reset's info."""

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, {**info, "probe": os.environ.get("DRIVELAB_PROBE", "unset")}


def test_env_workers_see_the_trainers_environment_of_when_they_start(monkeypatch):
    # The fork server (conftest starts it) began before these variables were set: the workers
    # must see the trainer's environment of now, as spawned workers would.
    cfg = EnvConfig(id="CartPole-v1", num_envs=2, backend="async")
    for value in ("first", "second"):
        monkeypatch.setenv("DRIVELAB_PROBE", value)
        envs = make_vector_env(cfg, wrapper=_ReportsProbeVariable)
        try:
            _, info = envs.reset(seed=0)
        finally:
            envs.close()
        assert list(info["probe"]) == [value, value]


def test_box2d_and_pygame_coexist_with_metadrive():
    env = gym.make("LunarLander-v3", render_mode="rgb_array")
    try:
        env.reset(seed=0)
        assert env.render().ndim == 3
    finally:
        env.close()
    import pygame

    assert pygame.get_sdl_version()[0] == 2
