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
# # Lesson 3: A2C with GAE, and GRPO, on LunarLander
#
# **What it teaches.** Two ways to give the policy gradient a baseline. A2C learns a critic V(s)
# and estimates advantages with GAE(lambda), whose lambda trades bias against variance (shown here
# on one batch of episodes). GRPO has no critic: it compares each episode with a *group* of
# episodes started from the same state, which takes grouped resets and masked stepping. Training
# curves with rolling means, and showcase episodes of both landers.
#
# **The seed lesson.** The course's third notebook (`002`: advantage actor-critic and GAE notes,
# and an unfinished GRPO on vectorised LunarLander-v3 with masked stepping and grouped resets,
# training plots with rolling means, showcase episodes). drivelab finishes that GRPO
# (`drivelab/algos/grpo.py`); A2C is `drivelab/algos/a2c.py`.
#
# **The result it reproduces.** GAE's trade-off, measured on one batch: as lambda goes from 0 to 1
# the bias of the value estimate falls and its spread rises. At the full budget (`BUDGET =
# "full"`: 300,000 env steps per algorithm, PPO's LunarLander budget, about 4 minutes on two
# cores): |bias| 11.9 -> 2.9 and std 0.2 -> 11.1 from lambda 0 to 1. Neither lander solves the task
# at that budget (200): training episodes averaged 48.5 (A2C) and 54.6 (GRPO), and the
# deterministic policies scored 29.2 +- 139.6 (A2C) and -126.7 +- 62.6 (GRPO) over 20 episodes:
# GRPO's sampled policy flies better than its most likely action. PPO, which reuses each batch
# for 10 epochs, lands at the same budget (`--config ppo_lunarlander`). Numbers and commit:
# `benchmarks/results/notebooks_full.json`. The quick budget (what CI runs, under a minute) runs
# every cell on 8,000 steps.

# %%
import os
import shutil
from pathlib import Path

import gymnasium as gym
import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Video, display

import drivelab
from drivelab.cli import run as drivelab_cli  # drivelab_cli("eval", RUN) is `drivelab eval RUN`, in this kernel
from drivelab.training.learning.returns import gae, group_relative_advantages
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.outputs.statistics import rolling_mean

BUDGET = os.environ.get("DRIVELAB_NOTEBOOK_BUDGET", "quick")  # "quick" (under a minute) or "full" (about 4 minutes)
STEPS = {"quick": 8_000, "full": 300_000}[BUDGET]
START_STATES, EPISODES_EACH = {"quick": (3, 6), "full": (8, 16)}[BUDGET]  # the GAE experiment's batch
RUNS = Path("runs") / "lesson3"
shutil.rmtree(RUNS, ignore_errors=True)  # each run of the notebook starts afresh (runs/ holds its runs)
GAMMA = 0.99
rng = np.random.default_rng(0)


# %% [markdown]
# ## A2C: an actor, a critic and GAE
#
# A2C (Mnih et al. 2016, synchronous) steps 8 landers for `num_steps` steps, then takes one
# gradient step on
#
#     L = -mean_t[ A_t log pi(a_t|s_t) ] + vf_coef * mean_t[ (V(s_t) - R_t)^2 ] - ent_coef * H
#
# where the advantage A_t is GAE (Schulman et al. 2016, eq. 16): with the TD error
# delta_t = r_t + gamma V(s_{t+1}) - V(s_t),
#
#     A_t = delta_t + (gamma lambda) delta_{t+1} + (gamma lambda)^2 delta_{t+2} + ...
#
# lambda = 0 trusts the critic after one step (low variance, biased where V is wrong);
# lambda = 1 is the Monte-Carlo return minus V(s_t) (unbiased, all the noise of the episode).

# %%
a2c = drivelab.train(config="a2c_lunarlander", steps=STEPS, seed=0, run_dir=RUNS / "a2c", progress=False,
                     checkpoint_every=STEPS)
print("A2C, last logged return (mean of recent episodes):", round(a2c.metrics["episode/return"], 1))

# %% [markdown]
# ## Lambda's trade-off, on one batch
#
# How good is each lambda's estimate of the value of a start state? LunarLander's reset takes a
# seed: every episode reset with the same seed starts from the same state (terrain and initial
# push). So for a few start states we play two groups of episodes each with the trained A2C
# policy's sampled actions: the mean discounted return of the first group estimates V(s_0) without
# bias, and the second group's episodes are the batch that each lambda estimates it from.
#
# The critic here is deliberately simple and imperfect, a linear fit of the returns on the
# observation (fitted on other episodes), as critics early in training are. For each episode and
# lambda, the lambda-return V_hat(s_0) + A_0 estimates V(s_0): its mean over a group shows the bias,
# its spread within the group the variance.

# %%
policy = drivelab.load(a2c.run_dir)
env = gym.make("LunarLander-v3")


def play(seed: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """One episode from the start state of ``seed`` with sampled actions: (observations (T+1, 8),
    rewards (T,), terminated). The last observation is the final one (for a truncated episode's bootstrap)."""
    obs, _ = env.reset(seed=seed)
    observations, rewards = [obs], []
    while True:
        obs, reward, terminated, truncated, _ = env.step(policy.act(obs, deterministic=False))
        observations.append(obs)
        rewards.append(reward)
        if terminated or truncated:
            return np.array(observations), np.array(rewards), terminated


def discounted(rewards: np.ndarray) -> np.ndarray:
    """(T,) discounted returns from each step to the episode's end."""
    out, running = np.zeros(len(rewards)), 0.0
    for t in reversed(range(len(rewards))):
        running = rewards[t] + GAMMA * running
        out[t] = running
    return out


# The imperfect critic: least squares of the returns on [obs, 1], from episodes of other start states.
fit = [play(seed) for seed in range(1000, 1000 + 2 * START_STATES)]
X = np.concatenate([np.c_[o[:-1], np.ones(len(o) - 1)] for o, _, _ in fit])
y = np.concatenate([discounted(r) for _, r, _ in fit])
weights = np.linalg.lstsq(X, y, rcond=None)[0]


def critic(observations: np.ndarray) -> np.ndarray:
    return np.c_[observations, np.ones(len(observations))] @ weights


lambdas = np.array([0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 1.0])
estimates = np.zeros((START_STATES, EPISODES_EACH, len(lambdas)))  # lambda-return estimates of V(s_0)
truth = np.zeros(START_STATES)
for s in range(START_STATES):
    # V(s_0) from a second, independent group of episodes: the estimates below never see them
    truth[s] = np.mean([discounted(play(seed=s)[1])[0] for _ in range(EPISODES_EACH)])
    episodes = [play(seed=s) for _ in range(EPISODES_EACH)]
    for e, (observations, rewards, terminated) in enumerate(episodes):
        values = critic(observations)                      # (T+1,)
        T = len(rewards)
        ends = np.zeros((T, 1), bool)
        ends[-1] = True
        term = np.zeros((T, 1), bool)
        term[-1] = terminated
        for k, lam in enumerate(lambdas):
            advantages, _ = gae(rewards[:, None], values[:-1, None], values[1:, None], term, ends, GAMMA, lam)
            estimates[s, e, k] = values[0] + advantages[0, 0]

bias = np.abs(estimates.mean(1) - truth[:, None]).mean(0)   # (lambdas,) mean over start states
spread = estimates.std(1).mean(0)                          # (lambdas,)
fig, ax = plt.subplots(figsize=(7, 3.6))
ax.plot(lambdas, bias, "o-", label="|bias|: |mean estimate - V(s0)|")
ax.plot(lambdas, spread, "s-", label="spread: std within a group")
ax.set_xlabel("lambda")
ax.set_ylabel("discounted return")
ax.legend()
plt.show()
for lam, b, sd in zip(lambdas, bias, spread):
    print(f"lambda {lam:4.2f}: |bias| {b:7.2f}   std {sd:7.2f}")

# %% [markdown]
# At lambda = 1 each estimate is the episode's own discounted return: no bias (what remains is
# the noise of two finite groups), and the most spread. Lower lambdas lean on the critic: less spread, more bias
# (the linear critic is far from V). drivelab's recipes use 0.95 (PPO) and 1.0 (A2C's
# LunarLander recipe, `a2c.gae_lambda`).
#
# ## GRPO: a group instead of a critic
#
# GRPO (Shao et al. 2024) drops the critic. The N landers form groups of G (`grpo.group_size`);
# a group's members reset with one shared seed, so they start from the same state, and an episode's
# advantage is its return relative to its group's: (R - mean) / std. A member that lands first
# waits, *masked*: it is not stepped again, and its steps are not recorded, until the whole group
# has finished; then the group resets together to a new seed. drivelab's recipe uses the per-step
# form: the reward-to-go relative to the group's members still flying at that step.
#
# One group's arithmetic, on the episodes above (group 0 of the GAE experiment):

# %%
group_returns = np.array([[estimates[0, e, -1] for e in range(EPISODES_EACH)]])  # (1, G) lambda=1: the returns
print("returns   ", group_returns.round(1))
print("advantages", group_relative_advantages(group_returns).round(2))

# %%
grpo = drivelab.train(config="grpo_lunarlander", steps=STEPS, seed=0, run_dir=RUNS / "grpo", progress=False,
                      checkpoint_every=STEPS)
print("GRPO, last logged return:", round(grpo.metrics["episode/return"], 1))

# %% [markdown]
# ## Training curves, with rolling means
#
# Each dot is one finished episode's return; the line is the mean of the last 50. 200 is
# "solved" for LunarLander.

# %%
fig, ax = plt.subplots(figsize=(8, 4))
for i, (label, run) in enumerate((("A2C", a2c.run_dir), ("GRPO", grpo.run_dir))):
    steps, _, returns = read_metrics(run)["episode/return"]
    ax.plot(steps, returns, ".", color=f"C{i}", alpha=0.15)
    ax.plot(steps, rolling_mean(returns, 50), color=f"C{i}", label=label)
ax.axhline(200, color="gray", ls="--", lw=1)
ax.set_xlabel("env steps")
ax.set_ylabel("episode return")
ax.set_ylim(-600, 320)
ax.legend()
plt.show()

# %% [markdown]
# ## Showcase episodes, and the final numbers
#
# The deterministic policies (the most likely action), on 10 start states neither trained on
# specifically; then one episode of each on video.

# %%
episodes = {"quick": 3, "full": 20}[BUDGET]
for label, run in (("A2C", a2c.run_dir), ("GRPO", grpo.run_dir)):
    row = drivelab.evaluate(drivelab.load(run), episodes=episodes, seed=100)
    print(f"{label:5s} return {row['return_mean']:7.1f} +- {row['return_std']:5.1f} over {episodes} episodes")

# %%
for label, run in (("a2c", a2c.run_dir), ("grpo", grpo.run_dir)):
    video = RUNS / f"{label}.mp4"
    drivelab_cli("eval", str(run), "--episodes", "1", "--seed", "100", "--video", str(video), "--no-progress")
    display(Video(str(video), embed=True))

# %% [markdown]
# ## Exercises
#
# * Train A2C with `a2c.gae_lambda` 0.9 and 1.0 for 300k steps (`drivelab train --config
#   a2c_lunarlander --a2c.gae_lambda 0.9`): does the critic's bias cost more than the noise saved?
# * GRPO with `grpo.group_size` 2 and 16 (keep `env.num_envs` a multiple): the group mean is a
#   noisier or a better baseline; what does the wait for a group's slowest member cost?
# * PPO (`--config ppo_lunarlander`) reuses each batch for 10 epochs: compare its curve at 300k.
