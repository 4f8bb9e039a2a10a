# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Lesson 2: the policy gradient, derived and checked
#
# **What it teaches.** Where the policy gradient comes from (the log-derivative trick), why the
# reward-to-go and a baseline leave it unbiased, and how much variance each removes: every step
# checked numerically on an MDP small enough to compute the exact gradient.
#
# **The seed lesson.** The course's second notebook (`001`: "Policy Gradient in MetaDrive"),
# which derives the discrete and continuous policy gradient before REINFORCE drives a car.
#
# **The result it reproduces.** The three score-function estimators (whole return, reward-to-go,
# reward-to-go minus a state-value baseline) average to the exact gradient, and their variance
# falls in that order. Measured at the full budget (`BUDGET = "full"`: 20,000 episodes):
# each mean within two standard errors of the exact gradient (relative distance 5.8%, 5.9% and
# 1.3%; standard errors 3.4%, 3.2% and 1.5%), variance per episode 1 : 0.87 : 0.19. The quick budget (2,000 episodes, seconds; what CI runs)
# gives the same variance ratios, with its means 7.8%, 5.7% and 2.3% away, each within its standard error.

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
import torch

from drivelab.training.learning.returns import reward_to_go

BUDGET = os.environ.get("DRIVELAB_NOTEBOOK_BUDGET", "quick")  # "quick" (seconds) or "full" (a minute)
EPISODES = {"quick": 2_000, "full": 20_000}[BUDGET]
torch.manual_seed(0)
rng = np.random.default_rng(0)

# %% [markdown]
# ## A tiny driving MDP
#
# A car at a junction (state 0) chooses *left* or *right*; then, on the road it took (state 1 or
# 2), it chooses *slow* or *fast*. Three decisions are never needed: the episode is two steps
# long, so every trajectory can be listed, and J(theta) = E[return] computed exactly.
#
# | state | action 0 | action 1 |
# |---|---|---|
# | 0 junction | left: reward 0, go to 1 | right (a shortcut): reward 8, go to 2 |
# | 1 left road | slow: reward 9 | fast: reward 14 (a quiet road) |
# | 2 right road | slow: reward 2 | fast: reward -6 (a crash) |
#
# The junction also has traffic: its reward carries zero-mean noise (standard deviation 5) that
# no action controls. It leaves J(theta) as in the table and makes the estimators' job harder.
#
# The policy is a softmax over two logits per state: theta has shape (3, 2).

# %%
REWARD = torch.tensor([[0.0, 8.0], [9.0, 14.0], [2.0, -6.0]])  # REWARD[state, action]
NEXT = {0: 1, 1: 2}                                             # the junction's action -> the road's state


def policy(theta: torch.Tensor) -> torch.Tensor:
    """(3, 2) action probabilities per state."""
    return torch.softmax(theta, dim=-1)


def exact_return(theta: torch.Tensor) -> torch.Tensor:
    """J(theta): the sum over the four trajectories of P(trajectory) x return."""
    pi = policy(theta)
    total = torch.zeros(())
    for a0 in (0, 1):
        road = NEXT[a0]
        for a1 in (0, 1):
            total = total + pi[0, a0] * pi[road, a1] * (REWARD[0, a0] + REWARD[road, a1])
    return total


theta = torch.tensor([[0.2, -0.1], [0.0, 0.3], [0.4, -0.2]], requires_grad=True)
exact_gradient = torch.autograd.grad(exact_return(theta), theta)[0]
print("J(theta) =", round(exact_return(theta).item(), 4))
print("exact gradient dJ/dtheta:\n", exact_gradient.numpy().round(4))

# %% [markdown]
# ## The log-derivative trick
#
# J(theta) = sum over trajectories tau of P(tau; theta) R(tau). Since grad P = P grad log P, and
# log P(tau) = sum_t log pi(a_t | s_t) + (terms of the dynamics, free of theta),
#
#     grad J = E_tau[ R(tau) * sum_t grad log pi(a_t | s_t) ]
#
# an expectation we can estimate from sampled episodes without knowing the dynamics. Two
# refinements keep it unbiased and shrink its variance:
#
# * **reward-to-go**: an action cannot change the rewards before it, so R(tau) can be replaced by
#   the rewards from t on, Psi_t = sum_{t' >= t} r_t' (their covariance with grad log pi(a_t|s_t) is 0);
# * **baseline**: subtracting any b(s_t) that does not depend on a_t leaves the expectation
#   unchanged, since E_a[grad log pi(a|s)] = grad sum_a pi(a|s) = grad 1 = 0. The state value V(s_t)
#   is the usual choice (with it, Psi_t is the advantage).
#
# First the identity E_a[grad log pi(a|s)] = 0, checked exactly for state 0:

# %%
pi0 = policy(theta)[0]
score = [torch.autograd.grad(torch.log(policy(theta)[0, a]), theta)[0] for a in (0, 1)]
expected_score = sum(pi0[a].detach() * score[a] for a in (0, 1))
print("E_a[grad log pi(a|s0)] =", expected_score[0].numpy().round(8), "(zero up to float error)")

# %% [markdown]
# ## Sampling episodes and the three estimators
#
# `reward_to_go` is the function drivelab's REINFORCE uses (`drivelab.training.learning.returns`).
# The baseline is the exact state value V(s) under the current policy (in practice a critic
# learns it; here we can afford the truth, which isolates what a baseline does).

# %%
def state_values(theta: torch.Tensor) -> np.ndarray:
    """V(s) for the three states under pi_theta (the roads end after one step)."""
    pi = policy(theta).detach()
    v_roads = (pi[1:] * REWARD[1:]).sum(-1)
    v0 = sum(pi[0, a] * (REWARD[0, a] + v_roads[NEXT[a] - 1]) for a in (0, 1))
    return np.array([float(v0), *v_roads.numpy()])


def sample_episode(theta: torch.Tensor):
    pi = policy(theta).detach().numpy()
    a0 = rng.choice(2, p=pi[0])
    road = NEXT[a0]
    a1 = rng.choice(2, p=pi[road])
    traffic = rng.normal(0.0, 5.0)  # zero-mean: J(theta) is unchanged
    return [0, road], [a0, a1], np.array([REWARD[0, a0] + traffic, REWARD[road, a1]], dtype=np.float64)


def score(theta: torch.Tensor, state: int, action: int) -> np.ndarray:
    """grad_theta log pi(action | state), (6,): for a softmax over logits it is onehot(action) - pi(.|state)
    in the state's row and 0 elsewhere (the cell above checked the autograd version's mean)."""
    g = np.zeros((3, 2))
    g[state] = -policy(theta).detach().numpy()[state]
    g[state, action] += 1.0
    return g.ravel()


def per_episode_gradients(theta: torch.Tensor, episodes: int) -> dict[str, np.ndarray]:
    """(episodes, 6) one-episode gradient estimates of each estimator."""
    values = state_values(theta)
    out = {"whole return": [], "reward-to-go": [], "reward-to-go - V(s)": []}
    for _ in range(episodes):
        states, actions, rewards = sample_episode(theta)
        scores = [score(theta, s_t, a_t) for s_t, a_t in zip(states, actions)]
        rtg = reward_to_go(rewards, np.array([False, True]), gamma=1.0)          # (2,)
        psi = {"whole return": [rewards.sum()] * 2, "reward-to-go": rtg,
               "reward-to-go - V(s)": rtg - values[states]}
        for name, weights in psi.items():
            out[name].append(sum(w * s for w, s in zip(weights, scores)))
    return {name: np.array(rows) for name, rows in out.items()}


grads = per_episode_gradients(theta, EPISODES)
exact = exact_gradient.numpy().ravel()
for name, g in grads.items():
    mean = g.mean(0)
    error = np.linalg.norm(mean - exact) / np.linalg.norm(exact)
    standard_error = np.sqrt(g.var(0).sum() / len(g)) / np.linalg.norm(exact)  # the expected distance, about
    print(f"{name:22s} relative error of the mean {error:6.2%} (standard error {standard_error:6.2%}), "
          f"variance per episode (trace) {g.var(0).sum():7.3f}")

# %% [markdown]
# Each estimator's mean lands on the exact gradient (the error shrinks as 1/sqrt(episodes));
# what differs is how many episodes that takes. The variance per episode says it directly: a batch
# of B episodes has variance (trace) / B, so an estimator with half the variance needs half the
# episodes for the same precision.

# %%
names = list(grads)
variance = np.array([grads[n].var(0).sum() for n in names])
fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
axes[0].bar(range(3), variance / variance[0], color=["C0", "C1", "C2"])
axes[0].set_xticks(range(3), names)
axes[0].set_ylabel("variance per episode (relative)")
axes[0].set_title("what each refinement removes")
batch_sizes = np.array([1, 4, 16, 64, 256])
for i, n in enumerate(names):
    g = grads[n]
    errors = [np.mean([np.linalg.norm(g[rng.choice(len(g), b)].mean(0) - exact) for _ in range(200)]) for b in batch_sizes]
    axes[1].loglog(batch_sizes, errors, "o-", color=f"C{i}", label=n)
axes[1].set_xlabel("episodes per gradient estimate")
axes[1].set_ylabel("mean distance to the exact gradient")
axes[1].legend()
fig.tight_layout()
plt.show()
print("variance per episode relative to the whole return:", dict(zip(names, (variance / variance[0]).round(2))))

# %% [markdown]
# ## What this means for REINFORCE
#
# drivelab's REINFORCE (`drivelab train --algo reinforce`, lesson 1) uses the reward-to-go
# (`reinforce.advantage: rtg`) and can centre or standardise it across the batch (`mean`,
# `normalize`): a constant baseline, cheaper than V(s) and weaker. A2C and PPO (lesson 3) learn
# V(s) with a critic and use GAE(lambda) to trade a little bias for much less variance.
