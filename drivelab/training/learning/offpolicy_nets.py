"""The networks of DDPG, TD3 and SAC: E Q-critics evaluated in one batched pass, a deterministic
or squashed-Gaussian actor, :class:`OffPolicyAgent` that holds them with the encoder, and the
target-network helpers (:func:`make_target`, :func:`polyak_update`, :func:`frozen`).

Actions are in the policy's [-1, 1] units (actors end in tanh); ``OffPolicyAgent.to_env`` maps
them affinely onto the env's Box bounds, so replay, critics and noise never see env units. Image
observations go through one CNN encoder that belongs to the critic and is trained by the critic
loss only; the actor reads its features detached (as in SAC-AE, Yarats et al. 2021), so the
actor's gradient cannot degrade the representation the critic relies on.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Iterator, Sequence

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from drivelab.errors import DrivelabError
from drivelab.training.learning.layers import CNNEncoder, activation, is_image_space, mlp
from drivelab.training.learning.precision import in_float32

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0   # the squashed-Gaussian actor's log sigma is clamped to this range


class EnsembleLinear(nn.Module):
    """E independent linear layers applied in one batched matmul: (E, B, in) -> (E, B, out).

    Twin (or single) critics are one module, so both Q-values come from one pass instead of
    one pass per critic. An input with e < E members, (e, B, in), goes through the first e."""

    def __init__(self, ensemble: int, in_dim: int, out_dim: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(ensemble, in_dim, out_dim))
        self.bias = nn.Parameter(torch.empty(ensemble, 1, out_dim))
        bound = 1 / math.sqrt(in_dim)  # nn.Linear's default initialisation, per member
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        members = x.shape[0]
        return torch.baddbmm(self.bias[:members], x, self.weight[:members])


class EnsembleBatchNorm(nn.Module):
    """Batch normalisation of each of E members on its own: (E, B, H) -> (E, B, H), each feature
    of each member scaled to zero mean and unit variance over the batch, then by its own learned
    gain and bias (Ioffe & Szegedy 2015). In train mode it uses the batch's statistics and moves
    the running ones toward them by ``momentum``; in eval mode it uses the running ones. An input
    with e < E members goes through the first e.

    The learned bias matters here: after a zero-mean layer, a critic's output could only shift its
    mean through the last layer's single bias, one learning-rate step per update, far too slowly
    for returns of -100s: without the learned bias, Q moves by about one learning rate per update.
    """

    def __init__(self, ensemble: int, width: int, momentum: float = 0.01, eps: float = 1e-3):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(ensemble, 1, width))
        self.bias = nn.Parameter(torch.zeros(ensemble, 1, width))
        self.register_buffer("running_mean", torch.zeros(ensemble, 1, width))
        self.register_buffer("running_var", torch.ones(ensemble, 1, width))
        self.momentum, self.eps = momentum, eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        members = x.shape[0]
        if self.training:
            var, mean = torch.var_mean(x, dim=1, keepdim=True, correction=0)
            with torch.no_grad():
                self.running_mean[:members].lerp_(mean, self.momentum)
                unbiased = var * (x.shape[1] / max(x.shape[1] - 1, 1))
                self.running_var[:members].lerp_(unbiased, self.momentum)
        else:
            mean, var = self.running_mean[:members], self.running_var[:members]
        return (x - mean) * torch.rsqrt(var + self.eps) * self.weight[:members] + self.bias[:members]


class Critics(nn.Module):
    """E Q-networks Q_e(s, a) over features of s: forward returns (E, B).

    ``layer_norm`` normalises each hidden layer before its activation (Ball et al. 2023, "RLPD":
    it bounds how far Q can extrapolate to actions the buffer never saw). The norm has no learned
    gain or bias, so the E critics still share no parameters.

    ``batch_norm`` normalises the input of every linear layer, (s, a) included, over the batch
    (CrossQ, Bhatt et al. 2024): the train-mode pass must then see (s, a) and (s', a') together,
    so that both are normalised with the same statistics (see ``drivelab.algos.td3``).
    """

    def __init__(self, feature_dim: int, act_dim: int, hidden: Sequence[int], act: str, ensemble: int = 2,
                 layer_norm: bool = False, batch_norm: bool = False):
        super().__init__()
        if layer_norm and batch_norm:
            raise DrivelabError("the critics take layer norm or batch norm (CrossQ), not both")
        layers: list[nn.Module] = []
        width = feature_dim + act_dim
        for h in hidden:
            if batch_norm:
                layers.append(EnsembleBatchNorm(ensemble, width))
            layers.append(EnsembleLinear(ensemble, width, h))
            if layer_norm:
                layers.append(nn.LayerNorm(h, elementwise_affine=False))
            layers.append(activation(act)())
            width = h
        if batch_norm:
            layers.append(EnsembleBatchNorm(ensemble, width))
        layers.append(EnsembleLinear(ensemble, width, 1))
        self.net = nn.Sequential(*layers)
        self.ensemble = ensemble

    def forward(self, features: torch.Tensor, actions: torch.Tensor, members: int | None = None) -> torch.Tensor:
        """Q_e(s, a) for e < ``members`` (all E by default): (members, B). TD3's actor step needs Q_1 only."""
        x = torch.cat([features, actions], dim=-1)
        hidden = self.net[:-1](x.unsqueeze(0).expand(members or self.ensemble, -1, -1))
        return in_float32(self.net[-1], hidden).squeeze(-1)


class DeterministicActor(nn.Module):
    """mu(s) = tanh(u(s)) in [-1, 1]^A (DDPG, TD3)."""

    def __init__(self, feature_dim: int, act_dim: int, hidden: Sequence[int], act: str):
        super().__init__()
        self.net = nn.Sequential(mlp(feature_dim, hidden, act), nn.Linear(hidden[-1], act_dim), nn.Tanh())

    def pre_tanh(self, features: torch.Tensor) -> torch.Tensor:
        """u(s), (B, A): the output before the tanh (for a penalty that keeps it unsaturated)."""
        return in_float32(self.net[1], self.net[0](features))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.pre_tanh(features))


class SquashedGaussianActor(nn.Module):
    """a = tanh(u), u ~ N(mu(s), sigma(s)^2) (SAC)."""

    def __init__(self, feature_dim: int, act_dim: int, hidden: Sequence[int], act: str):
        super().__init__()
        self.trunk = mlp(feature_dim, hidden, act)
        self.mean = nn.Linear(hidden[-1], act_dim)
        self.log_std = nn.Linear(hidden[-1], act_dim)

    def mean_action(self, features: torch.Tensor) -> torch.Tensor:
        """tanh(mean): the deterministic action, (B, A) in [-1, 1]."""
        return torch.tanh(self.mean(self.trunk(features)))

    def forward(self, features: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns (action (B, A) in [-1, 1], log pi(action|s) (B,))."""
        h = self.trunk(features)
        mean = in_float32(self.mean, h)
        # Soft clamp of log sigma into [LOG_STD_MIN, LOG_STD_MAX] (keeps gradients everywhere).
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(in_float32(self.log_std, h)) + 1)
        u = mean if deterministic else mean + log_std.exp() * torch.randn_like(mean)  # reparameterised
        return torch.tanh(u), squashed_gaussian_log_prob(u, mean, log_std)


def squashed_gaussian_log_prob(u: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log pi(tanh(u)) for u ~ N(mean, exp(log_std)^2), summed over action dims: shapes (B, A) -> (B,).

    Change of variables a = tanh(u) (Haarnoja et al. 2018, appendix C, eq. 21):
        log pi(a|s) = log N(u; mean, sigma) - sum_i log(1 - tanh(u_i)^2),
    with log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), which stays finite where tanh saturates.
    """
    normal = -0.5 * ((u - mean) / log_std.exp()).pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    log_det = 2 * (math.log(2) - u - nn.functional.softplus(-2 * u))
    return (normal - log_det).sum(-1)


class OffPolicyAgent(nn.Module):
    """Encoder + actor + E critics. ``act``/``to_env`` make it a policy for ``drivelab eval``.

    Vector observations are flattened (each MLP learns its own features); uint8 images share
    one CNN, trained by the critics (see the module docstring).

    ``cost_critics=1`` adds ``cost_critic``, one Q-network of the same shape that estimates the
    discounted cost Q_c(s, a) (SAC-Lagrangian). It reads the features detached, like the actor:
    the encoder stays the reward critics'. Built after the others, so an agent without it draws
    the same initial weights as before.
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int], act: str,
                 stochastic: bool, critics: int = 2, critic_layer_norm: bool = False,
                 critic_batch_norm: bool = False, cost_critics: int = 0):
        super().__init__()
        if not (isinstance(act_space, gym.spaces.Box) and len(act_space.shape) == 1):
            raise DrivelabError(f"DDPG, TD3 and SAC need a continuous 1-D Box action space, not {act_space} "
                                "(for discrete actions use ppo, a2c or grpo; drop env.action_grid)")
        if is_image_space(obs_space):
            self.encoder: nn.Module = CNNEncoder(obs_space)
            feature_dim = self.encoder.out_dim
        else:
            self.encoder = nn.Flatten()
            feature_dim = int(np.prod(obs_space.shape))
        act_dim = act_space.shape[0]
        actor_cls = SquashedGaussianActor if stochastic else DeterministicActor
        self.actor = actor_cls(feature_dim, act_dim, hidden, act)
        self.critic = Critics(feature_dim, act_dim, hidden, act, ensemble=critics, layer_norm=critic_layer_norm,
                              batch_norm=critic_batch_norm)
        self.stochastic = stochastic
        if cost_critics:
            self.cost_critic = Critics(feature_dim, act_dim, hidden, act, ensemble=cost_critics,
                                       layer_norm=critic_layer_norm)
        # [-1, 1] -> [low, high]
        low, high = (torch.tensor(b, dtype=torch.float32) for b in (act_space.low, act_space.high))
        self.register_buffer("action_scale", (high - low) / 2)
        self.register_buffer("action_bias", (high + low) / 2)

    def compile_networks(self) -> None:
        """torch.compile the forward passes (state_dict keys stay the same, so checkpoints too)."""
        for module in (self.encoder, self.actor, self.critic, *([self.cost_critic] if self.has_cost_critic else [])):
            module.forward = torch.compile(module.forward)

    @property
    def has_cost_critic(self) -> bool:
        return hasattr(self, "cost_critic")

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        return self.encoder(obs if obs.dtype == torch.uint8 else obs.float())

    def policy(self, features: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(action in [-1, 1] (B, A), log-prob (B,) or None for deterministic actors)."""
        if self.stochastic:
            return self.actor(features, deterministic)
        return self.actor(features), None

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        return self.policy(self.features(obs), deterministic)[0]

    def to_env(self, action: torch.Tensor) -> np.ndarray:
        """[-1, 1] actions (on any device: the trainers' come from numpy) -> the env's Box bounds."""
        action = torch.as_tensor(action, device=self.action_scale.device)
        return (action * self.action_scale + self.action_bias).cpu().numpy()

    def deterministic_action(self, obs: torch.Tensor) -> torch.Tensor:
        """(B, A) env action of the deterministic policy: mu(s), or tanh(mean) for SAC."""
        features = self.features(obs)
        action = self.actor.mean_action(features) if self.stochastic else self.actor(features)
        return action * self.action_scale + self.action_bias


@contextlib.contextmanager
def frozen(module: nn.Module) -> Iterator[nn.Module]:
    """Inside the block ``module``'s parameters build no gradient graph. The actor's step goes
    through the critics for dQ/da, but never updates them: freezing them saves computing their
    weight gradients, about a third of that step's critic work (as Spinning Up's SAC and TD3 do)."""
    trainable = [p for p in module.parameters() if p.requires_grad]
    for p in trainable:
        p.requires_grad_(False)
    try:
        yield module
    finally:
        for p in trainable:
            p.requires_grad_(True)


def polyak_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- (1 - tau) * target + tau * source, for every parameter, in one fused op."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def make_target(module: nn.Module) -> nn.Module:
    """A frozen copy that only Polyak averaging changes."""
    target = copy.deepcopy(module)
    target.requires_grad_(False)
    return target
