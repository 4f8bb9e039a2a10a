"""Reward shaping for driving: named terms with weights, chosen in config.

A reward config maps term names to their parameters (``weight`` scales the term)::

    reward:
      cte: {weight: 1.0, scale: 1.0, max_cte: 1.5, crash: -10.0}   # cross-track error
      lane: {weight: 0.1}                                           # Duckietown's lane reward
      native: {weight: 0.0}
      idle: {weight: 0.1, min_speed: 2.0}                           # waiting costs 0.1 per step
      cost: {weight: 5.0}                # minus 5 x the step's cost (drivelab.envs.costs): a fixed price
      headway: {weight: 1.0, seconds: 2.0}   # closer than 2 s to what is ahead costs 1 per step

Each term is a pure function of the step's ``info`` (the lane geometry drivelab's driving envs
report: ``cte``, ``heading_error``, ``speed``, ``speed_along_lane``, ``collided``,
``out_of_road``, ``route_completion``, ``native_reward``, ``cost``; MetaDrive's state observations
also ``ahead_m``) and the previous step's info (for
progress). :class:`RewardShaping` replaces the env's reward by the weighted sum, reports each
term's episode sum as ``info["reward/<term>"]`` (logged as ``episode/reward/<term>``, so a user
sees which term drives the behaviour), and ends the episode where a term says so.

Any env can be shaped: a term needs only the info keys it reads (``native`` and ``idle`` work
wherever the env reports its reward, or ``speed``), and a term named ``module:function`` is
the user's own: ``function(info, prev, **params)`` returns a float or a :class:`TermResult`,
with the env's ``native_reward``, the ``observation`` and the ``action`` added to ``info``::

    reward: {native: {}, "my_rewards:upright_bonus": {weight: 0.5, threshold: 0.1}}
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import gymnasium as gym

from drivelab.errors import DrivelabError


@dataclass(frozen=True)
class TermResult:
    value: float
    terminate: bool = False


def cte_reward(info: dict, prev: dict | None, scale: float = 1.0, max_cte: float = 1.5, crash: float = -10.0,
               per: str = "step") -> TermResult:
    """The cross-track-error reward of lane following (e.g. on a Donkey car): scale * (1 -
    (|cte| / max_cte)^2) near the lane centre; ``crash`` and the end of the episode on a
    collision, leaving the road, or |cte| > max_cte.

    ``per="step"`` pays it every step, which suits a car at a fixed throttle. When the
    agent controls the throttle, that makes standing still on the centre line optimal;
    ``per="progress"`` pays it in proportion to the route completion gained this step instead
    (scale = the whole route driven on the centre line), like MetaDrive's own lateral factor.
    """
    if per not in ("step", "progress"):
        raise TypeError(f"per must be 'step' or 'progress', got {per!r}")
    cte = abs(info["cte"])
    if info.get("collided") or info.get("out_of_road") or cte > max_cte:
        return TermResult(crash, terminate=True)
    centred = 1.0 - (cte / max_cte) ** 2
    return TermResult(scale * centred * (_route_gained(info, prev) if per == "progress" else 1.0))


def lane_reward(info: dict, prev: dict | None, w_speed: float = 1.0, w_dist: float = 10.0, w_col: float = 40.0) -> TermResult:
    """gym-duckietown's lane reward: w_speed * speed * dot_dir - w_dist * |dist|
    + w_col * collision_penalty, with dot_dir = cos(heading error), dist = CTE (m), and a
    collision penalty of -1 on a collision step (Duckietown's proximity penalty is <= 0)."""
    dot_dir = math.cos(info["heading_error"])
    penalty = -1.0 if info.get("collided") else 0.0
    return TermResult(w_speed * info["speed"] * dot_dir - w_dist * abs(info["cte"]) + w_col * penalty)


def native_reward(info: dict, prev: dict | None) -> TermResult:
    """The simulator's own reward (MetaDrive: progress along the route, speed, and penalties)."""
    return TermResult(info.get("native_reward", 0.0))


def progress_reward(info: dict, prev: dict | None, scale: float = 100.0) -> TermResult:
    """scale * (route completion gained this step): 100 = the whole route is worth 100."""
    return TermResult(scale * _route_gained(info, prev))


def idle_penalty(info: dict, prev: dict | None, min_speed: float = 2.0) -> TermResult:
    """-1 for each step slower than ``min_speed`` (m/s); scale it with ``weight``.

    Why: with progress rewards and crash penalties, standing still costs nothing, so a cautious
    policy can learn to stop behind traffic or before a bend and wait out the step limit (trained
    MetaDrive policies did: docs/results.md, PPO drive recipe). Paying a little for every
    idle step makes waiting worse than driving on, once it lasts longer than the crash penalty.
    """
    return TermResult(-1.0 if info["speed"] < min_speed else 0.0)


def _route_gained(info: dict, prev: dict | None) -> float:
    return info["route_completion"] - (prev["route_completion"] if prev is not None else info["route_completion"])


def cost_penalty(info: dict, prev: dict | None) -> TermResult:
    """Minus the step's cost (``info["cost"]``, after ``env.cost``'s terms: :mod:`drivelab.envs.costs`).

    The reward-shaping baseline of constrained RL: ``env.reward: {native: {}, cost: {weight: W}}``
    folds the cost into the reward with a fixed price W, where a constrained algorithm (ppo_lag,
    sac_lag) learns the price (its Lagrange multiplier) that meets a cost limit.
    """
    return TermResult(-float(info["cost"]))


def headway_penalty(info: dict, prev: dict | None, seconds: float = 2.0, min_speed: float = 1.0) -> TermResult:
    """-1 for each step whose time headway, the distance to the nearest thing ahead
    (``info["ahead_m"]``, m) over the speed (m/s), is under ``seconds`` while the car moves at
    ``min_speed`` or more: the two-second rule of driving schools, as a price.

    Why: a crash price (MetaDrive's penalties, ``cost``, or the end of the episode under
    ``env.cost_termination``) arrives only at the contact. On SafeMetaDrive the cars had the
    nearest lidar return 12-29 m away 2 s before a contact and still met the object at 2-10 m/s
    (docs/results.md, "Safe driving"): this term prices the approach itself.
    """
    speed = info["speed"]
    return TermResult(-1.0 if speed >= min_speed and info["ahead_m"] < seconds * speed else 0.0)


TERMS: dict[str, Callable[..., TermResult]] = {
    "cte": cte_reward, "lane": lane_reward, "native": native_reward, "progress": progress_reward,
    "idle": idle_penalty, "cost": cost_penalty, "headway": headway_penalty,
}


# The info keys each shipped term reads: a term is refused, in one line, on an env that lacks them.
NEEDS: dict[str, tuple[str, ...]] = {
    "cte": ("cte",), "lane": ("cte", "heading_error", "speed"), "native": (), "progress": ("route_completion",),
    "idle": ("speed",), "cost": ("cost",), "headway": ("ahead_m", "speed"),
}


def term_function(name: str, where: str = "env.reward", table: dict[str, Callable] | None = None,
                  kind: str = "reward") -> Callable[..., TermResult | float]:
    """A shipped term of ``table`` (default: the reward terms), or the function a ``module:function`` term names."""
    table = TERMS if table is None else table
    if name in table:
        return table[name]
    if ":" not in name:
        raise DrivelabError(f"{where}: unknown {kind} term '{name}' (choose from {', '.join(table)}, "
                            f"or name your own as module:function)")
    return _user_term(name, where)


@functools.lru_cache(maxsize=None)
def _user_term(name: str, where: str) -> Callable[..., TermResult | float]:
    from drivelab.envs.registration import import_attribute

    function = import_attribute(name, f"{where}.{name}")
    if not callable(function):
        raise DrivelabError(f"{where}.{name} is not a function")
    return function


def validate_terms(config: dict[str, Any], table: dict[str, Callable], where: str, kind: str) -> dict[str, dict]:
    """Check the term names and parameters of a reward or cost config against ``table``; returns
    {term: {"weight": w, **params}}. A shipped term is called once on a probe step, so a wrong
    parameter is one line here, not an error deep inside a run."""
    if not isinstance(config, dict) or not config:
        raise DrivelabError(f"{where} must map {kind} terms ({', '.join(table)}, or module:function) to their parameters")
    clean = {}
    for name, params in config.items():
        function = term_function(name, where, table, kind)
        if params is not None and not isinstance(params, dict):
            raise DrivelabError(f"{where}.{name} must map parameter names to values, got {params!r}")
        params = dict(params or {})
        weight = params.pop("weight", 1.0)
        try:
            if name in table:  # a user's term may read keys the probe lacks: it is called on real steps only
                function(_PROBE_INFO, None, **params)
        except TypeError as exc:
            raise DrivelabError(f"{where}.{name}: {exc}".replace(f"{function.__name__}() ", "")) from None
        if not isinstance(weight, (int, float)) or isinstance(weight, bool) or not math.isfinite(weight):
            raise DrivelabError(f"{where}.{name}.weight must be a number, got {weight!r}")
        clean[name] = {"weight": float(weight), **params}
    return clean


def validate_reward_config(config: dict[str, Any], where: str = "env.reward") -> dict[str, dict]:
    """Check reward term names and parameters (:func:`validate_terms` over :data:`TERMS`)."""
    return validate_terms(config, TERMS, where, "reward")


_PROBE_INFO = {"cte": 0.0, "heading_error": 0.0, "speed": 0.0, "speed_along_lane": 0.0, "collided": False,
               "out_of_road": False, "route_completion": 0.0, "native_reward": 0.0, "cost": 0.0,
               "on_solid_line": False, "on_broken_line": False, "ahead_m": 50.0}


def missing_info(config: dict[str, dict], needs: dict[str, tuple[str, ...]], info: dict, kind: str, hint: str) -> None:
    """Refuse, in one line, a term that reads an info key this env does not report."""
    for name in config:
        missing = [key for key in needs.get(name, ()) if key not in info]
        if missing:
            raise DrivelabError(f"{kind} term '{name}' needs info['{missing[0]}'], which this env does not report "
                                f"({hint})")


def score(config: dict[str, dict], info: dict, prev: dict | None,
          table: dict[str, Callable] | None = None) -> tuple[float, dict[str, float], bool]:
    """(total, weighted value of each term, terminate?) of one step under ``config``, whose terms
    come from ``table`` (default: the reward terms) or are a user's ``module:function``."""
    total, parts, terminate = 0.0, {}, False
    for name, params in config.items():
        params = dict(params)
        weight = params.pop("weight", 1.0)
        result = term_function(name, table=table)(info, prev, **params)
        if not isinstance(result, TermResult):  # a user's term may return a plain number
            result = TermResult(float(result))
        parts[name] = weight * result.value
        total += parts[name]
        terminate |= result.terminate
    return total, parts, terminate


class RewardShaping(gym.Wrapper):
    """Replace the env's reward by a weighted sum of named terms (see the module docstring).

    ``info["reward/<term>"]`` holds each term's weighted sum over the episode so far.
    """

    def __init__(self, env: gym.Env, config: dict[str, Any]):
        super().__init__(env)
        self.replace_terms(config)
        self._prev: dict | None = None

    def replace_terms(self, config: dict[str, Any]) -> None:
        """Use ``config``'s terms instead (a task's default reward overridden by ``env.reward``)."""
        self.config = validate_reward_config(config)
        self._sums = dict.fromkeys(self.config, 0.0)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._prev = info
        self._sums = dict.fromkeys(self.config, 0.0)
        return obs, {**info, **{f"reward/{k}": 0.0 for k in self.config}}

    def step(self, action):
        obs, env_reward, terminated, truncated, info = self.env.step(action)
        missing_info(self.config, NEEDS, info, "reward", "terms for any env: native, or your own module:function")
        # what the terms see: the env's own reward (unless a driving env reported it), and for a
        # user's term the observation and the action
        seen = {"native_reward": float(env_reward), **info, "observation": obs, "action": action}
        reward, parts, end = score(self.config, seen, self._prev)
        self._prev = seen
        for name, value in parts.items():
            self._sums[name] += value
        return obs, reward, terminated or end, truncated, {**info, **{f"reward/{k}": v for k, v in self._sums.items()}}
