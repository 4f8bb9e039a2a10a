"""Building blocks of every network: initialisation, MLPs and observation encoders.

:func:`make_encoder` picks an MLP for vector observations and a CNN for images (uint8 HxWxC or
CxHxW, scaled to [0, 1] inside the network).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from drivelab.errors import DrivelabError

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
