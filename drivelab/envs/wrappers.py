"""Action adapters for driving environments whose action is MetaDrive-style [steering, throttle],
an action repeat for any env, and a replay of failed scenarios for training on MetaDrive."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np

from drivelab.errors import DrivelabError


def parse_grid(text: str, field: str = "env.action_grid") -> tuple[int, int]:
    """'3x5' -> (3, 5): steering bins x throttle bins."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
    if not match or int(match[1]) < 1 or int(match[2]) < 1:
        raise DrivelabError(f"config field '{field}': expected 'NxM' (steering bins x throttle bins), got {text!r}")
    return int(match[1]), int(match[2])


def _levels(bins: int, magnitude: float, single: float) -> np.ndarray:
    """`bins` evenly spaced values from +magnitude down to -magnitude (one bin -> `single`)."""
    if bins == 1:
        return np.array([single])
    return np.linspace(magnitude, -magnitude, bins)


def grid_table(steering_bins: int, throttle_bins: int, max_steering: float = 0.6,
               max_throttle: float = 1.0) -> np.ndarray:
    """(N * M, 2) float32: row i is the [steering, throttle] of discrete action i, row-major over
    (throttle, steering) (see :class:`DiscreteActionGrid`)."""
    steering = _levels(steering_bins, max_steering, 0.0)
    throttle = _levels(throttle_bins, max_throttle, max_throttle)
    return np.array([[s, t] for t in throttle for s in steering], dtype=np.float32)


class DiscreteActionGrid(gym.ActionWrapper):
    """N steering x M throttle discrete actions over a continuous ``[steering, throttle]`` action.

    Index ``i`` maps to ``throttle_levels[i // N]`` and ``steering_levels[i % N]``, with throttle
    ordered from full forward to full brake and steering from full left (+) to full right (-).
    The default 3x3 grid therefore numbers its actions 0 = full throttle and left, 1 = full
    throttle and straight, ..., 8 = full brake and right, and emits each in the order MetaDrive
    expects: ``[steering, throttle]`` (with throttle first, a "full throttle" action would steer
    hard left and never accelerate).

    A single steering bin means "always straight"; a single throttle bin means "fixed throttle
    ``max_throttle``".
    """

    def __init__(self, env: gym.Env, steering_bins: int = 3, throttle_bins: int = 3,
                 max_steering: float = 0.6, max_throttle: float = 1.0):
        super().__init__(env)
        space = env.action_space
        if not (isinstance(space, gym.spaces.Box) and space.shape == (2,)):
            raise DrivelabError(
                f"env.action_grid needs a Box(2,) [steering, throttle] action space; {env.spec.id if env.spec else env} has {space}"
            )
        self.table = grid_table(steering_bins, throttle_bins, max_steering, max_throttle)
        self.action_space = gym.spaces.Discrete(len(self.table))

    def action(self, action) -> np.ndarray:
        return self.table[int(action)]


class FixedThrottle(gym.ActionWrapper):
    """Steering-only control at a constant throttle: the agent's action is a 1-D Box [steering]
    in [-1, 1]; the env receives [steering, throttle]."""

    def __init__(self, env: gym.Env, throttle: float = 0.3):
        super().__init__(env)
        space = env.action_space
        if not (isinstance(space, gym.spaces.Box) and space.shape == (2,)):
            raise DrivelabError(f"env.fixed_throttle needs a Box(2,) [steering, throttle] action space, got {space}")
        if not -1.0 <= throttle <= 1.0:
            raise DrivelabError(f"env.fixed_throttle must be in [-1, 1], got {throttle}")
        self.throttle = float(throttle)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def action(self, action) -> np.ndarray:
        return np.array([float(np.asarray(action).reshape(-1)[0]), self.throttle], np.float32)


class ActionRepeat(gym.Wrapper):
    """Each action is held for ``repeat`` env steps (frame skip; Mnih et al. 2015 hold Atari's
    actions for 4 frames): the rewards of those steps are summed, as are their costs
    (``info["cost"]``, :mod:`drivelab.envs.costs`); the observation and the rest of the info are the
    last step's, and an episode that ends (terminated or truncated) inside the repeat ends there.

    The env itself is unchanged (its traffic, physics and horizon still run at its own step), only
    the agent decides less often: on MetaDrive, whose step is 0.1 s, ``repeat: 2`` decides every
    0.2 s, and a learner that costs a fixed time per decision gets twice the driving per update.
    """

    def __init__(self, env: gym.Env, repeat: int):
        super().__init__(env)
        if repeat < 1:
            raise DrivelabError(f"config field 'env.action_repeat' must be >= 1, got {repeat}")
        self.repeat = int(repeat)
        # Videos see one frame per decision: their recorder slows its frame rate by this factor.
        self.metadata = {**env.metadata, "action_repeat": self.repeat}

    def step(self, action):
        total, cost = 0.0, 0.0
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            cost += float(info.get("cost", 0.0))
            if terminated or truncated:
                break
        if "cost" in info:  # the decision's cost, summed like its reward (info["episode_cost"] is already a running sum)
            info = {**info, "cost": cost}
        return obs, total, terminated, truncated, info


class ScenarioReplay(gym.Wrapper):
    """Start some training episodes on scenarios the agent failed, instead of a fresh draw.

    After Prioritized Level Replay (Jiang, Grefenstette & Rocktaschel 2021): with probability
    ``replay_prob`` a reset replays a scenario whose last episode in this env ended without
    reaching the destination (crash, off road or the step limit), else the env draws one as usual.
    PLR scores levels by the learner's value error; here the score is the driving outcome itself,
    which needs no critic in the worker. Among the failed scenarios, one is chosen with probability
    proportional to its staleness (episodes since it was last played, PLR's P_C): the oldest
    failures are tried again first, and one that now succeeds leaves the table, so the replays
    follow what the current policy still cannot drive. ``info["replayed"]`` says whether the
    episode is a replay (logged as ``episode/replay_rate``).

    The env must report ``info["scenario"]`` and ``info["success"]`` and take
    ``reset(options={"scenario": k})`` (drivelab's MetaDrive adapter does). A reset with a seed
    reseeds the replay draw, so a run stays reproducible for its seed. The table lives in the env's
    process: it starts empty in a new run, after a resume and after a worker restart.
    """

    def __init__(self, env: gym.Env, replay_prob: float):
        super().__init__(env)
        if not 0.0 <= replay_prob < 1.0:
            raise DrivelabError(f"config field 'env.scenario_replay' must be in [0, 1), got {replay_prob}")
        self.replay_prob = float(replay_prob)
        self.failed: dict[int, int] = {}  # scenario -> this env's episode count when it last failed
        self.episodes = 0
        self.rng = np.random.default_rng()
        self._scenario, self._replayed = -1, False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        options = dict(options or {})
        self._replayed = "scenario" not in options and bool(self.failed) and self.rng.random() < self.replay_prob
        if self._replayed:
            scenarios = np.fromiter(self.failed.keys(), np.int64, len(self.failed))
            staleness = self.episodes + 1 - np.fromiter(self.failed.values(), np.float64, len(self.failed))
            options["scenario"] = int(self.rng.choice(scenarios, p=staleness / staleness.sum()))
        obs, info = self.env.reset(seed=seed, options=options)
        self._scenario = int(info["scenario"])
        info["replayed"] = self._replayed
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            self.episodes += 1
            if info["success"]:
                self.failed.pop(self._scenario, None)
            else:
                self.failed[self._scenario] = self.episodes
        info["replayed"] = self._replayed
        return obs, reward, terminated, truncated, info


class CruiseControl(gym.Wrapper):
    """Steering-only control at a target speed: the agent's action is a 1-D Box [steering] and a
    proportional controller sets the throttle, clip(gain * (target_speed - speed), -1, 1), from the
    ``info["speed"]`` (m/s) of the previous step.

    A fixed throttle on MetaDrive is a constant engine force, so the car speeds up until it cannot
    take a curve; a Donkey car's throttle behaves more like a speed setting.
    """

    def __init__(self, env: gym.Env, target_speed: float = 8.0, gain: float = 0.5):
        super().__init__(env)
        space = env.action_space
        if not (isinstance(space, gym.spaces.Box) and space.shape == (2,)):
            raise DrivelabError(f"target_speed needs a Box(2,) [steering, throttle] action space, got {space}")
        if target_speed <= 0:
            raise DrivelabError(f"target_speed must be > 0 m/s, got {target_speed}")
        self.target_speed, self.gain = float(target_speed), float(gain)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self._speed = 0.0

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._speed = float(info.get("speed", 0.0))
        return obs, info

    def step(self, action):
        throttle = float(np.clip(self.gain * (self.target_speed - self._speed), -1.0, 1.0))
        obs, reward, terminated, truncated, info = self.env.step(
            np.array([float(np.asarray(action).reshape(-1)[0]), throttle], np.float32))
        self._speed = float(info["speed"])
        return obs, reward, terminated, truncated, info


def wheel_velocities(steering: float | np.ndarray, throttle: float | np.ndarray, gain: float = 1.0) -> np.ndarray:
    """(steering, throttle) -> (left, right) wheel velocities of a differential-drive robot.

    Forward speed is the wheels' mean and turning their difference: left = throttle - gain *
    steering, right = throttle + gain * steering (steering > 0 turns left: the right wheel runs
    faster). When a wheel would exceed [-1, 1], both are scaled down together, so the ratio, and
    therefore the turning radius, is kept.
    """
    left = np.asarray(throttle, np.float64) - gain * np.asarray(steering, np.float64)
    right = np.asarray(throttle, np.float64) + gain * np.asarray(steering, np.float64)
    peak = np.maximum(1.0, np.maximum(np.abs(left), np.abs(right)))
    return np.stack([left / peak, right / peak], axis=-1).astype(np.float32)


class DifferentialDrive(gym.ActionWrapper):
    """Expose [steering, throttle] in [-1, 1]^2 for an env driven by (left, right) wheel
    velocities, such as Duckietown."""

    def __init__(self, env: gym.Env, gain: float = 1.0):
        super().__init__(env)
        self.gain = gain
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def action(self, action) -> np.ndarray:
        steering, throttle = np.asarray(action, np.float64).reshape(2)
        return wheel_velocities(steering, throttle, self.gain)
