"""The losses, as small pure functions (shapes in docstrings), and the optimiser step and
learning-rate schedules that apply them.

Shared by every algorithm, so that each algorithm file shows only what is its own.
"""

from __future__ import annotations

import torch


def policy_gradient_loss(log_prob: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """-(1/B) sum_i log pi(a_i|s_i) * Psi_i: its gradient is minus the policy gradient estimate.

    Args:
        log_prob: (B,) log-probabilities of the taken actions (differentiable).
        weights: (B,) Psi, e.g. reward-to-go; treated as a constant.
    """
    return -(log_prob * weights.detach()).mean()


def clipped_surrogate_loss(log_prob: torch.Tensor, old_log_prob: torch.Tensor, advantages: torch.Tensor,
                           clip_coef: float) -> tuple[torch.Tensor, torch.Tensor]:
    """PPO-Clip policy loss (Schulman et al. 2017, eq. 7), negated for minimisation.

    Args: (B,) log pi_theta(a|s), (B,) log pi_old(a|s), (B,) advantages.
    Returns: (loss, ratio) with ratio (B,) = pi_theta / pi_old.
    """
    ratio = (log_prob - old_log_prob).exp()
    unclipped = ratio * advantages
    clipped = ratio.clamp(1 - clip_coef, 1 + clip_coef) * advantages
    return -torch.min(unclipped, clipped).mean(), ratio


def value_loss(values: torch.Tensor, old_values: torch.Tensor, returns: torch.Tensor,
               clip_coef: float | None) -> torch.Tensor:
    """0.5 * (V - R)^2; with ``clip_coef``, the pessimistic max with the clipped prediction
    V_old + clip(V - V_old, -eps, eps) (as in OpenAI baselines' PPO2). Shapes (B,)."""
    loss = (values - returns).pow(2)
    if clip_coef is not None:
        clipped = old_values + (values - old_values).clamp(-clip_coef, clip_coef)
        loss = torch.max(loss, (clipped - returns).pow(2))
    return 0.5 * loss.mean()


def standardize(x: torch.Tensor) -> torch.Tensor:
    """(x - mean) / (std + 1e-8) over a (B,) minibatch; a constant minibatch (no cost anywhere) gives zeros."""
    return (x - x.mean()) / (x.std() + 1e-8)


def lagrangian_advantages(advantages: torch.Tensor, cost_advantages: torch.Tensor, lam: float) -> torch.Tensor:
    """The advantage of the Lagrangian r - lambda * c, divided by 1 + lambda:
    (A_r - lambda * A_c) / (1 + lambda), all (B,).

    Maximising it with lambda >= 0 trades return for cost (Ray, Achiam & Amodei 2019, PPO-Lagrangian);
    the division keeps the size of the policy step the same whatever lambda grows to (as in their
    code and OmniSafe's PPOLag), so the clip range and learning rate keep their meaning.
    """
    return (advantages - lam * cost_advantages) / (1 + lam)


def approx_kl(log_ratio: torch.Tensor) -> torch.Tensor:
    """KL(pi_old || pi_theta) estimated by E[(rho - 1) - log rho] (Schulman 2020, "k3"):
    unbiased and never negative."""
    return ((log_ratio.exp() - 1) - log_ratio).mean()


def explained_variance(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1 - Var[target - predicted] / Var[target]: 1 is perfect, 0 no better than a constant."""
    var = target.var()  # NaN for a constant target; chosen on the device, without a host sync
    return torch.where(var > 0, 1 - (target - predicted).var() / var, torch.full_like(var, float("nan")))


def deterministic_actor_loss(q: torch.Tensor, pre_tanh: torch.Tensor, pre_tanh_l2: float = 0.0) -> torch.Tensor:
    """-E[Q(s, mu(s))] + pre_tanh_l2 * E[u(s)^2], with mu(s) = tanh(u(s)): q (B,), pre_tanh (B, A).

    The deterministic policy gradient (Silver et al. 2014) reaches u through tanh'(u) = 1 - mu^2,
    which vanishes as mu saturates at +-1: an actor pushed to a bound stays there whatever the
    critic later learns (TD3 on MetaDrive braked at throttle -0.99999 in every state). The penalty
    on u, whose gradient does not vanish there, keeps the actor off the bounds; like the action
    penalty of Andrychowicz et al. 2017 (HER), but on u, so it also pulls a saturated actor back.
    """
    loss = -q.mean()
    if pre_tanh_l2:
        loss = loss + pre_tanh_l2 * pre_tanh.pow(2).mean()
    return loss


def saturated_share(pre_tanh: torch.Tensor) -> torch.Tensor:
    """Share of the actor's outputs at a bound, |tanh(u)| > 0.995 (|u| > 3): (B, A) -> scalar.
    Logged as ``charts/actor_saturation``; near 1, the actor has stopped learning."""
    return (pre_tanh.detach().abs() > 3.0).float().mean()


# ---- applying a loss ----------------------------------------------------------------------
