"""The networks of the policy-gradient family (REINFORCE, A2C, PPO, GRPO).

:class:`Policy` turns encoder features into a ``torch.distributions`` object: ``Categorical`` for
``Discrete`` actions and a diagonal Gaussian (state-independent log-std, as in PPO/REINFORCE
baselines) for ``Box`` actions; :class:`ActorCritic` adds V(s), and for the constrained algorithms
(PPO-Lagrangian) a cost critic V_c(s). :func:`limit_log_std` applies the falling upper bound of
``log_std_final``.
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical, Distribution, Independent, Normal

from drivelab.errors import DrivelabError
from drivelab.training.learning.hyperparams import PolicyNetParams
from drivelab.training.learning.layers import is_image_space, layer_init, make_encoder
from drivelab.training.learning.normalize import RunningMeanStd
from drivelab.training.learning.optim import linear_decay

# Distribution argument checks cost tens of microseconds per call, i.e. a noticeable share of an
# env step in a rollout loop; drivelab's networks produce valid parameters by construction.
torch.distributions.Distribution.set_default_validate_args(False)


class Policy(nn.Module):
    """A stochastic policy pi(a|s) for Discrete or Box action spaces.

    ``distribution(obs)`` returns a ``torch.distributions.Distribution`` whose ``log_prob`` and
    ``entropy`` have shape (B,) (the Gaussian is ``Independent`` over action dims).
    Continuous actions are sampled unbounded; :meth:`to_env` clips them to the action bounds
    (the log-prob is of the unclipped sample, as in CleanRL's PPO).
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int] = (64, 64),
                 act: str = "tanh", log_std_init: float = 0.0):
        super().__init__()
        self.encoder = make_encoder(obs_space, hidden, act)
        self.discrete = isinstance(act_space, gym.spaces.Discrete)
        if self.discrete:
            # Small output gain: near-uniform initial policy (Andrychowicz et al. 2021).
            self.head = layer_init(nn.Linear(self.encoder.out_dim, int(act_space.n)), gain=0.01)
        elif isinstance(act_space, gym.spaces.Box) and len(act_space.shape) == 1:
            dim = act_space.shape[0]
            self.head = layer_init(nn.Linear(self.encoder.out_dim, dim), gain=0.01)
            self.log_std = nn.Parameter(torch.full((dim,), float(log_std_init)))
            self.register_buffer("low", torch.tensor(act_space.low, dtype=torch.float32))
            self.register_buffer("high", torch.tensor(act_space.high, dtype=torch.float32))
        else:
            raise DrivelabError(f"action space {act_space} is not supported (need Discrete or a 1-D Box)")

    def distribution(self, obs: torch.Tensor) -> Distribution:
        out = self.head(self.encoder(obs))
        if self.discrete:
            return Categorical(logits=out)
        return Independent(Normal(out, self.log_std.exp().expand_as(out)), 1)

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        """Actions for a batch of observations: sampled, or the mode when deterministic."""
        dist = self.distribution(obs)
        if not deterministic:
            return dist.sample()
        return dist.probs.argmax(-1) if self.discrete else dist.mean

    def to_env(self, action: torch.Tensor) -> np.ndarray:
        """Actions as the env expects them: ints for Discrete, clipped floats for Box."""
        return self.env_action(action).cpu().numpy()

    def env_action(self, action: torch.Tensor) -> torch.Tensor:
        """:meth:`to_env` as a tensor op (traceable for export): clip Box actions to the bounds."""
        return action if self.discrete else torch.maximum(torch.minimum(action, self.high), self.low)

    def deterministic_action(self, obs: torch.Tensor) -> torch.Tensor:
        """The env action of the mode of pi(.|obs), without a distribution object (exportable):
        (B,) int64 for Discrete, (B, A) for Box."""
        out = self.head(self.encoder(obs))
        return out.argmax(-1) if self.discrete else self.env_action(out)


def sample(dist: Distribution, generator: torch.Generator | None = None) -> torch.Tensor:
    """A sample of an on-policy :class:`Policy`'s distribution from ``generator`` (None: torch's
    global generator, drawing exactly what ``dist.sample()`` draws)."""
    if generator is None:
        return dist.sample()
    if isinstance(dist, Categorical):
        return torch.multinomial(dist.probs.reshape(-1, dist.probs.shape[-1]), 1, True, generator=generator
                                 ).reshape(dist.probs.shape[:-1])
    normal = dist.base_dist  # Independent(Normal)
    return torch.normal(normal.loc, normal.scale, generator=generator)


def limit_log_std(policy: Policy, hp: PolicyNetParams, step: int, total: int) -> dict[str, float]:
    """Project a Gaussian policy's log std onto its scheduled upper bound (``hp.log_std_final``),
    which falls linearly from ``log_std_init`` at step 0 to ``log_std_final`` at ``total``.

    Called once per iteration before the rollout, so rollout and update share one std. Returns
    ``{"charts/policy_std": mean std}`` for the log ({} for discrete actions). Because the
    parameter itself is clipped (projected gradient descent), the saved weights hold the std
    that was used (moved by at most the last update), and resuming recomputes the same bound
    from the step.
    """
    if policy.discrete:
        return {}
    with torch.no_grad():
        if hp.log_std_final is not None:
            gap = linear_decay(hp.log_std_init - hp.log_std_final, step, total)  # init-final at 0, 0 at total
            policy.log_std.clamp_(max=hp.log_std_final + gap)
        return {"charts/policy_std": float(policy.log_std.exp().mean())}


class ActorCritic(nn.Module):
    """Policy pi(a|s) and, optionally, value V(s), for the on-policy family (A2C, PPO, GRPO).

    Actor and critic have separate encoders (sharing one lets the value loss's scale disturb the
    policy; Andrychowicz et al. 2021 found separate networks better on continuous control).
    With ``obs_norm`` both see observations standardised by running statistics that are saved
    with the weights (vector observations only; images are scaled to [0, 1] by the CNN).
    With ``cost_critic`` a third network of the critic's shape estimates the expected discounted
    cost V_c(s) (PPO-Lagrangian); acting, evaluation and export never use it.
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int] = (64, 64),
                 act: str = "tanh", log_std_init: float = 0.0, obs_norm: bool = False, critic: bool = True,
                 cost_critic: bool = False):
        super().__init__()
        self.obs_rms = RunningMeanStd(obs_space.shape) if obs_norm and not is_image_space(obs_space) else None
        self.actor = Policy(obs_space, act_space, hidden, act, log_std_init)
        self.discrete = self.actor.discrete
        self.critic = _value_net(obs_space, hidden, act) if critic else None
        # built after the others, so the actor's and critic's initial weights do not depend on it
        self.cost_critic = _value_net(obs_space, hidden, act) if cost_critic else None

    def prepare(self, obs: torch.Tensor) -> torch.Tensor:
        return self.obs_rms.normalize(obs.float()) if self.obs_rms is not None else obs

    def distribution(self, obs: torch.Tensor) -> Distribution:
        return self.actor.distribution(self.prepare(obs))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """(B,) state values."""
        return self.critic(self.prepare(obs)).squeeze(-1)

    def cost_value(self, obs: torch.Tensor) -> torch.Tensor:
        """(B,) cost values V_c(s) (needs ``cost_critic``)."""
        return self.cost_critic(self.prepare(obs)).squeeze(-1)

    def distribution_and_value(self, obs: torch.Tensor) -> tuple[Distribution, torch.Tensor]:
        """pi(.|obs) and the (B,) values, normalising the observations once (the rollout's step)."""
        prepared = self.prepare(obs)
        return self.actor.distribution(prepared), self.critic(prepared).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        return self.actor.act(self.prepare(obs), deterministic)

    def to_env(self, action: torch.Tensor) -> np.ndarray:
        return self.actor.to_env(action)

    def deterministic_action(self, obs: torch.Tensor) -> torch.Tensor:
        return self.actor.deterministic_action(self.prepare(obs))


class MeanFieldActorCritic(ActorCritic):
    """A decentralised actor pi(a | o_i) and a centralised critic V(o_i, mean of the neighbours' o_j)
    (MAPPO, Yu et al. 2022, with the mean-field critic input of CoPO's CCPPO, Peng et al. 2021).

    The critic's input, the *joint* observation, is ``(B, 2 D)``: the car's own observation, then
    the mean observation of the cars within a radius (zeros without neighbours). Acting, evaluation
    and export use the actor alone, on the car's own ``(B, D)`` observation: every car still drives
    from what it sees. With ``obs_norm`` both halves are standardised by the own observations'
    running statistics (the mean of standardised observations is the standardised mean).
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int] = (64, 64),
                 act: str = "tanh", log_std_init: float = 0.0, obs_norm: bool = False):
        super().__init__(obs_space, act_space, hidden, act, log_std_init, obs_norm, critic=False)
        self.obs_dim = int(obs_space.shape[0])
        joint = gym.spaces.Box(np.concatenate([obs_space.low, obs_space.low]),
                               np.concatenate([obs_space.high, obs_space.high]), dtype=obs_space.dtype)
        self.critic = _value_net(joint, hidden, act)

    def prepare_joint(self, joint: torch.Tensor) -> torch.Tensor:
        if self.obs_rms is None:
            return joint
        own, neighbours = joint[..., :self.obs_dim], joint[..., self.obs_dim:]
        return torch.cat([self.obs_rms.normalize(own.float()), self.obs_rms.normalize(neighbours.float())], dim=-1)

    def value(self, joint: torch.Tensor) -> torch.Tensor:
        """(B,) V of ``(B, 2 D)`` joint observations."""
        return self.critic(self.prepare_joint(joint)).squeeze(-1)

    def distribution_and_value(self, joint: torch.Tensor) -> tuple[Distribution, torch.Tensor]:
        """pi(.|own observation) and the (B,) values of ``(B, 2 D)`` joint observations."""
        return self.distribution(joint[..., :self.obs_dim]), self.value(joint)


def _value_net(obs_space: gym.Space, hidden: Sequence[int], act: str) -> nn.Module:
    """An encoder and a linear head: (B, *obs_shape) -> (B, 1)."""
    encoder = make_encoder(obs_space, hidden, act)
    return nn.Sequential(encoder, layer_init(nn.Linear(encoder.out_dim, 1), gain=1.0))
