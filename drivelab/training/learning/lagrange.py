"""The Lagrange multiplier of constrained RL: maximise the return subject to the mean episode cost
J_c <= d (``cost_limit``) by maximising, over the policy, the Lagrangian J_r - lambda (J_c - d)
while lambda >= 0 rises as long as the constraint is violated (Altman 1999, "Constrained Markov
Decision Processes"; Ray, Achiam & Amodei 2019, "Benchmarking Safe Exploration in Deep RL").

Two updates of lambda from the measured cost J_c of the episodes that finished since the last one:

* ``gradient``: projected ascent on the dual, lambda <- clip(lambda + lr (J_c - d), 0, max).
  It integrates the violation only, so lambda overshoots and the cost oscillates around d.
* ``pid`` (Stooke, Achiam & Abbeel 2020, "Responsive Safety in Reinforcement Learning by PID
  Lagrangian Methods", Algorithm 2): with e = J_c - d,
  I <- max(0, I + Ki e);  lambda = clip(Kp EMA(e) + I + Kd max(0, EMA(J_c) - EMA(J_c) delay updates ago), 0, max).
  The proportional and derivative terms react to a rising cost before the integral has grown.

The state lives in float64 buffers, so it is checkpointed with the run's modules and a resumed
run continues bit-exactly.
"""

from __future__ import annotations

import torch
from torch import nn

from drivelab.training.learning.hyperparams import ConstraintParams


class LagrangeMultiplier(nn.Module):
    """lambda >= 0 and the state of its update (see the module docstring). ``measured_cost(...)``
    turns the episode tracker's running totals into J_c of the episodes since the last call."""

    def __init__(self, hp: ConstraintParams):
        super().__init__()
        self.hp = hp
        as64 = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
        self.register_buffer("value", as64(hp.lagrange_init))           # lambda
        self.register_buffer("integral", as64(hp.lagrange_init))        # pid: I
        self.register_buffer("error_ema", as64(0.0))                    # pid: EMA of e
        self.register_buffer("cost_ema", as64(0.0))                     # pid: EMA of J_c
        self.register_buffer("cost_history", torch.zeros(hp.pid_d_delay, dtype=torch.float64))
        self.register_buffer("updates", torch.tensor(0, dtype=torch.int64))
        self.register_buffer("seen", torch.zeros(2, dtype=torch.float64))  # cost total, episodes at the last update

    @property
    def lam(self) -> float:
        return float(self.value)

    def measured_cost(self, cost_total: float, cost_episodes: int) -> float | None:
        """J_c: the mean cost of the episodes that finished since the last call, from the running
        totals of :class:`~drivelab.training.outputs.episodes.EpisodeTracker` (None: none finished)."""
        total, episodes = float(self.seen[0]), float(self.seen[1])
        if cost_episodes <= episodes:
            return None
        self.seen.copy_(torch.tensor([cost_total, float(cost_episodes)], dtype=torch.float64))
        return (cost_total - total) / (cost_episodes - episodes)

    def update(self, measured_cost: float) -> dict[str, float]:
        """Move lambda from J_c = ``measured_cost``; returns what to log."""
        hp, error = self.hp, measured_cost - self.hp.cost_limit
        logs = {"charts/measured_cost": measured_cost, "charts/cost_violation": error}
        if hp.lagrange == "gradient":
            new = self.value + hp.lagrange_lr * error
        else:
            a = hp.pid_ema
            first = int(self.updates) == 0
            self.integral.copy_(torch.clamp(self.integral + hp.pid_ki * error, min=0.0))
            self.error_ema.copy_(error if first else a * self.error_ema + (1 - a) * error)
            self.cost_ema.copy_(measured_cost if first else a * self.cost_ema + (1 - a) * measured_cost)
            if first:  # no history yet: no derivative kick on the first update
                self.cost_history.fill_(float(self.cost_ema))
            derivative = torch.clamp(self.cost_ema - self.cost_history[0], min=0.0)
            self.cost_history.copy_(torch.cat([self.cost_history[1:], self.cost_ema.view(1)]))
            new = hp.pid_kp * self.error_ema + self.integral + hp.pid_kd * derivative
            logs |= {"charts/pid_integral": float(self.integral), "charts/pid_derivative": float(derivative)}
        self.value.copy_(torch.clamp(new, 0.0, hp.lagrange_max))
        self.updates += 1
        return logs | {"charts/lagrange_multiplier": self.lam}
