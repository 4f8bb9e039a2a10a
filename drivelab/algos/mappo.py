"""MAPPO: PPO with a shared decentralised policy and a centralised mean-field critic (Yu et al. 2022).

Every car acts from its own observation, as in IPPO (:mod:`drivelab.algos.ippo`); only the critic,
which training alone uses, sees more: the car's observation and the mean observation of the cars
within ``neighbour_radius`` metres (CoPO's CCPPO with a mean-field critic, Peng et al. 2021). A
critic that sees the neighbours can tell "my advantage" from "the traffic around me", which lowers
the variance of the advantages where cars interact (intersections, bottlenecks). The update is
PPO's (:func:`drivelab.algos.ppo.update`) on the joint observations: the actor reads their first
half (:class:`~drivelab.training.learning.policy_nets.MeanFieldActorCritic`). Evaluation and
export use the actor alone, on each car's own observation.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym

from drivelab.algos import ippo, ppo
from drivelab.config import TrainConfig
from drivelab.errors import DrivelabError
from drivelab.training.learning.policy_nets import MeanFieldActorCritic
from drivelab.training.run import Run


@dataclass
class Params(ippo.Params):
    """IPPO's hyperparameters, plus the critic's neighbourhood."""
    neighbour_radius: float = 10.0    # metres: the cars whose mean observation the critic sees

    def validate(self) -> None:
        super().validate()
        if not self.neighbour_radius > 0:
            raise DrivelabError("config field 'mappo.neighbour_radius' must be > 0 metres, "
                                f"got {self.neighbour_radius}")


def build_policy(cfg: TrainConfig, obs_space: gym.Space, act_space: gym.Space) -> MeanFieldActorCritic:
    """One car's actor (own observation) and the mean-field critic (own and neighbours')."""
    hp = cfg.algo_params
    return MeanFieldActorCritic(obs_space, act_space, hp.hidden, hp.activation, hp.log_std_init,
                                obs_norm=hp.normalize_obs)


update = ppo.update  # PPO's update; the batch's observations are the critic's joint ones


def train(cfg: TrainConfig, run: Run) -> None:
    """IPPO's loop (:func:`drivelab.algos.ippo.train_shared_policy`) with this file's actor-critic:
    collect every car's decisions with their joint observations (``neighbour_radius``), then PPO's
    epochs on them, the actor reading the own half and the critic the whole."""
    ippo.train_shared_policy(cfg, run, build_policy)
