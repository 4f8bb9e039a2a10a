"""Networks shared by every algorithm: observation encoders, policy heads, critics.

* :func:`make_encoder` picks an MLP for vector observations and a CNN for images
  (uint8 HxWxC or CxHxW, scaled to [0, 1] inside the network).
* :class:`Policy` turns encoder features into a ``torch.distributions`` object:
  ``Categorical`` for ``Discrete`` actions and a diagonal Gaussian (state-independent
  log-std, as in PPO/REINFORCE baselines) for ``Box`` actions; :class:`ActorCritic` adds V(s).
* :class:`OffPolicyAgent` (DDPG, TD3, SAC): a deterministic or squashed-Gaussian actor and E
  Q-critics evaluated in one batched pass; :func:`make_target` and :func:`polyak_update` for
  the target networks.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical, Distribution, Independent, Normal

from drivelab.errors import DrivelabError
from drivelab.training.losses import linear_decay
from drivelab.training.normalize import RunningMeanStd

# Distribution argument checks cost tens of microseconds per call, i.e. a noticeable share of an
# env step in a rollout loop; drivelab's networks produce valid parameters by construction.
torch.distributions.Distribution.set_default_validate_args(False)

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "silu": nn.SiLU}


@dataclass
class PolicyNetParams:
    """Network hyperparameters of the policy-gradient family (REINFORCE, A2C, PPO, GRPO); each
    algorithm's ``Params`` extends it."""
    hidden: list[int] = field(default_factory=lambda: [64, 64])  # hidden layer widths
    activation: str = "tanh"          # tanh | relu | elu | silu
    log_std_init: float = 0.0     # initial log std of the Gaussian policy (continuous actions)
    # Upper bound on the log std, lowered linearly from log_std_init to this over the run (None:
    # the std is learned freely). The deterministic policy (the mean) is what gets evaluated;
    # when the std stays large, the clipped, noisy actions it was trained with behave differently.
    log_std_final: float | None = None

    def validate(self) -> None:
        if self.log_std_final is not None and self.log_std_final > self.log_std_init:
            raise DrivelabError(f"config field 'log_std_final' ({self.log_std_final}) must be <= "
                                f"'log_std_init' ({self.log_std_init})")


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
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int] = (64, 64),
                 act: str = "tanh", log_std_init: float = 0.0, obs_norm: bool = False, critic: bool = True):
        super().__init__()
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


# ---------------------------------------------------------------------------------------------
# Off-policy networks (DDPG, TD3, SAC): actions in the policy's [-1, 1] units (actors end in
# tanh); ``OffPolicyAgent.to_env`` maps them affinely onto the env's Box bounds, so replay,
# critics and noise never see env units. Image observations go through one CNN encoder that
# belongs to the critic and is trained by the critic loss only; the actor reads its features
# detached (as in SAC-AE, Yarats et al. 2021), so the actor's gradient cannot degrade the
# representation the critic relies on.


def in_float32(layer: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """layer(x) computed in float32, also inside a bfloat16 autocast region (``bf16_updates``).

    bfloat16 keeps 8 bits of mantissa: a Q-value near 300 would be rounded to steps of 2, larger
    than a step's reward, so the output layers (Q, the actor's mean and log sigma) stay float32
    while the hidden layers, where the time goes, run in bfloat16. Outside autocast (acting,
    evaluation) it is layer(x), without the context's cost."""
    device = x.device.type
    if not (torch.amp.is_autocast_available(device) and torch.is_autocast_enabled(device)):
        return layer(x)
    with torch.autocast(device, enabled=False):
        return layer(x.float())


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
    for returns of -100s (measured on Pendulum: without them Q stayed near -lr * updates).
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


LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


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
    """

    def __init__(self, obs_space: gym.Space, act_space: gym.Space, hidden: Sequence[int], act: str,
                 stochastic: bool, critics: int = 2, critic_layer_norm: bool = False,
                 critic_batch_norm: bool = False):
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
        # [-1, 1] -> [low, high]
        low, high = (torch.tensor(b, dtype=torch.float32) for b in (act_space.low, act_space.high))
        self.register_buffer("action_scale", (high - low) / 2)
        self.register_buffer("action_bias", (high + low) / 2)

    def compile_networks(self) -> None:
        """torch.compile the forward passes (state_dict keys stay the same, so checkpoints too)."""
        for module in (self.encoder, self.actor, self.critic):
            module.forward = torch.compile(module.forward)

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
