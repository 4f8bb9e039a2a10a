"""IPPO: PPO with one policy shared by every car of a multi-agent scene (de Witt et al. 2020).

The baseline of MetaDrive's multi-agent benchmark (CoPO, Peng et al. 2021): each car decides
from its own observation (its lidar and navigation, 91 numbers) with the same network; each car's
trajectory is its own for GAE, across the arrivals, crashes and respawns of one scene episode
(:class:`drivelab.training.collection.agents.AgentRolloutCollector`). The update is PPO's own
(:func:`drivelab.algos.ppo.update`: clipped surrogate, value loss, entropy bonus) on the car
decisions of the rollout, all cars pooled: parameter sharing makes one car's experience train
every car.

``steps`` counts env steps of the scenes (one step moves every car), as CoPO counts them; a
rollout holds ``num_steps x num_envs`` of them and one sample per live car and step.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import torch

from drivelab.algos import ppo
from drivelab.config import EnvConfig, TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.collection.agents import AgentRolloutCollector
from drivelab.training.learning.optim import linear_decay, set_learning_rate
from drivelab.training.learning.policy_nets import ActorCritic, limit_log_std
from drivelab.training.run import Run


@dataclass
class Params(ppo.Params):
    """PPO's hyperparameters (:class:`drivelab.algos.ppo.Params`), for every car at once."""
    multiagent = True  # a class attribute, not a config field: this algorithm trains multi-agent scenes

    def validate(self) -> None:
        super().validate()
        if self.act_in_workers or self.normalize_reward:
            raise DrivelabError("config fields 'ippo.act_in_workers' and 'ippo.normalize_reward' are single-agent "
                                "options; set them to false")

    def validate_env(self, env: EnvConfig) -> None:
        pass  # the number of samples depends on the live cars; a minibatch holds at least one car step


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> ActorCritic:
    """One car's policy and value function (every car shares them)."""
    return ppo.build_policy(cfg, obs_space, act_space)


update = ppo.update  # the PPO update, on the pooled decisions of every car


def train(cfg: TrainConfig, run: Run) -> None:
    train_shared_policy(cfg, run, build_policy)


def train_shared_policy(cfg: TrainConfig, run: Run,
                        build: Callable[[TrainConfig, gym.Space, gym.Space], ActorCritic]) -> None:
    """The loop of a policy shared by every car (IPPO here; MAPPO with its centralised critic)."""
    hp: Params = cfg.algo_params
    collector = AgentRolloutCollector(cfg, run)  # MAPPO's neighbour_radius: joint observations for its critic
    agent = build(cfg, collector.obs_space, collector.act_space).to(run.device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=hp.lr, eps=1e-5)
    own = collector.obs_space.shape[0]  # a sample's own observation: the first `own` numbers of batch.obs
    run.start({"policy": agent}, {"policy": optimizer}, policy=agent)
    try:
        while not run.done:
            if hp.anneal_lr:
                set_learning_rate(optimizer, linear_decay(hp.lr, run.step, cfg.steps))
            std_log = limit_log_std(agent.actor, hp, run.step, cfg.steps)
            # 1. T steps of every scene; each car's decisions with its own GAE(lambda).
            batch = collector.collect(agent)
            # 2. PPO's epochs of clipped minibatch steps on the pooled decisions.
            with run.timing.update:
                stats = update(agent, optimizer, batch, hp)
            run.record(stats)
            if agent.obs_rms is not None:  # statistics of the cars' own observations
                agent.obs_rms.update(batch.obs[:, :own].float())
            run.record({"charts/lr": optimizer.param_groups[0]["lr"], "charts/car_decisions": float(len(batch.obs)),
                        **std_log})
            # 3. Log and checkpoint when due (steps: scene steps).
            run.end_iteration(collector.steps_per_rollout)
    finally:
        collector.close()
