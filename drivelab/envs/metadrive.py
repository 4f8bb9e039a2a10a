"""MetaDrive behind the Gymnasium API, offline and headless.

What this adapter adds to ``metadrive.MetaDriveEnv``:

* **Offline.** MetaDrive downloads a 3D asset pack into its own site-packages folder the first
  time an engine starts. Physics, lidar/state observations and the pygame top-down renderer use
  none of it, so drivelab turns the download off (nothing is written into site-packages) and
  raises a one-line error if something that needs the pack is asked for (the 3D window, camera
  observations) while it is missing.
* **Gymnasium seeding.** ``reset(seed=k)`` selects scenario ``start_seed + k % num_scenarios``,
  so equal seeds give equal scenarios (evaluation on seeds 0..99 visits 100 distinct scenarios);
  ``reset()`` draws the scenario from the env's own seeded RNG. MetaDrive alone draws it from an
  unseeded global RNG, which makes runs irreproducible.
* **A step limit.** MetaDrive 0.4.3 has no horizon by default, so a car that stands still never
  ends its episode. drivelab sets ``horizon=1000`` (MetaDrive's later default); reaching it is
  reported as ``truncated``, never ``terminated``.
* **A lean, stable ``info``** (MetaDrive's full dict costs time in vector envs at every step):
  ``success``, ``crash`` and ``out_of_road`` (did it happen in this episode so far), ``timeout``
  (the step limit ended it before the destination),
  ``route_completion`` (0..1), ``cost``, ``speed`` (m/s) and ``scenario``, plus the lane geometry
  that driving rewards and metrics are written against (:func:`lane_geometry`): ``cte``,
  ``heading_error``, ``speed_along_lane``, ``collided``, ``on_solid_line`` and
  ``on_broken_line`` (this step) and ``native_reward``; with state observations also ``ahead_m``,
  the nearest lidar return within 10 degrees of the heading (:func:`lidar_ahead`, read by the
  ``headway`` reward term). Pass ``full_info=True`` for MetaDrive's own dict as well.
* **Cars that can go nowhere.** On the ``SafeMetaDrive-*`` ids (where crashes do not end the
  episode) a car that rolled over, stalled or stays pinned in a collision ends its episode as
  truncated, with ``info["rolled_over"]`` or ``info["stuck"]`` (:class:`StuckGuard`,
  ``stuck_guard=``).
* **No** ``cost_to_reward``: SafeMetaDrive 0.4.3 accepts it and ignores it (metadrive#844);
  drivelab refuses it and points to its ``cost`` reward term (:mod:`drivelab.envs.costs`).
* **Observations**: ``observation="state"`` (259-d lidar/state vector) or ``"topdown"``
  (MetaDrive's multi-channel bird's-eye raster, uint8 (84, 84, 5): road, lane lines, navigation,
  past positions; drawn with pygame, no 3D assets).

Only one MetaDrive engine can live in a process: build vector envs with
:func:`drivelab.envs.make_vector_env`, which puts each one in its own subprocess.
"""

from __future__ import annotations

import logging
import math
import os
from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np

from drivelab.envs.costs import refuse_cost_to_reward
from drivelab.errors import DrivelabError

# drivelab's defaults on top of MetaDrive's: headless, quiet, and a step limit.
DEFAULTS: dict[str, Any] = {"use_render": False, "horizon": 1000, "log_level": logging.ERROR}


# MetaDrive's own default: an env step is decision_repeat physics steps of 0.02 s (0.1 s).
DECISION_REPEAT = 5

# The cone info["ahead_m"] looks along: +-10 degrees of the heading, about a lane either side at 17 m.
AHEAD_DEGREES = 10.0


def lidar_returns(obs: np.ndarray, lidar: dict) -> np.ndarray:
    """(num_lasers,) lidar returns in metres (the range where nothing is hit): MetaDrive's state
    observation ends with them, each a distance over the range; laser 0 points along the heading,
    the others follow round."""
    return np.asarray(obs[-int(lidar["num_lasers"]):]) * lidar["distance"]


def lidar_ahead(obs: np.ndarray, lidar: dict) -> float:
    """The nearest lidar return (m) within :data:`AHEAD_DEGREES` of the car's heading."""
    returns = lidar_returns(obs, lidar)
    k = int(len(returns) * AHEAD_DEGREES / 360)
    return float(min(returns[:k + 1].min(), returns[len(returns) - k:].min(initial=lidar["distance"])))


def held_in_simulator(kwargs: dict[str, Any], repeat: int) -> dict[str, Any]:
    """MetaDrive kwargs whose env step holds the action ``repeat`` times as long: ``repeat`` x
    ``decision_repeat`` physics steps, and a horizon of ``horizon // repeat`` env steps (the same
    time limit). Faster than repeating the step (the traffic decides, and the observation, reward
    and crash / line checks are computed, once instead of ``repeat`` times), but not the same env:
    the traffic decides every ``repeat`` x 0.1 s and per-step reward terms (MetaDrive's
    ``speed_reward``, drivelab's ``idle``) count once per decision."""
    given = {**DEFAULTS, "decision_repeat": DECISION_REPEAT, **(kwargs.get("config") or {}), **kwargs}
    step, horizon = given["decision_repeat"], given["horizon"]
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (step, horizon or 1)):
        return dict(kwargs)  # not integers: left for MetaDriveGym's one-line error on the config
    return {**kwargs, "decision_repeat": step * repeat, "horizon": None if horizon is None else max(1, horizon // repeat)}


def asset_dir() -> str:
    from metadrive.engine.asset_loader import AssetLoader

    return str(AssetLoader.asset_path)


def assets_installed() -> bool:
    return os.path.exists(os.path.join(asset_dir(), "version.txt"))


def _needs_3d_assets(config: dict) -> str | None:
    """Name of the requested feature that needs the 3D asset pack, or None."""
    if config.get("use_render"):
        return "the 3D window (use_render=True)"
    if config.get("image_observation"):
        return "camera observations (image_observation=True)"
    if config.get("render_pipeline"):
        return "the render pipeline (render_pipeline=True)"
    for name, sensor in (config.get("sensors") or {}).items():
        cls = sensor[0] if isinstance(sensor, (tuple, list)) and sensor else sensor
        if "camera" in str(getattr(cls, "__name__", cls)).lower():
            return f"the camera sensor '{name}'"
    return None


def lane_geometry(agent) -> dict[str, float]:
    """Where the car is relative to its current lane, from MetaDrive's lane object.

    Returns:
        cte: signed cross-track error in metres, the distance from the lane centre line,
            positive when the car is left of it (MetaDrive's lane frame has its lateral axis
            pointing right, so this is minus MetaDrive's lateral coordinate);
        heading_error: car heading minus lane heading at the car's position, in radians wrapped
            to [-pi, pi), positive when the car points left of the lane direction;
        speed_along_lane: speed * cos(heading_error), m/s (negative when driving backwards).
    """
    lane = agent.lane
    longitudinal, lateral = lane.local_coordinates(agent.position)
    heading_error = agent.heading_theta - lane.heading_theta_at(longitudinal)
    heading_error = (heading_error + math.pi) % (2 * math.pi) - math.pi
    return {"cte": float(-lateral), "heading_error": float(heading_error),
            "speed_along_lane": float(agent.speed * math.cos(heading_error))}


def _disable_asset_download() -> None:
    """Stop MetaDrive's engine from fetching its 3D asset pack from the internet on start-up.

    ``BaseEngine.__init__`` calls ``try_pull_asset``, which downloads and unpacks a zip into
    site-packages whenever the pack is missing or outdated. That fails offline (and writes into
    the installation). Headless physics does not read the pack, and :class:`MetaDriveGym`
    refuses, with a clear error, the configurations that would.
    """
    from metadrive.engine.base_engine import BaseEngine

    BaseEngine.try_pull_asset = staticmethod(lambda: None)


def _steps(seconds: float, step_seconds: float) -> int:
    """The number of env steps of ``step_seconds`` that make ``seconds`` (at least 1)."""
    return max(1, math.ceil(round(seconds / step_seconds, 6)))


class StuckGuard:
    """Ends an episode that can no longer go anywhere: a car rolled over, or a car that stalled.

    MetaDrive 0.4.3 never ends an episode whose car lies on its roof (metadrive#793): such a car
    costs nothing, crashes into nothing and runs until the step limit, up to 100 s of useless steps
    in a batch. :meth:`update` reads the car's state once per env step and answers

    * ``"rolled_over"``: tilted more than ``max_tilt_deg`` from upright for ``rollover_seconds``;
      the tilt of the car's up axis is arccos(cos(roll) cos(pitch)) (the heading does not move it);
    * ``"stuck"``: slower than ``stall_speed`` (m/s) with less than ``min_progress`` route
      completion gained for ``stall_seconds`` (a car waiting at a jam for a few seconds is fine),
      or *pinned*: in a collision on at least ``pinned_share`` of the last ``pinned_seconds``.
      A car pressed against a traffic cone, or bumping a broken-down car, jitters at 0.1-0.5 m/s,
      so the stall test alone never fires, while SafeMetaDrive charges a cost for every step in
      contact: without this test such a car runs to the step limit, paying on most steps;
    * ``None`` otherwise.

    ``step_seconds`` is the simulated time of one env step (MetaDrive: decision_repeat x 0.02 s),
    so the windows are in simulated seconds under ``simulator_repeat`` too. Pure Python.
    """

    def __init__(self, step_seconds: float, max_tilt_deg: float = 60.0, rollover_seconds: float = 1.0,
                 stall_speed: float = 0.1, stall_seconds: float = 30.0, min_progress: float = 1e-4,
                 pinned_seconds: float = 10.0, pinned_share: float = 0.5):
        if not step_seconds > 0:
            raise DrivelabError(f"StuckGuard step_seconds must be > 0, got {step_seconds}")
        self.max_tilt = math.radians(max_tilt_deg)
        self.rollover_steps = _steps(rollover_seconds, step_seconds)
        self.stall_steps = _steps(stall_seconds, step_seconds)
        self.stall_speed, self.min_progress = stall_speed, min_progress
        self.pinned_steps = _steps(pinned_seconds, step_seconds)
        self.pinned_contacts = math.ceil(pinned_share * self.pinned_steps)
        self.reset()

    def reset(self) -> None:
        """A new episode: no tilted, stalled or colliding steps yet."""
        self.tilted, self.stalled = 0, 0
        self.anchor: float | None = None  # route completion where the current stall began
        # the last pinned_steps collision flags and how many of them are set
        self.recent: deque[bool] = deque(maxlen=self.pinned_steps)
        self.contacts = 0

    def update(self, roll: float, pitch: float, speed: float, route_completion: float,
               collided: bool = False) -> str | None:
        """One env step (angles in radians, speed in m/s, ``collided``: in contact with a vehicle,
        an object or a building this step): "rolled_over", "stuck" or None."""
        if len(self.recent) == self.pinned_steps:
            self.contacts -= self.recent[0]   # the oldest flag leaves the window
        self.recent.append(collided)
        self.contacts += collided
        tilt = math.acos(max(-1.0, min(1.0, math.cos(roll) * math.cos(pitch))))
        self.tilted = self.tilted + 1 if tilt > self.max_tilt else 0
        if speed >= self.stall_speed:
            self.anchor, self.stalled = None, 0
        elif self.anchor is None or route_completion - self.anchor >= self.min_progress:
            self.anchor, self.stalled = route_completion, 1  # a slow step without progress so far: a stall starts
        else:
            self.stalled += 1
        if self.tilted >= self.rollover_steps:
            return "rolled_over"
        return "stuck" if self.stalled >= self.stall_steps or self.contacts >= self.pinned_contacts else None


class MetaDriveGym(gym.Env):
    """A single-agent MetaDrive (or SafeMetaDrive) environment; see the module docstring.

    Args:
        config: MetaDrive config dict, as in ``gym.make("MetaDrive-validation-v0", config={...})``.
        render_mode: ``"rgb_array"`` renders MetaDrive's pygame top-down view (no 3D assets needed).
        safe: use ``SafeMetaDriveEnv`` (the registered ``SafeMetaDrive-*`` ids set this).
        full_info: also return MetaDrive's full info dict.
        render_size: (width, height) of ``render()`` images.
        stuck_guard: end an episode whose car rolled over or stalled as truncated
            (:class:`StuckGuard`, ``info["rolled_over"]`` / ``info["stuck"]``); None: on for ``safe``
            only, so the MetaDrive-* numbers stay as published.
        **overrides: MetaDrive config keys given directly, e.g. ``num_scenarios=10``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, config: dict | None = None, render_mode: str | None = None, safe: bool = False,
                 full_info: bool = False, render_size: tuple[int, int] = (400, 400), observation: str = "state",
                 stuck_guard: bool | None = None, **overrides: Any):
        # pygame draws the top-down views; headless machines have no display or sound card.
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
        refuse_cost_to_reward({**(config or {}), **overrides})
        merged = {**DEFAULTS, **(config or {}), **overrides}
        for key, low in (("horizon", 1), ("num_scenarios", 1), ("start_seed", 0)):
            value = merged.get(key)
            if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < low):
                raise DrivelabError(f"MetaDrive config '{key}' must be an integer >= {low}, got {value!r}")
        if observation == "topdown":
            merged = {"norm_pixel": False, **merged}  # uint8 images: 4x smaller, the CNN scales them
        elif observation != "state":
            raise DrivelabError(f"MetaDrive observation must be 'state' or 'topdown', got {observation!r}")
        needs_assets = _needs_3d_assets(merged)
        if needs_assets and not assets_installed():
            raise DrivelabError(
                f"MetaDrive's {needs_assets} needs its 3D asset pack, which is not installed in {asset_dir()}: "
                "on a machine with internet run `python -m metadrive.pull_asset`; state observations and "
                "render_mode='rgb_array' (top-down) need no assets"
            )
        if render_mode not in (None, "rgb_array"):
            raise DrivelabError(f"MetaDrive render_mode must be None or 'rgb_array' (top-down), got {render_mode!r}")
        _disable_asset_download()
        from metadrive.envs import MetaDriveEnv, SafeMetaDriveEnv
        from metadrive.envs.top_down_env import TopDownMetaDrive

        if observation == "topdown" and safe:
            raise DrivelabError("MetaDrive top-down observations are available for MetaDriveEnv, not SafeMetaDriveEnv")
        env_cls = TopDownMetaDrive if observation == "topdown" else SafeMetaDriveEnv if safe else MetaDriveEnv
        try:
            self._env = env_cls(merged)
        except (KeyError, ValueError, AssertionError, TypeError) as exc:
            raise DrivelabError(f"MetaDrive rejected its config: {exc}") from None
        self.render_mode = render_mode
        self.render_size = tuple(render_size)
        self.full_info = full_info
        self.start_seed = int(self._env.config["start_seed"])
        self.num_scenarios = int(self._env.config["num_scenarios"])
        self.observation_space = self._env.observation_space
        self.action_space = self._env.action_space
        self._crashed = False
        self._left_road = False
        config = self._env.config
        lidar = config["vehicle_config"]["lidar"]
        self._lidar = lidar if observation == "state" and lidar["num_lasers"] > 0 else None   # for ahead_m
        self._guard = StuckGuard(config["decision_repeat"] * config["physics_world_step_size"]) \
            if (safe if stuck_guard is None else stuck_guard) else None

    @property
    def metadrive(self):
        """The wrapped ``metadrive`` environment (for its agent, lanes and engine)."""
        return self._env

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if options and "scenario" in options:
            scenario = int(options["scenario"])
        elif seed is not None:
            scenario = self.start_seed + seed % self.num_scenarios
        else:
            scenario = self.start_seed + int(self.np_random.integers(self.num_scenarios))
        obs, info = self._env.reset(seed=scenario)
        self._crashed = False
        self._left_road = False
        self._abs_cte_sum, self._steps = 0.0, 0
        lean = self._info(info, scenario)
        if self._guard is not None:
            self._guard.reset()
            lean.update(stuck=False, rolled_over=False)
        return obs, lean

    def step(self, action):
        obs, reward, terminated, truncated, info = self._env.step(action)
        self._steps += 1
        lean = self._info(info, int(self._env.current_seed), reward)
        if self._lidar is not None:
            lean["ahead_m"] = lidar_ahead(obs, self._lidar)
        terminated, truncated = bool(terminated), bool(truncated)
        if self._guard is not None:
            agent = self._env.agent
            verdict = None if terminated or truncated else \
                self._guard.update(agent.roll, agent.pitch, lean["speed"], lean["route_completion"], lean["collided"])
            lean.update(stuck=verdict == "stuck", rolled_over=verdict == "rolled_over")
            if verdict is not None:  # the car can go nowhere: end the episode, not as a timeout
                truncated, lean["timeout"] = True, False
        return obs, float(reward), terminated, truncated, lean

    def _info(self, info: dict, scenario: int, reward: float = 0.0) -> dict:
        collided = bool(info.get("crash", False))
        self._crashed |= collided
        self._left_road |= bool(info.get("out_of_road", False))
        geometry = lane_geometry(self._env.agent)
        if self._steps:
            self._abs_cte_sum += abs(geometry["cte"])
        lean = {
            "success": bool(info.get("arrive_dest", False)),
            "crash": self._crashed,
            "out_of_road": self._left_road,
            # the step limit ended the episode short of the destination: a car that stalled
            "timeout": bool(info.get("max_step", False)) and not info.get("arrive_dest", False),
            "route_completion": float(info.get("route_completion", 0.0)),
            "cost": float(info.get("cost", 0.0)),
            "speed": float(info.get("velocity", 0.0)),  # m/s
            "scenario": scenario,
            "collided": collided,
            "on_solid_line": bool(self._env.agent.on_white_continuous_line or self._env.agent.on_yellow_continuous_line),
            "on_broken_line": bool(self._env.agent.on_broken_line),
            "native_reward": float(reward),
            **geometry,
            "mean_abs_cte": self._abs_cte_sum / max(self._steps, 1),  # over this episode's steps so far
        }
        if self.full_info:
            lean["metadrive"] = info
        return lean

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        frame = self._env.render(mode="topdown", window=False, screen_size=self.render_size,
                                 target_agent_heading_up=True)
        return np.asarray(frame, dtype=np.uint8)

    def close(self) -> None:
        self._env.close()
