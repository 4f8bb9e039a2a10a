"""MetaDrive's multi-agent scenes: every car on the road is a learning agent.

Six scenes (MetaDrive's MARL benchmark, the one CoPO reports on), offline and headless like every
MetaDrive env here, one scene per process:

==============  =================================  ==============  ============
scene           MetaDrive class                    agents (def.)   drivelab id
==============  =================================  ==============  ============
Intersection    ``MultiAgentIntersectionEnv``      30              ``MultiAgentIntersection-v0``
Roundabout      ``MultiAgentRoundaboutEnv``        40              ``MultiAgentRoundabout-v0``
Tollgate        ``MultiAgentTollgateEnv``          40              ``MultiAgentTollgate-v0``
Bottleneck      ``MultiAgentBottleneckEnv``        20              ``MultiAgentBottleneck-v0``
ParkingLot      ``MultiAgentParkingLotEnv``        10              ``MultiAgentParkingLot-v0``
PGMap           ``MultiAgentMetaDrive``            15              ``MultiAgentPGMap-v0``
==============  =================================  ==============  ============

Cars arrive, crash, leave the road and respawn during one scene episode, so the set of agents
changes every step (the reason fixed-team MARL frameworks cannot run these scenes unchanged,
metadrive#319). Two views of a scene:

* :class:`MultiAgentDrive`, a PettingZoo ``ParallelEnv``: agents ``agent0, agent1, ...`` appear
  (a respawned car is a new agent, never a revived one) and leave once terminated (arrived,
  crashed, left the road) or truncated (its own step limit, MetaDrive's ``max_step``: the car
  could have driven on). Other libraries use it as any PettingZoo env.
* :class:`AgentSlots`, the batch view drivelab's trainers step: a Gymnasium env whose observation
  is ``(K, D)``, one row per *slot*, K = the scene's ``num_agents``. A car keeps its slot from the
  step it appears to the step it leaves; a new car takes a free slot. ``info`` says, per slot,
  who acted, what they got and how they ended (see :meth:`AgentSlots.step`). A scene episode
  that ends (no car left) is reset inside ``step``, so a vector env of these never autoresets.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv

from drivelab.envs.metadrive import DEFAULTS, _disable_asset_download
from drivelab.errors import DrivelabError

# scene -> MetaDrive class name (in metadrive.envs.marl_envs)
SCENES = {
    "Intersection": "MultiAgentIntersectionEnv",
    "Roundabout": "MultiAgentRoundaboutEnv",
    "Tollgate": "MultiAgentTollgateEnv",
    "Bottleneck": "MultiAgentBottleneckEnv",
    "ParkingLot": "MultiAgentParkingLotEnv",
    "PGMap": "MultiAgentMetaDrive",
}
RENDER_PIXELS = 600          # the side of a rendered frame
SPAWN_SCENARIOS = 10_000     # seeds of the spawn places on a fixed map


def scene_class(scene: str) -> type:
    """The MetaDrive env class of ``scene``, or one line naming the scenes."""
    if scene not in SCENES:
        raise DrivelabError(f"unknown multi-agent scene {scene!r}: one of {', '.join(SCENES)}")
    import metadrive.envs.marl_envs as marl

    return getattr(marl, SCENES[scene])


@functools.cache
def scene_capacity(scene: str) -> int:
    """How many cars the scene can hold at once: its spawn points (lanes x spawn roads x places
    per lane), the most ``num_agents`` MetaDrive accepts."""
    from metadrive.manager.spawn_manager import SpawnManager

    config = scene_class(scene).default_config()
    roads = config["spawn_roads"]
    if roads is None:  # the parking lot: its entry roads, and a road out of each parking space
        roads = list(config["in_spawn_roads"]) + [None] * config["parking_space_num"]
    map_config = config["map_config"]
    return SpawnManager.max_capacity(roads, map_config["exit_length"], map_config["lane_num"])


def check_num_agents(scene: str, num_agents: Any, where: str) -> int:
    """``num_agents`` (None: the scene's default) as an int in 1..capacity, or one line naming ``where``."""
    if num_agents is None:
        return int(scene_class(scene).default_config()["num_agents"])
    capacity = scene_capacity(scene)
    if isinstance(num_agents, bool) or not isinstance(num_agents, int) or not 1 <= num_agents <= capacity:
        raise DrivelabError(f"{where}: num_agents must be an integer from 1 to {capacity} (the {scene} scene's "
                            f"spawn points), got {num_agents!r}")
    return num_agents


class MultiAgentDrive(ParallelEnv):
    """One MetaDrive multi-agent scene behind PettingZoo's parallel API.

    ``step`` takes an action for every agent in :attr:`agents` and returns dicts keyed by the
    agents that acted plus the cars that appeared at this step (their first observation; reward 0,
    not done). An agent's episode ends in exactly one of ``terminations`` (crash, out of road,
    arrival: no future) and ``truncations`` (its step limit). ``infos[agent]`` is MetaDrive's
    step info (``arrive_dest``, ``crash``, ``out_of_road``, ``route_completion``, ``cost``, ...).
    The scene episode is over when :attr:`agents` is empty.
    """

    metadata = {"name": "drivelab_multiagent_drive_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(self, scene: str = "Intersection", num_agents: int | None = None,
                 render_mode: str | None = None, **config: Any):
        cls = scene_class(scene)
        self.scene = scene
        self.num_agents_max = check_num_agents(scene, num_agents, f"multi-agent scene {scene}")
        self.render_mode = render_mode
        _disable_asset_download()
        # Reproducible scenes: MetaDrive draws where cars spawn from an unseeded generator unless
        # force_seed_spawn_manager; seeded, a scene's scenario is where its cars start, and the
        # fixed-map scenes get many of them (PGMap's scenarios are maps: MetaDrive's own count).
        seeding = {"force_seed_spawn_manager": True,
                   **({} if scene == "PGMap" else {"num_scenarios": SPAWN_SCENARIOS})}
        merged = {"use_render": False, "log_level": DEFAULTS["log_level"], **seeding, **config,
                  "num_agents": self.num_agents_max}
        try:
            self._env = cls(merged)
        except (KeyError, ValueError, TypeError, AssertionError) as exc:
            message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise DrivelabError(f"multi-agent scene {scene} could not be created with {config}: {message}") from None
        # Every car has the same spaces; PettingZoo asks for the same object on every call.
        self._obs_space = self._env.observation_space["agent0"]
        self._act_space = self._env.action_space["agent0"]
        self.agents: list[str] = []
        horizon = self._env.config["horizon"] or 1000
        # Names MetaDrive can give within one episode: the first cars, then fewer than num_agents
        # new cars per step until respawns stop at the horizon (a bound, never reached).
        self._possible = self.num_agents_max * (horizon + 1)
        self._start_seed = int(self._env.config["start_seed"])
        self._num_scenarios = int(self._env.config["num_scenarios"])

    @functools.cached_property
    def possible_agents(self) -> list[str]:
        return [f"agent{i}" for i in range(self._possible)]

    def observation_space(self, agent: str) -> gym.Space:
        return self._obs_space

    def action_space(self, agent: str) -> gym.Space:
        return self._act_space

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """A new scene episode; ``seed`` picks one of the scene's scenarios (modulo their number)."""
        scenario = None if seed is None else self._start_seed + int(seed) % self._num_scenarios
        obs, infos = self._env.reset(seed=scenario)
        self.agents = list(obs)
        return obs, {agent: infos.get(agent, {}) for agent in obs}

    def step(self, actions: dict[str, np.ndarray]) -> tuple[dict, dict, dict, dict, dict]:
        obs, rewards, terminated, _, infos = self._env.step(actions)
        terminations, truncations = {}, {}
        for agent in obs:
            info = infos.setdefault(agent, {})
            # MetaDrive counts a car's step limit as terminated too (truncate_as_terminate); a time
            # limit is a truncation (Pardo et al. 2018): the car could have driven on.
            truncations[agent] = bool(info.get("max_step", False))
            terminations[agent] = bool(terminated.get(agent, False)) and not truncations[agent]
        self.agents = [a for a in obs if not (terminations[a] or truncations[a])]
        return (obs, {a: float(rewards.get(a, 0.0)) for a in obs}, terminations, truncations,
                {a: infos[a] for a in obs})

    def positions(self, agents: list[str]) -> np.ndarray:
        """(len(agents), 2) the cars' positions in metres (NaN for a car already taken off the road)."""
        out = np.full((len(agents), 2), np.nan)
        for i, agent in enumerate(agents):
            car = self._env.agent_manager.get_agent(agent, raise_error=False)
            if car is not None:
                out[i] = car.position
        return out

    def render(self) -> np.ndarray | None:
        """The whole scene from above, every car drawn (MetaDrive's pygame top-down view)."""
        if self.render_mode != "rgb_array":
            return None
        # the camera over the middle of the map, scaled so that the whole scene fits the frame
        xmin, xmax, ymin, ymax = self._env.current_map.road_network.get_bounding_box()
        extent = max(xmax - xmin, ymax - ymin) + 10.0  # metres, with a margin
        frame = self._env.render(mode="topdown", window=False, screen_size=(RENDER_PIXELS, RENDER_PIXELS),
                                 film_size=(2 * RENDER_PIXELS, 2 * RENDER_PIXELS), scaling=RENDER_PIXELS / extent,
                                 camera_position=((xmin + xmax) / 2, (ymin + ymax) / 2))
        return np.asarray(frame, dtype=np.uint8)

    def close(self) -> None:
        self._env.close()



# Per-agent outcome at the end of an agent's episode, from MetaDrive's step info.
OUTCOMES = {"success": "arrive_dest", "crash": "crash", "out_of_road": "out_of_road", "timeout": "max_step"}


class AgentSlots(gym.Env):
    """A multi-agent scene as K agent slots, the batch view drivelab's trainers step.

    Observation ``(K, D)`` and action ``(K, A)``: row k is the car in slot k (zeros for a free
    slot, whose action is ignored). ``step`` returns the next observations, a placeholder scalar
    reward (the mean over the cars that acted), ``terminated = truncated = False`` (the scene
    resets itself) and an ``info`` of ``(K,)`` arrays, for the car that acted in each slot:

    * ``acted``: the slot held a car that took this step's action;
    * ``agent_reward``, ``agent_cost``: what that car got;
    * ``agent_terminated``, ``agent_truncated``: its episode ended here, and how;
    * ``agent_final_obs`` ``(K, D)``: its last observation where it ended (to bootstrap a truncation);
    * ``success``, ``crash``, ``out_of_road``, ``timeout``, ``route_completion``: its outcome where it ended;
    * ``agent_final_position`` ``(K, 2)``: where it ended (NaN if MetaDrive took it off at once);
    * ``alive``: the slot holds a car after this step (the next action is that car's);
    * ``position`` ``(K, 2)``: where the slot's car is after this step (NaN for a free slot);
    * ``scene_end``: scalar, the scene episode ended and a new one began (the rows are its first cars).

    A car that ends at step t and a new car that takes its slot at t are two episodes: the row of
    the observation is the new car's, ``agent_final_obs`` the old one's.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}  # a MetaDrive step is 0.1 s

    def __init__(self, scene: str | ParallelEnv = "Intersection", num_agents: int | None = None,
                 render_mode: str | None = None, **config: Any):
        if isinstance(scene, str):
            scene = MultiAgentDrive(scene, num_agents, render_mode=render_mode, **config)
            num_agents = scene.num_agents_max
        elif num_agents is None:  # any PettingZoo ParallelEnv whose agents share their spaces
            raise DrivelabError("AgentSlots over a ParallelEnv needs num_agents: the most agents it holds at once")
        self.scene = scene
        self.render_mode = render_mode
        self.num_slots = k = num_agents
        first = scene.possible_agents[0]
        single_obs, single_act = scene.observation_space(first), scene.action_space(first)
        self.agent_observation_space, self.agent_action_space = single_obs, single_act
        self.observation_space = gym.spaces.Box(np.broadcast_to(single_obs.low, (k, *single_obs.shape)),
                                                np.broadcast_to(single_obs.high, (k, *single_obs.shape)),
                                                dtype=single_obs.dtype)
        self.action_space = gym.spaces.Box(np.broadcast_to(single_act.low, (k, *single_act.shape)),
                                           np.broadcast_to(single_act.high, (k, *single_act.shape)),
                                           dtype=single_act.dtype)
        self.slot_agent: list[str | None] = [None] * k
        self._scene_rng = np.random.default_rng()

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self._scene_rng = np.random.default_rng(seed)
        obs = self._new_scene()
        return obs, {"alive": np.array([a is not None for a in self.slot_agent]), "position": self._positions()}

    def _positions(self) -> np.ndarray:
        """(K, 2) where the slots' cars are (NaN for free slots)."""
        seated = [k for k, agent in enumerate(self.slot_agent) if agent is not None]
        out = np.full((self.num_slots, 2), np.nan)
        out[seated] = self._scene_positions([self.slot_agent[k] for k in seated])
        return out

    def _scene_positions(self, agents: list[str]) -> np.ndarray:
        """Where the scene's cars are; NaN for a ParallelEnv that does not say (``positions``)."""
        if not agents or not hasattr(self.scene, "positions"):
            return np.full((len(agents), 2), np.nan)
        return self.scene.positions(agents)

    def _new_scene(self) -> np.ndarray:
        obs, _ = self.scene.reset(seed=int(self._scene_rng.integers(2**31 - 1)))
        self.slot_agent = [None] * self.num_slots
        return self._seat(obs)

    def _seat(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Give every car without a slot a free one; the (K, D) observation of the cars seated."""
        seated = set(self.slot_agent)
        free = (k for k, agent in enumerate(self.slot_agent) if agent is None)
        for agent in self.scene.agents:
            if agent not in seated:
                self.slot_agent[next(free)] = agent  # K = num_agents: MetaDrive never holds more cars
        rows = np.zeros(self.observation_space.shape, self.observation_space.dtype)
        for k, agent in enumerate(self.slot_agent):
            if agent is not None:
                rows[k] = obs[agent]
        return rows

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        acting = {agent: np.asarray(action[k]) for k, agent in enumerate(self.slot_agent) if agent is not None}
        obs, rewards, terminations, truncations, infos = self.scene.step(acting)
        k = self.num_slots
        info: dict[str, Any] = {"acted": np.zeros(k, bool), "agent_reward": np.zeros(k), "agent_cost": np.zeros(k),
                                "agent_terminated": np.zeros(k, bool), "agent_truncated": np.zeros(k, bool),
                                "agent_final_obs": np.zeros(self.observation_space.shape, self.observation_space.dtype),
                                "agent_final_position": np.full((k, 2), np.nan), "route_completion": np.zeros(k),
                                **{name: np.zeros(k, bool) for name in OUTCOMES}}
        ended = [(slot, agent) for slot, agent in enumerate(self.slot_agent)
                 if agent is not None and (terminations[agent] or truncations[agent])]
        if ended:
            info["agent_final_position"][[slot for slot, _ in ended]] = self._scene_positions([a for _, a in ended])
        for slot, agent in enumerate(self.slot_agent):
            if agent is None:
                continue
            info["acted"][slot] = True
            info["agent_reward"][slot] = rewards[agent]
            info["agent_cost"][slot] = float(infos[agent].get("cost", 0.0))
            if terminations[agent] or truncations[agent]:
                info["agent_terminated"][slot], info["agent_truncated"][slot] = terminations[agent], truncations[agent]
                info["agent_final_obs"][slot] = obs[agent]
                for name, key in OUTCOMES.items():
                    info[name][slot] = bool(infos[agent].get(key, False))
                info["route_completion"][slot] = float(infos[agent].get("route_completion", math.nan))
                self.slot_agent[slot] = None
        info["scene_end"] = not self.scene.agents
        rows = self._new_scene() if info["scene_end"] else self._seat(obs)
        info["alive"] = np.array([a is not None for a in self.slot_agent])
        info["position"] = self._positions()
        acted = info["acted"]
        reward = float(info["agent_reward"][acted].mean()) if acted.any() else 0.0
        return rows, reward, False, False, info

    def render(self) -> np.ndarray | None:
        return self.scene.render()

    def close(self) -> None:
        self.scene.close()


def agent_spaces(env_space: gym.Space) -> gym.Space:
    """The space of one agent's row of a ``(K, ...)`` slot space (what a shared policy sees)."""
    return gym.spaces.Box(env_space.low[0], env_space.high[0], dtype=env_space.dtype)
