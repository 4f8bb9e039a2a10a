"""Rollouts of a shared policy on multi-agent scenes: every live car of every scene in one batch.

N scene processes, each an :class:`~drivelab.envs.multiagent.AgentSlots` env of K slots, step
together; the policy acts for all N x K slots at once (a free slot's action is ignored). The
rollout is stored as (T, N x K) arrays, one column per slot, so a car's trajectory is a run of
rows in its slot's column, and GAE runs per column as in the single-agent case
(:func:`drivelab.training.learning.returns.gae`) with three kinds of row:

* the car went on: ``V(s_{t+1})`` is the next row's value (the same car);
* the car's episode ended at t: terminated (crash, off road, arrived: no future) or truncated
  (its step limit: bootstrap from ``V`` of its last observation, ``info["agent_final_obs"]``);
  the trace stops either way, since the next row of that column is another car or empty;
* the slot was empty at t: no reward, no future, and the row is left out of the update.

A car that arrives takes a free slot at the step it appears; its first row is the next one. The
samples of the update are the rows where a car acted, flattened: the batch size changes with
the number of live cars. Each ended car is one agent episode for ``run.episodes`` (return,
length, success, crash, out of road, time-out, route completion, cost).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from drivelab.config import TrainConfig
from drivelab.envs import make_vector_env
from drivelab.envs.multiagent import OUTCOMES, agent_spaces
from drivelab.training.collection.checks import check_finite_step
from drivelab.training.learning.hyperparams import ActorCriticParams
from drivelab.training.learning.policy_nets import ActorCritic, sample
from drivelab.training.learning.returns import gae
from drivelab.training.learning.rollout_buffers import RolloutBatch
from drivelab.training.outputs.episodes import DRIVING_METRICS, Episode

if TYPE_CHECKING:  # the collector calls the run's services; run/ sits above collection/
    from drivelab.training.run import Run

# The (K,) arrays of an AgentSlots info that the collector reads.
AGENT_KEYS = ("acted", "agent_reward", "agent_cost", "agent_terminated", "agent_truncated", "route_completion",
              *OUTCOMES)


def slot_arrays(info: dict, num_envs: int, num_slots: int, obs_dim: int) -> dict[str, np.ndarray]:
    """The per-slot arrays of a vector env's batched ``info`` as (N x K, ...) arrays: (N x K,) for
    the flags and numbers, (N x K, 2) for positions, (N x K, D) for ``agent_final_obs``. An env
    whose info lacks a key (a restarted worker's new scene has no step yet) gets zeros there (NaN
    positions): no car acted in it."""
    shapes = {"agent_final_obs": ((num_slots, obs_dim), 0.0), "agent_final_position": ((num_slots, 2), np.nan),
              "position": ((num_slots, 2), np.nan)}
    out = {}
    for key in (*AGENT_KEYS, "agent_final_obs", "agent_final_position", "position", "alive"):
        shape, fill = shapes.get(key, ((num_slots,), 0))
        present = info.get(f"_{key}", np.zeros(num_envs, bool))
        out[key] = np.concatenate([np.asarray(info[key][i]) if present[i] else np.full(shape, fill)
                                   for i in range(num_envs)])
    for key in ("acted", "agent_terminated", "agent_truncated", "alive", *OUTCOMES):
        out[key] = out[key].astype(bool)
    return out


def mean_field(obs: np.ndarray, positions: np.ndarray, alive: np.ndarray, query_obs: np.ndarray,
               query_positions: np.ndarray, radius: float) -> np.ndarray:
    """The critic's joint observation of each query car: its own observation, then the mean
    observation of the other live cars of its scene within ``radius`` metres (zeros if none).

    Args:
        obs, positions, alive: (N, K, D), (N, K, 2), (N, K) the scenes' cars (slots) after a step.
        query_obs, query_positions: (N, K, D), (N, K, 2) the cars whose joint observation is wanted
            (the same cars, or the cars that ended at this step and their last observations).
        radius: the neighbourhood, in metres.
    Returns:
        (N x K, 2 D) float32.
    """
    distance = np.linalg.norm(query_positions[:, :, None, :] - positions[:, None, :, :], axis=-1)  # (N, K, K)
    # a car is not its own neighbour: the same slot at the same position (a new car in the slot is elsewhere)
    near = (distance <= radius) & alive[:, None, :] & (distance > 0)
    count = near.sum(-1, keepdims=True)
    mean = np.einsum("nqk,nkd->nqd", near.astype(np.float32), obs) / np.maximum(count, 1)
    joint = np.concatenate([query_obs, mean], axis=-1)
    return joint.reshape(-1, joint.shape[-1]).astype(np.float32)


def agent_advantages(rewards: np.ndarray, values: np.ndarray, next_values: np.ndarray, acted: np.ndarray,
                     terminated: np.ndarray, truncated: np.ndarray, gamma: float,
                     lam: float) -> tuple[np.ndarray, np.ndarray]:
    """GAE(lambda) per slot column over a (T, M) multi-agent rollout (M = N x K slots).

    Args:
        rewards, values: (T, M) r_t and V(s_t) of the car in the slot (anything where it is empty).
        next_values: (T, M) V(s_{t+1}) of the same car: the next row's value where the car goes
            on, V of its last observation where it was truncated, the value of the observation
            after the rollout on the last row.
        acted: (T, M) a car acted in the slot at t.
        terminated, truncated: (T, M) that car's episode ended at t, and how.
        gamma, lam: discount and GAE lambda.

    Returns:
        (advantages, returns), (T, M) float32; 0 where ``acted`` is False.
    """
    empty = ~acted
    # An empty row cuts the trace and bootstraps nothing: it is a terminal step of no one.
    adv, ret = gae(np.where(acted, rewards, 0.0), np.where(acted, values, 0.0), next_values,
                   terminated | empty, terminated | truncated | empty, gamma, lam)
    return np.where(acted, adv, 0.0).astype(np.float32), np.where(acted, ret, 0.0).astype(np.float32)


class AgentRolloutCollector:
    """N multi-agent scenes stepped T steps at a time with a shared policy; see the module docstring."""

    def __init__(self, cfg: TrainConfig, run: Run):
        hp: ActorCriticParams = cfg.algo_params
        self.run, self.gamma, self.gae_lambda, self.device = run, hp.gamma, hp.gae_lambda, run.device
        # MAPPO: the critic sees the mean observation of the neighbours within this radius (None: IPPO)
        self.radius: float | None = getattr(hp, "neighbour_radius", None)
        # AgentSlots resets its own scenes: SAME_STEP only matters if a worker is restarted
        # (every car of its scene is then cut, as truncated, and the scene begins anew).
        self.envs = make_vector_env(cfg.env, autoreset_mode=AutoresetMode.SAME_STEP, on_restart=run.note_env_restart)
        self.num_envs = n = cfg.env.num_envs
        self.num_slots = k = self.envs.single_observation_space.shape[0]
        self.obs_space = agent_spaces(self.envs.single_observation_space)
        self.act_space = agent_spaces(self.envs.single_action_space)
        m, t = n * k, hp.num_steps
        self.num_steps = t
        self.steps_per_rollout = t * n                    # env (scene) steps: what `steps` counts
        obs, info = self.envs.reset(seed=run.reset_seeds(np.ones(n, bool)))
        self.obs = obs.reshape(m, -1)
        self.alive = np.concatenate(list(info["alive"]))
        self.positions = np.concatenate(list(info["position"]))
        # (T, M) storage, written in place every step; the policy's inputs (with a centralised
        # critic, the joint observations: own and neighbours')
        width = self.obs_space.shape[0] * (2 if self.radius is not None else 1)
        self.b_obs = torch.zeros((t, m, width), dtype=torch.float32)
        self.b_actions = torch.zeros((t, m, *self.act_space.shape), dtype=torch.float32)
        self.b_log_probs, self.b_values = torch.zeros(t, m), torch.zeros(t, m)
        self.rewards, self.next_values = np.zeros((t, m)), np.zeros((t, m))
        self.acted, self.terminated, self.truncated = (np.zeros((t, m), bool) for _ in range(3))
        # each slot's car so far: return, length, cost
        self.running = np.zeros((3, m))
        self.live_sum = 0.0

    @torch.no_grad()
    def collect(self, agent: ActorCritic) -> RolloutBatch:
        """T steps of ``agent`` in every scene; the rows where a car acted, with per-car GAE, as a
        flat batch (B = the number of car decisions in the rollout)."""
        self.live_sum = 0.0
        for t in range(self.num_steps):
            self._step(agent, t)
        last_value = agent.value(self._inputs(self.obs, self.positions, self.alive)).cpu().numpy()
        # V(s_{t+1}) of a car that went on: the next row (same slot, same car) or, after the last row, last_value.
        went_on = self.acted & ~(self.terminated | self.truncated)
        following = np.concatenate([self.b_values[1:].numpy(), last_value[None]])
        self.next_values[went_on] = following[went_on]
        adv, ret = agent_advantages(self.rewards, self.b_values.numpy(), self.next_values, self.acted,
                                    self.terminated, self.truncated, self.gamma, self.gae_lambda)
        rows = torch.as_tensor(self.acted)
        self.run.record({"charts/live_agents": self.live_sum / (self.num_steps * self.num_envs)})
        batch = (self.b_obs[rows], self.b_actions[rows], self.b_log_probs[rows], self.b_values[rows],
                 torch.as_tensor(adv)[rows], torch.as_tensor(ret)[rows])
        return RolloutBatch(*(x.to(self.device) for x in batch))

    def _inputs(self, obs: np.ndarray, positions: np.ndarray, alive: np.ndarray, query_obs: np.ndarray | None = None,
                query_positions: np.ndarray | None = None) -> torch.Tensor:
        """The policy's (M, D) inputs: the cars' observations, or with a centralised critic their
        (M, 2 D) joint observations (:func:`mean_field`; ``query_*``: other cars than ``obs``'s own)."""
        if self.radius is None:
            own = obs if query_obs is None else query_obs
            return torch.as_tensor(own, dtype=torch.float32, device=self.device)
        n, k = self.num_envs, self.num_slots
        scene = (obs.reshape(n, k, -1), positions.reshape(n, k, 2), alive.reshape(n, k))
        query = (scene[0], scene[1]) if query_obs is None else (query_obs.reshape(n, k, -1),
                                                                 query_positions.reshape(n, k, 2))
        return torch.as_tensor(mean_field(*scene, *query, self.radius), device=self.device)

    def _step(self, agent: ActorCritic, t: int) -> None:
        obs = self._inputs(self.obs, self.positions, self.alive)
        dist, value = agent.distribution_and_value(obs)
        action = sample(dist)
        self.b_obs[t], self.b_actions[t] = obs.cpu(), action.cpu()
        self.b_log_probs[t], self.b_values[t] = dist.log_prob(action).cpu(), value.cpu()
        env_action = agent.to_env(action).reshape(self.num_envs, self.num_slots, -1)
        with self.run.timing.env:
            next_obs, _, _, restarted, info = self.envs.step(env_action)
        slots = slot_arrays(info, self.num_envs, self.num_slots, self.obs_space.shape[0])
        acted = slots["acted"] & self.alive
        if restarted.any():  # a worker failed: its cars' episodes are cut where they were
            cut = np.repeat(restarted, self.num_slots) & self.alive
            slots["agent_truncated"] |= cut
            slots["agent_final_obs"][cut] = self.obs[cut]
            slots["agent_final_position"][cut] = self.positions[cut]
            acted |= cut
        check_finite_step(next_obs, slots["agent_reward"], self.run.step)
        self.rewards[t], self.acted[t] = slots["agent_reward"], acted
        self.terminated[t], self.truncated[t] = slots["agent_terminated"] & acted, slots["agent_truncated"] & acted
        self.next_values[t] = 0.0
        cut = self.truncated[t]
        if cut.any():  # a car's step limit: bootstrap from V of its last observation
            final = self._inputs(next_obs.reshape(len(self.obs), -1), slots["position"], slots["alive"].astype(bool),
                                 slots["agent_final_obs"], slots["agent_final_position"])
            self.next_values[t, cut] = agent.value(final[torch.as_tensor(cut)]).cpu().numpy()
        self._count_episodes(slots, acted)
        self.live_sum += float(acted.sum())
        self.obs = next_obs.reshape(len(self.obs), -1)
        self.alive = slots["alive"].astype(bool)  # after a restart: the new scenes' first cars
        self.positions = slots["position"]

    def _count_episodes(self, slots: dict[str, np.ndarray], acted: np.ndarray) -> None:
        """Add each car's step to its running return, length and cost; hand ended cars to the run."""
        self.running[0] += np.where(acted, slots["agent_reward"], 0.0)
        self.running[1] += acted
        self.running[2] += np.where(acted, slots["agent_cost"], 0.0)
        ended = np.flatnonzero(acted & (slots["agent_terminated"] | slots["agent_truncated"]))
        for slot in ended:
            metrics = {DRIVING_METRICS[name]: float(slots[name][slot]) for name in OUTCOMES}
            metrics["route_completion"] = float(slots["route_completion"][slot])
            metrics["cost"] = float(self.running[2, slot])
            self.run.episodes.add(Episode(int(slot) // self.num_slots, float(self.running[0, slot]),
                                          int(self.running[1, slot]), metrics))
        self.running[:, ended] = 0.0

    def close(self) -> None:
        self.envs.close()
