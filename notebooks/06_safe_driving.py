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
# # Lesson 6: safe driving, reward and cost apart
#
# **What it teaches.** Safe reinforcement learning as a constrained problem (Altman 1999): maximise
# the return while the expected episode cost stays at or below a limit. Where the cost comes from
# in MetaDrive's safety task; why a fixed penalty in the reward is the wrong tool; the Lagrangian
# method, whose multiplier rises while the cost is above the limit and falls when it is below,
# with PPO-Lagrangian on a road whose constrained optimum is known; and how drivelab counts the
# cost a policy causes, in training and in evaluation (OmniSafe's names: episode cost, cost rate,
# cumulative cost).
#
# **The seed lesson.** None of the five seed notebooks poses safety: their rewards mix progress
# with crash penalties (`000`, `003`, `004`). This lesson follows from their reward engineering:
# it takes the crash out of the reward and bounds it instead.
#
# **The result it reproduces.** On the three-lane road below, unconstrained PPO takes the fast lane
# (return 10, cost 4 per episode) and PPO-Lagrangian with a cost limit of 1 the middle lane
# (return 8, cost 1), the constrained optimum. At the full budget (`BUDGET = "full"`: 65,536 env
# steps per run, under 2 minutes on two cores) both deterministic policies landed exactly there,
# with lambda settled between 0.85 and 1.17 (inside the window (2/3, 3) that makes the middle lane
# best); the driver that ships with drivelab, trained without a cost, caused a mean episode cost
# of 40.9 (cost rate 0.083) on 20 unseen SafeMetaDrive scenarios while succeeding on 55% of them.
# Numbers and commit: `benchmarks/results/notebooks_full.json`. The quick budget (what CI runs,
# under a minute) trains on 8,192 steps, where lambda has not settled yet.

# %%
import os
import shutil
import sys
from pathlib import Path

import gymnasium as gym
import matplotlib.pyplot as plt
import numpy as np

import drivelab
from drivelab.training.outputs.plots import read_metrics

BUDGET = os.environ.get("DRIVELAB_NOTEBOOK_BUDGET", "quick")  # "quick" (under a minute) or "full" (a few minutes)
STEPS = {"quick": 8_192, "full": 65_536}[BUDGET]
EPISODES = {"quick": 2, "full": 20}[BUDGET]  # SafeMetaDrive evaluation episodes per policy
RUNS = "runs/lesson6"
shutil.rmtree(RUNS, ignore_errors=True)  # each run of the notebook starts afresh (runs/ holds its runs)

# %% [markdown]
# ## Where the cost comes from
#
# MetaDrive's safety task (`SafeMetaDrive-*`: more accidents on the road, and a crash does not end
# the episode) reports, at every step, `info["cost"]`: 1 for a step in contact with a vehicle or
# an object, or off the road. The reward does not see it. drivelab adds the episode's running sum.

# %%
env = drivelab.make_env("SafeMetaDrive-validation-v0")
obs, info = env.reset(seed=0)
costs = []
for _ in range(100):
    obs, reward, terminated, truncated, info = env.step(np.array([0.6, 1.0]))  # hard left, full throttle
    costs.append(info["cost"])
    if terminated or truncated:
        break
env.close()
print(f"{len(costs)} steps steering into the kerb: cost per step {costs[:12]} ...; episode cost {info['episode_cost']}")

# %% [markdown]
# ## The constrained problem, and the Lagrangian
#
# With J_R(pi) the expected return and J_C(pi) the expected episode cost, the task is
#
#     max_pi J_R(pi)   subject to   J_C(pi) <= d.
#
# A fixed penalty, maximising J_R - w J_C, needs the one w that lands exactly on the limit, and
# that w depends on the task, the policy and the stage of training. The Lagrangian method learns
# it: it solves max_pi min_{lambda >= 0} J_R(pi) - lambda (J_C(pi) - d), alternating a policy step
# on the advantage A_R - lambda A_C (scaled by 1 / (1 + lambda)) and a step on lambda:
#
#     lambda <- max(0, lambda + lr * (J_C - d))      (lagrange: gradient)
#
# or a PID controller on the same error (`lagrange: pid`, Stooke, Achiam & Abbeel 2020), which
# damps the oscillation that the plain gradient step shows. `drivelab/algos/ppo_lag.py` and
# `drivelab/algos/sac_lag.py` implement both; `drivelab/training/learning/lagrange.py` holds the
# multiplier.
#
# ## A road with a known answer
#
# Four stretches; at each, the car's one action picks a lane:
#
# | lane | action | reward per stretch | cost per stretch | episode return | episode cost |
# |---|---|---|---|---|---|
# | shoulder | a < -1/3 | 1.25 | 0 | 5 | 0 |
# | middle | -1/3 <= a <= 1/3 | 2.0 | 0.25 | 8 | 1 |
# | fast | a > 1/3 | 2.5 | 1.0 | 10 | 4 |
#
# With a cost limit of 1 the best policy is the middle lane throughout: return 8, cost 1.

# %%
# drivelab's env workers import an env from a module, as they would your own env: so the road is
# written to three_lanes.py beside the notebook, then passed as the class.
Path("three_lanes.py").write_text('''
"""Four stretches, one lane choice each; the observation is the one-hot stretch, the cost in info."""
import gymnasium as gym
import numpy as np

LANES = ((1.25, 0.0), (2.0, 0.25), (2.5, 1.0))  # (reward, cost) per stretch: shoulder, middle, fast


class ThreeLanes(gym.Env):
    def __init__(self):
        self.observation_space = gym.spaces.Box(0.0, 1.0, (4,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.t = 0

    def _obs(self):
        return np.eye(4, dtype=np.float32)[min(self.t, 3)]

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {"cost": 0.0}

    def step(self, action):
        a = float(np.asarray(action).reshape(-1)[0])
        reward, cost = LANES[0 if a < -1 / 3 else (1 if a <= 1 / 3 else 2)]
        self.t += 1
        return self._obs(), reward, self.t >= 4, False, {"cost": cost}
''')
sys.path.insert(0, os.getcwd())
from three_lanes import ThreeLanes  # noqa: E402

common = dict(steps=STEPS, seed=0, num_envs=8, progress=False, log_every=2048)
ppo = drivelab.train("ppo", ThreeLanes, run_dir=f"{RUNS}/ppo", ppo={"num_steps": 64, "hidden": [32], "lr": 3e-3}, **common)
lag = drivelab.train("ppo_lag", ThreeLanes, run_dir=f"{RUNS}/ppo_lag", **common,
                     ppo_lag={"num_steps": 64, "hidden": [32], "lr": 3e-3, "cost_limit": 1.0, "lagrange_lr": 0.1})

# %% [markdown]
# Both runs log `episode/cost` beside the return; PPO-Lagrangian adds its multiplier
# (`charts/lagrange_multiplier`). The dashed line is the limit.

# %%
fig, axes = plt.subplots(1, 3, figsize=(15, 3.6))
for i, (label, result) in enumerate((("PPO", ppo), ("PPO-Lagrangian, limit 1", lag))):
    logged = read_metrics(result.run_dir)
    for ax, name in zip(axes, ("episode/return", "episode/cost")):
        steps, _, values = logged[name]
        ax.plot(steps, values, color=f"C{i}", label=label)
        ax.set_title(name)
lam_steps, _, lam = read_metrics(lag.run_dir)["charts/lagrange_multiplier"]
axes[2].plot(lam_steps, lam, color="C1")
axes[2].set_title("lambda (PPO-Lagrangian)")
axes[1].axhline(1.0, color="gray", ls="--")
for ax in axes:
    ax.set_xlabel("env steps")
axes[0].legend()
fig.tight_layout()
plt.show()

# %%
for label, result in (("PPO", ppo), ("PPO-Lagrangian", lag)):
    row = drivelab.evaluate(drivelab.load(result.run_dir), ThreeLanes, episodes=5)
    print(f"{label:15s} deterministic return {row['return_mean']:.2f}, episode cost {row['cost']:.2f}")

# %% [markdown]
# Lambda rises while the sampled episodes cost more than 1 and settles where the middle lane pays
# best: per stretch the Lagrangian reward r - lambda c is 2.5 - lambda (fast), 2 - 0.25 lambda
# (middle) and 1.25 (shoulder), so any lambda between 2/3 and 3 makes the middle lane the best.
#
# ## Counting the cost a driver causes
#
# On MetaDrive's safety task, `drivelab eval` (and `drivelab.evaluate`) reports beside success the
# mean episode cost and the cost rate (cost per step of all episodes together). The driver that
# ships with drivelab was trained for success, with crashes only in its reward; MetaDrive's expert
# is a rule-based planner. Both, on the same unseen safety scenarios:

# %%

for name in ("drivelab-driver",):
    row = drivelab.evaluate(drivelab.load(name), "SafeMetaDrive-validation-v0", episodes=EPISODES)
    print(f"{name:16s} success {row['success_rate']:.0%}, episode cost {row['cost']:.2f}, cost rate {row['cost_rate']:.4f}, "
          f"crash {row['crash_rate']:.0%}, off road {row['out_of_road_rate']:.0%}")

# %% [markdown]
# `benchmarks/safe_drive.py` trains SAC-Lagrangian (`--config safe_drive`) against unconstrained SAC
# and a fixed penalty on this task for 30 minutes each; its measured numbers are in the results
# (`docs/results.md`, "Safe driving").
#
# ## Exercises
#
# * Set `lagrange: pid` in the PPO-Lagrangian run: does lambda overshoot less?
# * A fixed penalty: train PPO on a ThreeLanes whose reward subtracts w * cost, for w = 0.5, 2 and 5.
#   Which w lands on the limit, and would it on another road?
# * Set the limit to 0: the shoulder is the only feasible lane. How high must lambda climb?
