"""The cost signal of constrained RL (drivelab.envs.costs): the env's own cost and episode sums,
cost terms, the action repeat's cost, the reward-shaping baseline, MetaDrive's cost_to_reward,
and the guard that ends episodes of rolled-over or stalled cars."""

import math
import re

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import drivelab  # noqa: F401
from drivelab.envs import EnvConfig, make_env, make_vector_env
from drivelab.envs.costs import CostSignal
from drivelab.envs.metadrive import StuckGuard
from drivelab.errors import DrivelabError
from drivelab.training.outputs.episodes import EpisodeTracker, step_costs

LANES = "constrained_env:ThreeLanes-v0"
FAST, MIDDLE = np.ones(1, np.float32), np.zeros(1, np.float32)


def _episode(env, action) -> list[tuple[float, dict]]:
    """(reward, info) of each step of one episode, the reset's info first (reward 0)."""
    _, info = env.reset(seed=0)
    steps, done = [(0.0, info)], False
    while not done:
        _, reward, terminated, truncated, info = env.step(action)
        steps.append((reward, info))
        done = terminated or truncated
    return steps


def test_the_env_cost_passes_through_with_its_episode_sum():
    env = make_env(EnvConfig(id=LANES))
    steps = _episode(env, FAST)
    assert [info["cost"] for _, info in steps] == [0.0, 1.0, 1.0, 1.0, 1.0]
    assert [info["episode_cost"] for _, info in steps] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert not any(key.startswith("cost/") for _, info in steps for key in info)


def test_an_env_without_cost_gets_no_new_keys():
    env = make_env(EnvConfig(id="CartPole-v1"))
    _, info = env.reset(seed=0)
    assert info == {} and env.step(0)[4] == {}


class _CostOnlyInSteps(gym.Env):
    """An env whose reset info says nothing of cost: CostSignal starts at its first step's cost."""
    observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        return np.zeros(1, np.float32), {}

    def step(self, action):
        return np.zeros(1, np.float32), 0.0, False, False, {"cost": 0.5}


def test_a_cost_first_reported_in_a_step_is_summed_from_there():
    env = CostSignal(_CostOnlyInSteps())
    assert env.reset()[1] == {}
    assert env.step(0)[4] == {"cost": 0.5, "episode_cost": 0.5}
    assert env.step(0)[4]["episode_cost"] == 1.0
    assert env.reset()[1] == {"cost": 0.0, "episode_cost": 0.0}  # known from now on


@pytest.mark.parametrize("backend", ["sync", "async"])
@pytest.mark.parametrize("mode", [AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
def test_the_tracker_sees_the_episode_cost_of_a_vector_env(backend, mode):
    env = make_vector_env(EnvConfig(id=LANES, num_envs=2, backend=backend), autoreset_mode=mode)
    tracker, summed, episodes = EpisodeTracker(2), 0.0, []
    try:
        env.reset(seed=0)
        for _ in range(8):   # two episodes in each env, all in the fast lane
            _, reward, terminated, truncated, info = env.step(np.ones((2, 1), np.float32))
            done = terminated | truncated
            summed += step_costs(info, done).sum()
            episodes += tracker.step(reward, done, info)
            if mode == AutoresetMode.DISABLED and done.any():
                env.reset(options={"reset_mask": done})
    finally:
        env.close()
    assert len(episodes) == 4 and all(episode.metrics["cost"] == 4.0 for episode in episodes)
    assert (tracker.cost_total, tracker.cost_episodes, summed) == (16.0, 4, 16.0)


def test_action_repeat_sums_the_cost_of_its_steps():
    env = make_env(EnvConfig(id=LANES, action_repeat=3))
    steps = _episode(env, FAST)   # 4 stretches: a decision of 3, then the last stretch alone
    assert [(reward, info["cost"], info["episode_cost"]) for reward, info in steps[1:]] == [(7.5, 3.0, 3.0), (2.5, 1.0, 4.0)]


@pytest.mark.parametrize("budget, action, ends", [(0.0, FAST, [1.0]),                     # the first cost ends it
                                                  (0.6, MIDDLE, [0.25, 0.5, 0.75]),       # 0.75 > 0.6 at step 3
                                                  (4.0, FAST, [1.0, 2.0, 3.0, 4.0])])     # never over: the env ends it
def test_cost_termination_ends_the_episode_where_its_cost_exceeds_the_budget(budget, action, ends):
    steps = _episode(make_env(EnvConfig(id=LANES, cost_termination=budget)), action)
    assert [info["episode_cost"] for _, info in steps[1:]] == ends
    over = len(ends) < 4
    assert [info["cost_terminated"] for _, info in steps[1:]] == [False] * (len(ends) - 1) + [over]


def test_cost_termination_is_for_training_only():
    from drivelab.config import TrainConfig
    from drivelab.training.run.periodic_evaluation import eval_env_config

    trained = EnvConfig(id=LANES, cost_termination=0.0)
    assert trained.played().cost_termination is None
    assert trained.on("CartPole-v1").cost_termination is None
    assert eval_env_config(TrainConfig(env=trained)).cost_termination is None
    steps = _episode(make_env(trained.played()), FAST)
    assert len(steps) == 5 and "cost_terminated" not in steps[-1][1]


@pytest.mark.parametrize("budget", [-1.0, "soon", True, math.inf])
def test_a_bad_cost_termination_budget_is_one_line(budget):
    with pytest.raises(DrivelabError, match=r"^config field 'env.cost_termination' must be a cost budget >= 0"):
        EnvConfig(id=LANES, cost_termination=budget).validate()


# ---- cost terms


class _Scripted(gym.Env):
    """Plays back a list of step infos (the reset's info is the first)."""
    observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
    action_space = gym.spaces.Discrete(2)

    def __init__(self, infos):
        self.infos, self.t = infos, 0

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return np.zeros(1, np.float32), dict(self.infos[0])

    def step(self, action):
        self.t += 1
        return np.zeros(1, np.float32), 1.0, self.t == len(self.infos) - 1, False, dict(self.infos[self.t])


def _drive(**step):
    return {"cost": 0.0, "collided": False, "out_of_road": False, "on_solid_line": False, "on_broken_line": False,
            "speed": 5.0, **step}


def test_cost_terms_by_hand():
    infos = [_drive(), _drive(collided=True, cost=1.0), _drive(collided=True, on_solid_line=True),
             _drive(speed=12.0, on_broken_line=True), _drive(out_of_road=True, cost=1.0), _drive(out_of_road=True)]
    config = {"native": {"weight": 2.0}, "crash": {}, "out_of_road": {"weight": 3.0}, "solid_line": {"weight": 0.5},
              "broken_line": {}, "speeding": {"max_speed": 10.0}}
    env = CostSignal(_Scripted(infos), config)
    _, info = env.reset()
    assert info["cost"] == 0.0 and info["episode_cost"] == 0.0 and info["cost/crash"] == 0.0
    infos = [env.step(0)[4] for _ in range(5)]
    # native x2 + crash, crash + solid, speeding + broken, native x2 + out of road x3 (once: "so far" stays True)
    assert [info["cost"] for info in infos] == [3.0, 1.5, 2.0, 5.0, 0.0]
    sums = {key: value for key, value in infos[-1].items() if key.startswith("cost/")}
    assert sums == {"cost/native": 4.0, "cost/crash": 2.0, "cost/out_of_road": 3.0, "cost/solid_line": 0.5,
                    "cost/broken_line": 1.0, "cost/speeding": 1.0}
    assert infos[-1]["episode_cost"] == 11.5
    assert env.reset()[1]["cost/native"] == 0.0


def test_cost_term_sums_reach_the_episode_metrics():
    infos = [_drive(), _drive(collided=True), _drive(collided=True), _drive(speed=20.0)]
    env = CostSignal(_Scripted(infos), {"crash": {"weight": 2.0}, "speeding": {"max_speed": 10.0}})
    info = _episode(env, 0)[-1][1]
    assert (info["cost/crash"], info["cost/speeding"], info["episode_cost"]) == (4.0, 1.0, 5.0)


def near_miss(info, prev, distance=1.0):
    """A user's cost term (``test_costs:near_miss``)."""
    return float(info["gap"] < distance)


def ends_episode(info, prev):
    from drivelab.envs.rewards import TermResult

    return TermResult(1.0, terminate=True)


def negative(info, prev):
    return -1.0


def test_a_users_cost_term_sees_the_step_info():
    env = CostSignal(_Scripted([{"gap": 5.0}, {"gap": 0.5}, {"gap": 3.0}]), {"test_costs:near_miss": {"distance": 2.0}})
    steps = _episode(env, 0)
    assert [info["cost"] for _, info in steps] == [0.0, 1.0, 0.0]
    assert steps[-1][1]["cost/test_costs:near_miss"] == 1.0


@pytest.mark.parametrize("config, message", [
    ({"crashes": {}}, "env.cost: unknown cost term 'crashes'"),
    ({"crash": {"weight": -1.0}}, "env.cost.crash.weight must be >= 0"),
    ({"crash": {"weight": "heavy"}}, "env.cost.crash.weight must be a number"),
    ({"speeding": {}}, "env.cost.speeding: missing 1 required positional argument: 'max_speed'"),
    ({"crash": {"scale": 2}}, "env.cost.crash: got an unexpected keyword argument 'scale'"),
    ({}, "env.cost must map cost terms"),
])
def test_bad_cost_configs_are_one_line(config, message):
    with pytest.raises(DrivelabError, match="^" + re.escape(message)):
        EnvConfig(id=LANES, cost=config).validate()


@pytest.mark.parametrize("term, message", [("test_costs:ends_episode", "ends the episode"),
                                           ("test_costs:negative", "costs must be finite and >= 0"),
                                           ("crash", "cost term 'crash' needs info['collided']")])
def test_a_cost_term_that_ends_episodes_goes_negative_or_lacks_its_info_is_refused_at_its_step(term, message):
    env = CostSignal(_Scripted([{}, {}, {}]), {term: {}})
    env.reset()
    with pytest.raises(DrivelabError, match=message.replace("[", r"\[")):
        env.step(0)


def test_the_cost_reward_term_is_the_reward_shaping_baseline():
    """ThreeLanes' middle lane pays 2 and costs 0.25 per stretch: with the cost priced at 4
    (outside the window (2/3, 3) where the middle lane is best), it pays 1, less than the shoulder."""
    env = make_env(EnvConfig(id=LANES, reward={"native": {}, "cost": {"weight": 4.0}}))
    steps = _episode(env, MIDDLE)
    assert [reward for reward, _ in steps[1:]] == [1.0] * 4
    assert steps[-1][1]["reward/cost"] == -4.0 and steps[-1][1]["episode_cost"] == 1.0
    # the reward term sees the cost after env.cost's terms
    env = make_env(EnvConfig(id=LANES, cost={"native": {"weight": 2.0}}, reward={"native": {}, "cost": {}}))
    assert [reward for reward, _ in _episode(env, MIDDLE)[1:]] == [1.5] * 4


def test_the_cost_reward_term_needs_an_env_with_a_cost():
    env = make_env(EnvConfig(id="CartPole-v1", reward={"native": {}, "cost": {}}))
    env.reset(seed=0)
    with pytest.raises(DrivelabError, match=r"reward term 'cost' needs info\['cost'\]"):
        env.step(0)


# ---- MetaDrive's cost_to_reward (metadrive#844)


@pytest.mark.parametrize("kwargs", [{"cost_to_reward": True}, {"config": {"cost_to_reward": False}}])
def test_cost_to_reward_is_refused_in_one_line(kwargs):
    with pytest.raises(DrivelabError, match=r"^config field 'env\.kwargs': MetaDrive config 'cost_to_reward' does "
                                            r"nothing .*metadrive#844.*cost: \{weight: W\}"):
        EnvConfig(id="SafeMetaDrive-10env-v0", kwargs=kwargs).validate()
    from drivelab.envs.metadrive import MetaDriveGym

    with pytest.raises(DrivelabError, match="^MetaDrive config 'cost_to_reward'"):
        MetaDriveGym(safe=True, **kwargs)   # refused before an engine starts


def test_cost_to_reward_on_the_command_line_exits_2_and_writes_nothing(tmp_path, capsys):
    from drivelab.cli import main

    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", "ppo", "--env", "SafeMetaDrive-10env-v0", "--steps", "512", "--no-progress",
              "--run-dir", str(run_dir), "--env.kwargs.cost_to_reward", "true"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_info.value.code == 2 and len(err) == 1 and "metadrive#844" in err[0]
    assert not run_dir.exists()


def test_a_negative_cost_weight_on_the_command_line_exits_2(tmp_path, capsys):
    from drivelab.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", "ppo", "--env", LANES, "--steps", "512", "--no-progress",
              "--run-dir", str(tmp_path / "run"), "--env.cost", "{crash: {weight: -1}}"])
    assert exit_info.value.code == 2 and "env.cost.crash.weight must be >= 0" in capsys.readouterr().err


# ---- rolled-over and stalled cars (metadrive#793)


def _guard_run(guard, steps):
    """The guard's verdicts over ``steps`` of (roll_deg, pitch_deg, speed, route_completion)."""
    return [guard.update(math.radians(roll), math.radians(pitch), speed, rc) for roll, pitch, speed, rc in steps]


def test_stuck_guard_on_synthetic_drives():
    guard = StuckGuard(step_seconds=0.1)
    assert _guard_run(guard, [(5.0, -3.0, 8.0, k / 1000) for k in range(600)]) == [None] * 600   # upright, driving
    guard.reset()
    rolled = _guard_run(guard, [(180.0, 0.0, 0.0, 0.2)] * 10)          # on its roof: the 10th step is 1 s
    assert rolled == [None] * 9 + ["rolled_over"]
    guard.reset()
    assert _guard_run(guard, [(0.0, 70.0, 3.0, 0.2)] * 10)[-1] == "rolled_over"   # nose up counts as tilt too
    guard.reset()
    assert _guard_run(guard, [(0.0, 50.0, 3.0, 0.2)] * 50) == [None] * 50          # a steep ramp does not
    guard.reset()
    parked = _guard_run(guard, [(0.0, 0.0, 0.0, 0.3)] * 300)            # parked for 30 s
    assert parked == [None] * 299 + ["stuck"]
    guard.reset()
    waiting = [(0.0, 0.0, 0.05, 0.3)] * 290 + [(0.0, 0.0, 5.0, 0.3 + k / 1000) for k in range(100)]
    assert _guard_run(guard, waiting) == [None] * 390                   # waited 29 s, then drove on
    guard.reset()
    creeping = [(0.0, 0.0, 0.05, 0.3 + k * 5e-5) for k in range(600)]   # slow, but getting somewhere
    assert _guard_run(guard, creeping) == [None] * 600


def test_stuck_guard_ends_a_car_pinned_in_a_collision():
    """A car pressed against a cone jitters around the stall speed, so only the contact test ends it:
    in a collision on half of the last 10 s (100 steps of 0.1 s)."""
    guard = StuckGuard(step_seconds=0.1)
    jitter = [guard.update(0.0, 0.0, 0.3 if k % 2 else 0.05, 0.4, collided=True) for k in range(100)]
    assert jitter == [None] * 49 + ["stuck"] * 51                       # the 50th contact in the window
    guard.reset()
    bumping = [guard.update(0.0, 0.0, 0.4, 0.2, collided=k % 3 == 0) for k in range(300)]   # a third in contact
    assert bumping == [None] * 300
    guard.reset()
    scrape = [guard.update(0.0, 0.0, 6.0, 0.2 + k / 1000, collided=k < 40) for k in range(300)]  # 4 s, then away
    assert scrape == [None] * 300
    guard.reset()
    # contacts that leave the window no longer count: 49 in contact, 51 clear, then 49 more
    steps = [True] * 49 + [False] * 51 + [True] * 49
    assert [guard.update(0.0, 0.0, 1.0, 0.3, collided=c) for c in steps] == [None] * 149


def test_stuck_guard_counts_simulated_seconds():
    guard = StuckGuard(step_seconds=0.2)   # simulator_repeat 2: 0.2 s per env step
    assert _guard_run(guard, [(180.0, 0.0, 0.0, 0.0)] * 5)[-1] == "rolled_over"
    guard.reset()
    assert _guard_run(guard, [(0.0, 0.0, 0.0, 0.0)] * 150)[-2:] == [None, "stuck"]


def test_a_rolled_over_car_ends_its_safe_metadrive_episode():
    """metadrive#793, the probe: a car put on its roof stays there, costs nothing and would run to
    the step limit; the guard ends the episode after 1 s, as truncated and not as a timeout."""
    env = make_env(EnvConfig(id="SafeMetaDrive-10env-v0"))
    try:
        _, info = env.reset(seed=0)
        assert info["rolled_over"] is False and info["stuck"] is False and info["episode_cost"] == 0.0
        agent = env.unwrapped.metadrive.agent
        agent.set_roll(180)
        agent.set_position(agent.position, height=1.5)
        for step in range(1, 13):
            _, _, terminated, truncated, info = env.step(np.array([0.0, 1.0], np.float32))
            if terminated or truncated:
                break
        assert (truncated, terminated, step) == (True, False, 10)
        assert info["rolled_over"] and not info["stuck"] and not info["timeout"]
    finally:
        env.close()
