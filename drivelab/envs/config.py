"""The ``env`` section of a run's config: which env, how many copies, where they run, and
drivelab's wrappers around it (action grid, fixed throttle, reward terms, observation filters).

It lives with the envs, which build from it (:func:`drivelab.envs.make_vector_env`);
:mod:`drivelab.config` composes it into the whole run's config.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from drivelab.envs.costs import check_cost_budget, refuse_cost_to_reward, validate_cost_config
from drivelab.envs.registration import (
    MULTIAGENT_SCENES,
    is_multiagent,
    metadrive_ids,
    needs_own_process,
    register_envs,
    registered_id,
)
from drivelab.envs.rewards import validate_reward_config
from drivelab.envs.wrappers import parse_grid
from drivelab.errors import DrivelabError

BACKENDS = ("auto", "sync", "async", "ray")
# kwargs that shape what the policy senses and drives (MetaDrive's vehicle_config: its lidar,
# num_others, ...): a policy evaluated on another env id keeps them, or its observation changes.
POLICY_KWARGS = ("vehicle_config",)


@dataclass
class EnvConfig:
    id: str = "CartPole-v1"           # a Gymnasium id, a drivelab id, or module:EnvClass
    num_envs: int = 4                 # envs stepped in parallel
    # Where the envs run: sync (in this process), async (one subprocess each), ray (in Ray actors,
    # on this machine or a cluster: drivelab.envs.ray_backend), or auto: async for simulators that
    # allow one instance per process (MetaDrive), sync otherwise. (A saved config's
    # `vectorization` is read as this field: drivelab.config.parse_config.)
    backend: str = "auto"
    # Ray backend: envs per actor (stepped together, one remote call per actor and step; MetaDrive
    # allows 1) and the CPUs Ray reserves for each actor.
    envs_per_actor: int = 1
    actor_cpus: float = 1.0
    # "NxM": N steering x M throttle discrete actions over a [steering, throttle] Box action.
    action_grid: str | None = None
    max_steering: float = 0.6         # the action grid's steering range: [-max, max]
    # Steering-only 1-D actions at this constant throttle (drivelab.envs.wrappers.FixedThrottle).
    fixed_throttle: float | None = None
    # Hold each action for this many env steps, summing their rewards (wrappers.ActionRepeat):
    # the agent decides every action_repeat steps; the env, its traffic and horizon are unchanged.
    action_repeat: int = 1
    # MetaDrive, in training only: hold each action inside the simulator (MetaDrive's
    # decision_repeat x action_repeat physics steps in one env step, horizon / action_repeat)
    # instead of the ActionRepeat wrapper. One traffic decision, one observation and one crash /
    # line check per decision instead of per env step, so a decision costs less
    # (benchmarks/metadrive_reset_cost.py), but the traffic also decides every
    # action_repeat x 0.1 s and per-step reward terms count once per decision. Evaluation always
    # plays the env as published, with the wrapper (EnvConfig.played).
    simulator_repeat: bool = False
    # MetaDrive, in training only: the share of episodes that start on a scenario this env
    # failed before (wrappers.ScenarioReplay, after Prioritized Level Replay); 0: every episode
    # draws its scenario as usual. Evaluation never replays (EnvConfig.played).
    scenario_replay: float = 0.0
    # Reward shaping: {term: {weight: w, ...params}} over cte, lane, native, progress, idle, cost
    # (drivelab.envs.rewards); replaces the env's reward.
    reward: dict[str, Any] | None = None
    # Cost terms of constrained RL: {term: {weight: w, ...params}} over native, crash, out_of_road,
    # solid_line, broken_line, speeding or module:function (drivelab.envs.costs); info["cost"]
    # becomes their weighted sum. None: the env's own cost, where it reports one.
    cost: dict[str, Any] | None = None
    # In training only: end an episode (terminated) once its cost exceeds this budget (safe
    # exploration's early-terminated MDP: costs.CostTermination). None: as the env says.
    cost_termination: float | None = None
    # Observation filters, applied in order: names or {name: params} (drivelab.envs.filters).
    obs_filters: list[Any] = field(default_factory=list)
    # keyword overrides for gym.make, e.g. MetaDrive's {num_scenarios: 10, traffic_density: 0.2}
    kwargs: dict[str, Any] = field(default_factory=dict)
    # Subprocess envs: a worker that raises, dies or answers no step/reset within step_timeout
    # seconds is restarted (its episode ends as truncated); more than max_restarts restarts within
    # restart_window vector steps stop the run with the env's error.
    step_timeout: float | None = 300.0
    max_restarts: int = 3
    restart_window: int = 10_000
    # On-policy rollouts: the subprocess envs step as this many groups, each on its own, so the
    # trainer picks one group's actions while the others simulate (drivelab.envs.groups). None: 1
    # (lockstep); N (one per env) helps where cores are free while the trainer computes.
    step_groups: int | None = None

    def validate(self, where: str = "env") -> None:
        """Check every field once, before anything is built (the env factory trusts the result)."""
        if self.num_envs < 1:
            raise DrivelabError(f"config field '{where}.num_envs' must be >= 1, got {self.num_envs}")
        if self.action_repeat < 1:
            raise DrivelabError(f"config field '{where}.action_repeat' must be >= 1, got {self.action_repeat}")
        if self.simulator_repeat and registered_id(self.id) not in metadrive_ids():
            raise DrivelabError(f"config field '{where}.simulator_repeat' holds actions inside MetaDrive's simulator; "
                                f"'{self.id}' is not a MetaDrive env")
        if not 0.0 <= self.scenario_replay < 1.0:
            raise DrivelabError(f"config field '{where}.scenario_replay' must be in [0, 1), got {self.scenario_replay}")
        if self.cost_termination is not None:
            check_cost_budget(self.cost_termination, f"{where}.cost_termination")
        if self.scenario_replay and registered_id(self.id) not in metadrive_ids():
            raise DrivelabError(f"config field '{where}.scenario_replay' replays MetaDrive scenarios; "
                                f"'{self.id}' is not a MetaDrive env")
        if self.step_timeout is not None and not self.step_timeout > 0:
            raise DrivelabError(f"config field '{where}.step_timeout' must be > 0 seconds, got {self.step_timeout}")
        if self.max_restarts < 0 or self.restart_window < 1:
            raise DrivelabError(f"config fields '{where}.max_restarts' (>= 0) and '{where}.restart_window' (>= 1) are out of range")
        if self.backend not in BACKENDS:
            raise DrivelabError(f"config field '{where}.backend' must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.envs_per_actor < 1 or not self.actor_cpus >= 0:
            raise DrivelabError(f"config fields '{where}.envs_per_actor' (>= 1) and '{where}.actor_cpus' (>= 0) are out of range")
        self.check_one_per_process(where)
        if self.step_groups is not None and not 1 <= self.step_groups <= self.num_envs:
            raise DrivelabError(f"config field '{where}.step_groups' must be between 1 and num_envs "
                                f"({self.num_envs}), got {self.step_groups}")
        if (self.step_groups or 1) > 1 and self.resolved_backend() != "async":
            raise DrivelabError(f"config field '{where}.step_groups' > 1 needs subprocess envs (env.backend: async, "
                                f"or auto for a simulator such as MetaDrive); '{self.id}' runs {self.resolved_backend()}")
        if self.action_grid is not None:
            parse_grid(self.action_grid, f"{where}.action_grid")
            if self.fixed_throttle is not None:
                raise DrivelabError(f"config fields '{where}.action_grid' and '{where}.fixed_throttle' exclude each other")
        if self.reward is not None:
            validate_reward_config(self.reward, f"{where}.reward")
        if self.cost is not None:
            validate_cost_config(self.cost, f"{where}.cost")
        refuse_cost_to_reward(self.kwargs, f"config field '{where}.kwargs'")
        if is_multiagent(self.id):
            check_multiagent(self, where)

    def on(self, env_id: str, kwargs: dict[str, Any] | None = None) -> EnvConfig:
        """This config (wrappers, filters, action grid) on another env id, e.g. a validation set:
        the kwargs that shape the policy's observation and car (:data:`POLICY_KWARGS`) go along;
        the others, which may redefine the scenario range, traffic or reward, give way to ``kwargs``."""
        kept = {key: value for key, value in self.kwargs.items() if key in POLICY_KWARGS}
        return dataclasses.replace(self.played(), id=env_id, kwargs={**kept, **(kwargs or {})})

    def played(self) -> EnvConfig:
        """This config as evaluation plays it: ``simulator_repeat`` (a training speed-up that changes
        the simulator's own step) off, so a decision every ``action_repeat`` steps is held by the
        wrapper on the env as published, and the training curricula ``scenario_replay`` and
        ``cost_termination`` off."""
        if not (self.simulator_repeat or self.scenario_replay or self.cost_termination is not None):
            return self
        return dataclasses.replace(self, simulator_repeat=False, scenario_replay=0.0, cost_termination=None)

    def resolved_step_groups(self) -> int:
        """``step_groups``, with None resolved to 1 (lockstep): groups pay off only where cores are
        free while the trainer computes, so they are asked for, not assumed (throughput of both:
        ``benchmarks/throughput.py``)."""
        return self.step_groups or 1

    def resolved_backend(self) -> str:
        """``backend``, with auto resolved: async for one-per-process simulators, sync otherwise."""
        if self.backend != "auto":
            return self.backend
        register_envs()
        return "async" if needs_own_process(self.id) else "sync"

    def check_one_per_process(self, where: str = "env") -> None:
        """Simulators with one instance per process (MetaDrive) cannot share a process: not with
        the trainer (sync) nor with each other in one Ray actor."""
        register_envs()
        if self.backend == "sync" and needs_own_process(self.id):
            raise DrivelabError(f"config field '{where}.backend': '{self.id}' allows one instance per process; use async, ray or auto")
        if self.backend == "ray" and self.envs_per_actor > 1 and needs_own_process(self.id):
            raise DrivelabError(f"config field '{where}.envs_per_actor': '{self.id}' allows one instance per process; use 1")


# Fields that wrap a single-agent env; the slots of a multi-agent scene take none of them.
SINGLE_AGENT_FIELDS = ("action_grid", "fixed_throttle", "reward", "cost", "cost_termination", "obs_filters",
                       "scenario_replay", "simulator_repeat")


def check_multiagent(cfg: EnvConfig, where: str) -> None:
    """A multi-agent scene: no single-agent wrappers, and ``kwargs.num_agents`` within its spawn points."""
    from drivelab.envs.multiagent import check_num_agents

    defaults = EnvConfig()
    for name in SINGLE_AGENT_FIELDS:
        if getattr(cfg, name) != getattr(defaults, name):
            raise DrivelabError(f"config field '{where}.{name}' wraps a single-agent env; the multi-agent scene "
                                f"'{cfg.id}' takes MetaDrive's own settings in '{where}.kwargs'")
    if cfg.action_repeat != 1:
        raise DrivelabError(f"config field '{where}.action_repeat': the multi-agent scene '{cfg.id}' takes "
                            f"MetaDrive's decision_repeat in '{where}.kwargs' instead")
    check_num_agents(MULTIAGENT_SCENES[registered_id(cfg.id)], cfg.kwargs.get("num_agents"),
                     f"config field '{where}.kwargs.num_agents'")
