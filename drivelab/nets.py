"""Networks shared by every algorithm: observation encoders and policy heads.

* :func:`make_encoder` picks an MLP for vector observations and a CNN for images
  (uint8 HxWxC or CxHxW, scaled to [0, 1] inside the network).
* :class:`Policy` turns encoder features into a ``torch.distributions`` object:
  ``Categorical`` for ``Discrete`` actions and a diagonal Gaussian (state-independent
  log-std, as in PPO/REINFORCE baselines) for ``Box`` actions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical, Distribution, Independent, Normal

from drivelab.errors import DrivelabError

# Distribution argument checks cost tens of microseconds per call, i.e. a noticeable share of an
# env step in a rollout loop; drivelab's networks produce valid parameters by construction.
torch.distributions.Distribution.set_default_validate_args(False)

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "silu": nn.SiLU}


def layer_init(layer: nn.Module, gain: float = math.sqrt(2), bias: float = 0.0) -> nn.Module:
    """Orthogonal weights and constant bias (Engstrom et al. 2020, "Implementation Matters")."""
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.constant_(layer.bias, bias)
    return layer


def activation(name: str) -> type[nn.Module]:
    if name not in ACTIVATIONS:
        raise DrivelabError(f"unknown activation '{name}' (choose from {', '.join(ACTIVATIONS)})")
    return ACTIVATIONS[name]


def mlp(in_dim: int, hidden: Sequence[int], act: str = "tanh") -> nn.Sequential:
    """Linear-activation stack; output size is hidden[-1] (in_dim if hidden is empty)."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [layer_init(nn.Linear(in_dim, width)), activation(act)()]
        in_dim = width
    return nn.Sequential(*layers)


def is_image_space(space: gym.Space) -> bool:
    return isinstance(space, gym.spaces.Box) and space.dtype == np.uint8 and len(space.shape) == 3


class CNNEncoder(nn.Module):
    """The Nature-DQN convolution stack (Mnih et al. 2015) for uint8 images, then a linear layer.

    Input: (B, H, W, C) or (B, C, H, W) uint8 (channels-last is detected from the space: the
    smallest of the first and last dims is taken as channels). Output: (B, features).
    """

    def __init__(self, space: gym.spaces.Box, features: int = 512):
        super().__init__()
        h, w, c = space.shape
        self.channels_last = c <= h
        if not self.channels_last:
            c, h, w = space.shape
        self.convs = nn.Sequential(
            layer_init(nn.Conv2d(c, 32, 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            n_flat = self.convs(torch.zeros(1, c, h, w)).shape[1]
        self.fc = nn.Sequential(layer_init(nn.Linear(n_flat, features)), nn.ReLU())
        self.out_dim = features

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = obs.float() / 255.0
        if self.channels_last:
            x = x.permute(0, 3, 1, 2)
        return self.fc(self.convs(x))


class MLPEncoder(nn.Module):
    """Flattens (B, *shape) observations and applies an MLP. Output: (B, hidden[-1])."""

    def __init__(self, space: gym.spaces.Box, hidden: Sequence[int], act: str = "tanh"):
        super().__init__()
        in_dim = int(np.prod(space.shape))
        self.net = mlp(in_dim, hidden, act)
        self.out_dim = hidden[-1] if hidden else in_dim

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs.float().flatten(1))


def make_encoder(space: gym.Space, hidden: Sequence[int], act: str = "tanh") -> nn.Module:
    if not isinstance(space, gym.spaces.Box):
        raise DrivelabError(f"observation space {space} is not supported (need a Box: vector or uint8 image)")
    if is_image_space(space):
        return CNNEncoder(space)
    return MLPEncoder(space, hidden, act)


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
            self.register_buffer("low", torch.as_tensor(act_space.low, dtype=torch.float32))
            self.register_buffer("high", torch.as_tensor(act_space.high, dtype=torch.float32))
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
        if self.discrete:
            return action.cpu().numpy()
        return torch.maximum(torch.minimum(action, self.high), self.low).cpu().numpy()


class ActorCritic(nn.Module):
    """Policy pi(a|s) and, optionally, value V(s), for the on-policy family (A2C, PPO, GRPO).

    Actor and critic have separate encoders (sharing one lets the value loss's scale disturb the
    policy; Andrychowicz et al. 2021 found separate networks better on continuous control).
    With ``obs_norm`` both see observations standardised by running statistics that are saved
    with the weights (vector observations only; images are scaled to [0, 1] by the CNN).
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int] = (64, 64),
                 act: str = "tanh", log_std_init: float = 0.0, obs_norm: bool = False, critic: bool = True):
        super().__init__()
        from drivelab.normalize import RunningMeanStd

        self.obs_rms = RunningMeanStd(obs_space.shape) if obs_norm and not is_image_space(obs_space) else None
        self.actor = Policy(obs_space, act_space, hidden, act, log_std_init)
        self.discrete = self.actor.discrete
        self.critic = None
        if critic:
            encoder = make_encoder(obs_space, hidden, act)
            self.critic = nn.Sequential(encoder, layer_init(nn.Linear(encoder.out_dim, 1), gain=1.0))

    def prepare(self, obs: torch.Tensor) -> torch.Tensor:
        return self.obs_rms.normalize(obs.float()) if self.obs_rms is not None else obs

    def distribution(self, obs: torch.Tensor) -> Distribution:
        return self.actor.distribution(self.prepare(obs))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """(B,) state values."""
        return self.critic(self.prepare(obs)).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        return self.actor.act(self.prepare(obs), deterministic)

    def to_env(self, action: torch.Tensor) -> np.ndarray:
        return self.actor.to_env(action)
