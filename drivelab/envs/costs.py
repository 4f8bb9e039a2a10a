"""The cost signal of constrained RL: what a step costs, summed over the episode.

Constrained RL (Altman 1999; Safety Gym, Ray, Achiam & Amodei 2019) keeps the reward and the cost
apart: the agent maximises its return while the episode's cost stays under a limit. drivelab's
contract, for every env that has a cost:

* ``info["cost"]``: the step's cost, a float >= 0 (0.0 in the reset info);
* ``info["episode_cost"]``: the episode's cost so far (0.0 in the reset info), logged as
  ``episode/cost`` and ``eval/cost``;
* ``info["cost/<term>"]``: with ``env.cost`` terms, each term's weighted sum over the episode.

An env without a cost gets none of these keys. :class:`CostSignal` puts them there; ``make_env``
installs it on every env. Without ``env.cost`` it passes the env's own ``info["cost"]`` through
(MetaDrive, SafeMetaDrive, Duckietown's collisions, a user's env that reports one) and stays silent
on an env that never reports one. With ``env.cost`` the step's cost is the weighted sum of terms,
named like the reward terms (:mod:`drivelab.envs.rewards`)::

    cost:
      crash: {}                          # 1 on each step with a collision
      out_of_road: {weight: 1.0}         # 1 on the step the car leaves the road
      speeding: {max_speed: 15.0}        # 1 on each step faster than 15 m/s
      "my_costs:near_miss": {weight: 0.5}

``native`` is the env's own cost. A cost term is a pure ``f(info, prev, **params)`` that returns a
float or a :class:`~drivelab.envs.rewards.TermResult`; it must be >= 0 and may not end the episode
(the cost is a signal to constrain, the env decides when an episode ends). Weights are >= 0.

**Units.** A cost is counted per env step, the step the agent decides on:

* MetaDrive counts its cost once per env step (0.1 s): a contact that lasts k steps costs k
  (``crash_vehicle_cost`` per step), leaving the road costs 1 once (the episode ends).
* ``env.action_repeat: N`` (the :class:`~drivelab.envs.wrappers.ActionRepeat` wrapper) sums the
  cost of the N inner steps, as it sums their rewards, so a decision's cost is in env-step units
  and an episode's cost is the same as without the repeat.
* ``env.simulator_repeat: true`` holds the action inside MetaDrive instead: one env step then lasts
  N x 0.1 s and MetaDrive checks contacts and counts the cost once for it. A contact of k x 0.1 s
  costs about k / N, so training sees less cost than evaluation (which always plays the env as
  published, with the wrapper) measures. Set a constrained run's ``cost_limit`` with that in mind,
  or train with ``simulator_repeat: false`` so the two agree.

A task that shapes its reward inside its env (lane following) sees the env's own cost in its
``cost`` reward term; ``env.reward``'s ``cost`` term sees the cost after ``env.cost``'s terms.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import gymnasium as gym

from drivelab.envs.rewards import TermResult, missing_info, score, validate_terms
from drivelab.errors import DrivelabError


def native_cost(info: dict, prev: dict | None) -> float:
    """The env's own cost (MetaDrive: 1 for a step in contact with a vehicle or an object, or off road)."""
    return float(info["cost"])


def crash_cost(info: dict, prev: dict | None) -> float:
    """1 on each step with a collision (``info["collided"]``): a contact of k steps costs k."""
    return float(bool(info["collided"]))


def out_of_road_cost(info: dict, prev: dict | None) -> float:
    """1 on the step the car leaves the road (``info["out_of_road"]`` says "so far this episode")."""
    return float(bool(info["out_of_road"]) and not (prev or {}).get("out_of_road", False))


def solid_line_cost(info: dict, prev: dict | None) -> float:
    """1 on each step on a solid lane line (MetaDrive's white or yellow continuous line)."""
    return float(bool(info["on_solid_line"]))


def broken_line_cost(info: dict, prev: dict | None) -> float:
    """1 on each step on a broken lane line (changing lanes)."""
    return float(bool(info["on_broken_line"]))


def speeding_cost(info: dict, prev: dict | None, max_speed: float) -> float:
    """1 on each step faster than ``max_speed`` (m/s)."""
    return float(info["speed"] > max_speed)


COST_TERMS: dict[str, Callable[..., float]] = {
    "native": native_cost, "crash": crash_cost, "out_of_road": out_of_road_cost, "solid_line": solid_line_cost,
    "broken_line": broken_line_cost, "speeding": speeding_cost,
}

# The info keys each shipped cost term reads (a term is refused, in one line, on an env without them).
COST_NEEDS: dict[str, tuple[str, ...]] = {
    "native": ("cost",), "crash": ("collided",), "out_of_road": ("out_of_road",), "solid_line": ("on_solid_line",),
    "broken_line": ("on_broken_line",), "speeding": ("speed",),
}

COST_TO_REWARD = ("MetaDrive config 'cost_to_reward' does nothing in MetaDrive 0.4.3 (no code reads it, metadrive#844); "
                  "to fold the cost into the reward use drivelab's reward term: env.reward: {native: {}, cost: {weight: W}}, "
                  "or train a constrained algorithm (ppo_lag, sac_lag)")


def refuse_cost_to_reward(kwargs: dict[str, Any] | None, where: str | None = None) -> None:
    """One line for MetaDrive's ``cost_to_reward`` in ``kwargs`` or ``kwargs["config"]``, whatever its value."""
    kwargs = kwargs or {}
    nested = kwargs.get("config")
    if "cost_to_reward" in kwargs or (isinstance(nested, dict) and "cost_to_reward" in nested):
        raise DrivelabError(f"{where}: {COST_TO_REWARD}" if where else COST_TO_REWARD)


def validate_cost_config(config: dict[str, Any], where: str = "env.cost") -> dict[str, dict]:
    """Check cost term names, parameters and weights (>= 0); returns {term: {"weight": w, **params}}."""
    clean = validate_terms(config, COST_TERMS, where, "cost")
    for name, params in clean.items():
        if params["weight"] < 0:
            raise DrivelabError(f"{where}.{name}.weight must be >= 0 (a cost is never negative), got {params['weight']}")
    return clean


def score_costs(config: dict[str, dict], info: dict, prev: dict | None) -> tuple[float, dict[str, float]]:
    """(the step's cost, weighted cost of each term) under ``config``; a term that returns a negative
    or non-finite cost, or asks to end the episode, is one line naming it."""
    total, parts, terminate = score(config, info, prev, COST_TERMS)
    if terminate:
        users = ", ".join(name for name in config if name not in COST_TERMS)
        raise DrivelabError(f"cost term {users} returned a TermResult that ends the episode; cost terms only "
                            f"measure (end episodes with a reward term)")
    for name, value in parts.items():
        if not (math.isfinite(value) and value >= 0):
            raise DrivelabError(f"cost term '{name}' gave {value} at a step; costs must be finite and >= 0")
    return total, parts


class CostSignal(gym.Wrapper):
    """Report the step's cost and the episode's cost so far (see the module docstring).

    ``config`` (``env.cost``, or None): without it, the env's own ``info["cost"]`` is passed through
    once the env has reported one (in a reset or a step info), and an env that never does gets no
    new keys. With it, ``info["cost"]`` is the terms' weighted sum and ``info["cost/<term>"]`` each
    term's episode sum; the terms see the env's info with its ``observation`` and ``action``.
    """

    def __init__(self, env: gym.Env, config: dict[str, Any] | None = None):
        super().__init__(env)
        self.config = validate_cost_config(config) if config else None
        self.active = self.config is not None      # set on the first info with a "cost" otherwise
        self._episode_cost = 0.0
        self._sums: dict[str, float] = {}
        self._prev: dict | None = None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._episode_cost, self._prev = 0.0, info
        self._sums = dict.fromkeys(self.config or (), 0.0)
        self.active = self.active or "cost" in info
        if not self.active:
            return obs, info
        return obs, {**info, "cost": 0.0, "episode_cost": 0.0, **self._term_sums()}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.active = self.active or "cost" in info
        if not self.active:
            return obs, reward, terminated, truncated, info
        if self.config is None:
            cost = float(info["cost"]) if "cost" in info else 0.0
        else:
            missing_info(self.config, COST_NEEDS, info, "cost", "terms for any env: your own module:function")
            seen = {**info, "observation": obs, "action": action}
            cost, parts = score_costs(self.config, seen, self._prev)
            self._prev = seen
            for name, value in parts.items():
                self._sums[name] += value
        self._episode_cost += cost
        return obs, reward, terminated, truncated, {**info, "cost": cost, "episode_cost": self._episode_cost,
                                                    **self._term_sums()}

    def _term_sums(self) -> dict[str, float]:
        return {f"cost/{name}": value for name, value in self._sums.items()}


def check_cost_budget(budget: Any, where: str = "env.cost_termination") -> float:
    """``budget`` as a float, or one line when it is not a finite number >= 0."""
    if isinstance(budget, bool) or not isinstance(budget, (int, float)) or not 0 <= budget < math.inf:
        raise DrivelabError(f"config field '{where}' must be a cost budget >= 0 (or null), got {budget!r}")
    return float(budget)


class CostTermination(gym.Wrapper):
    """End an episode, as terminated, on the step its cost first exceeds ``budget`` (a training
    curriculum: ``env.cost_termination``; evaluation plays the env as published).

    The early-terminated MDP of Sun et al. 2021 ("Safe Exploration by Solving Early Terminated
    MDP"): a constrained problem with a per-episode cost budget becomes an unconstrained one whose
    episode stops where the budget is spent, so every later reward is lost. The policy learns to
    stay within the budget from the return alone, and a learner never lives through the rest of a
    costly episode, which is where exploration's cost piles up on SafeMetaDrive (a car that crashes
    keeps driving, and may stay in contact for many steps). With budget 0, the first step with
    any cost ends the episode, as MetaDrive's own ``crash_*_done`` would for crashes, but for any env
    that reports a cost. ``info["cost_terminated"]`` says whether the budget ended the episode.

    Goes right after :class:`CostSignal`, whose ``info["episode_cost"]`` it reads.
    """

    def __init__(self, env: gym.Env, budget: float):
        super().__init__(env)
        self.budget = check_cost_budget(budget)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        over = float(info.get("episode_cost", 0.0)) > self.budget and not (terminated or truncated)
        return obs, reward, terminated or over, truncated, {**info, "cost_terminated": over}


__all__ = ["COST_TERMS", "COST_NEEDS", "CostSignal", "CostTermination", "TermResult",
           "check_cost_budget", "refuse_cost_to_reward", "score_costs", "validate_cost_config"]
