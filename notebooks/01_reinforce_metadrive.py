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
# # Lesson 1: REINFORCE on MetaDrive
#
# **What it teaches.** The simplest policy-gradient method driving a car: a softmax policy over
# 9 discrete actions (a 3x3 grid of steering x throttle), batches of whole episodes, each action
# weighted by its discounted reward-to-go, an entropy bonus; the learning curve and a video of
# the agent; and what the variance of the gradient estimate does to learning.
#
# **The seed lesson.** The course's first notebook (`000`: "REINFORCE on MetaDrive"): 9 discrete
# actions mapped to (steering, throttle), reward-to-go with GAMMA, an entropy bonus, batches of
# episodes, TensorBoard scalars and periodic checkpoints. Here all of that is one drivelab config,
# `reinforce_metadrive`, and this notebook looks inside the run it makes.
#
# **The result it reproduces.** REINFORCE learns to drive part of MetaDrive's 10 training roads,
# and only with a baseline. At the full budget (`BUDGET = "full"`: 60,000 env steps per run, two
# runs, about 12 minutes on two cores) the deterministic policy trained with normalised
# rewards-to-go (a baseline) drove 22.3% of the route on average over the 10 roads (return 75.7),
# the same run without a baseline (`advantage: rtg`) 2.0% (return -2.6). Numbers and commit: `benchmarks/results/notebooks_full.json`. The quick budget (1,000
# steps per run; what CI runs) shows the machinery, not learning.

# %%
import os
import shutil
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Video, display

import drivelab
from drivelab.cli import run as drivelab_cli  # drivelab_cli("eval", RUN) is `drivelab eval RUN`, in this kernel
from drivelab.envs.config import EnvConfig
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.outputs.statistics import rolling_mean

BUDGET = os.environ.get("DRIVELAB_NOTEBOOK_BUDGET", "quick")  # "quick" (a minute) or "full" (about 12 minutes)
STEPS = {"quick": 1_000, "full": 60_000}[BUDGET]
BATCH_STEPS = {"quick": 500, "full": 4_000}[BUDGET]  # env steps of whole episodes per gradient step
ENVS = {"quick": 1, "full": 2}[BUDGET]  # simulator processes (the quick budget saves starting a second)
ENT_COEF = 0.01  # the entropy bonus's weight (the shipped config has none)
RUNS = Path("runs") / "lesson1"
shutil.rmtree(RUNS, ignore_errors=True)  # each run of the notebook starts afresh (runs/ holds its runs)


# %% [markdown]
# ## The environment: MetaDrive with 9 actions
#
# MetaDrive's car takes a continuous action, [steering, throttle] in [-1, 1]^2. The seed lesson
# made it discrete: 3 steering values x 3 throttle values. drivelab does the same with
# `env.action_grid: 3x3`: the policy picks one of 9 indices, and the env maps it to the pair.
# The observation is MetaDrive's 259-number vector (the car's state, lidar, the road ahead),
# each in [0, 1].

# %%
env = drivelab.make_env(EnvConfig(id="MetaDrive-10env-v0", action_grid="3x3"))
print("observation:", env.observation_space.shape, " actions:", env.action_space)
print("action index -> (steering, throttle):\n", np.asarray(env.get_wrapper_attr("table")).round(2))
env.close()

# %% [markdown]
# ## The algorithm
#
# For a batch of whole episodes with B steps in all, REINFORCE ascends
#
#     g = 1/B * sum_t grad log pi(a_t | s_t) * Psi_t  +  ent_coef * grad H(pi(. | s_t))
#
# where Psi_t is the discounted reward-to-go G_t = r_t + gamma r_{t+1} + ... to the end of the
# episode (lesson 2 derives why that is the gradient of the expected return). The file that
# implements it is `drivelab/algos/reinforce.py`, readable top to bottom: collect whole episodes
# until `batch_steps` steps, compute the rewards-to-go, one gradient step.
#
# `reinforce.advantage` chooses Psi_t: `rtg` is G_t itself; `normalize` subtracts the batch's mean
# and divides by its standard deviation: a constant baseline, which leaves the gradient's direction
# in expectation (lesson 2) and cuts its variance.

# %%
print(Path(drivelab.__file__).with_name("configs").joinpath("reinforce_metadrive.yaml").read_text())

# %% [markdown]
# ## Training
#
# `drivelab.train` is what `drivelab train --config reinforce_metadrive` runs. Two env processes
# play episodes in parallel (MetaDrive runs one simulator per process). The run directory holds
# `metrics.csv`, TensorBoard logs (`tensorboard --logdir runs`) and checkpoints.

# %%
def train(advantage: str) -> Path:
    result = drivelab.train(config="reinforce_metadrive", steps=STEPS, seed=0, run_dir=RUNS / advantage, num_envs=ENVS,
                            checkpoint_every=STEPS, progress=False,
                            reinforce={"advantage": advantage, "batch_steps": BATCH_STEPS, "ent_coef": ENT_COEF})
    print(f"advantage={advantage}: {STEPS:,} steps, last logged route completion "
          f"{result.metrics.get('episode/route_completion', float('nan')):.1%}")
    return result.run_dir


run = train("normalize")

# %% [markdown]
# ## The learning curve
#
# Every finished episode logs its return and MetaDrive's driving metrics. Route completion (the
# share of the route driven) is the clearest sign of learning; the entropy of the policy (in nats,
# at most log 9 = 2.2) shows it becoming decisive. The entropy bonus slows that fall, so that the
# agent keeps trying actions while their values are still uncertain.

# %%
metrics = read_metrics(run)
fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
for ax, name in zip(axes, ("episode/return", "episode/route_completion", "loss/entropy")):
    if name not in metrics:
        ax.set_title(f"{name}: not logged yet")
        continue
    steps, _, values = metrics[name]
    ax.plot(steps, values, ".", alpha=0.3, color="C0")
    ax.plot(steps, rolling_mean(values, 20), color="C0")
    ax.set_xlabel("env steps")
    ax.set_title(name)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## The agent, on video
#
# `drivelab eval RUN --video FILE` plays the run's latest checkpoint deterministically (the most
# likely action) and records MetaDrive's top-down view.

# %%
video = RUNS / "agent.mp4"
drivelab_cli("eval", str(run), "--episodes", "1", "--video", str(video), "--no-progress")
display(Video(str(video), embed=True))

# %% [markdown]
# ## What the variance of the gradient does
#
# The same run with `advantage: rtg` (no baseline) takes its gradient steps on the raw
# rewards-to-go. Every G_t of MetaDrive's reward is positive early on (the car is paid for
# progress), so every sampled action is pushed up, by amounts that differ more between batches
# than between actions: a noisy gradient. Lesson 2 measured that a baseline removes most of that
# variance; here is what it does to learning, at the same number of env steps. The right panel
# shows each gradient's norm: without the baseline it carries the returns' scale and swings with
# them from batch to batch (Adam divides much of the scale out, not the noise in direction).

# %%
run_rtg = train("rtg")
fig, axes = plt.subplots(1, 2, figsize=(12, 3.6))
for i, (label, path) in enumerate((("normalize (a baseline)", run), ("rtg (no baseline)", run_rtg))):
    logged = read_metrics(path)
    steps, _, values = logged["episode/route_completion"]
    axes[0].plot(steps, rolling_mean(values, 20), color=f"C{i}", label=label)
    steps, _, values = logged["loss/grad_norm"]
    axes[1].semilogy(steps, values, "o-", color=f"C{i}", label=label)
axes[0].set_ylabel("route completion (rolling mean of 20 episodes)")
axes[1].set_ylabel("gradient norm (unclipped)")
for ax in axes:
    ax.set_xlabel("env steps")
    ax.legend()
fig.tight_layout()
plt.show()

# %% [markdown]
# ## Judging the result
#
# The training curve is measured on sampled actions; the policy that ships acts deterministically.
# `drivelab.evaluate` plays it on the training roads (episode k on seed k).

# %%
for label, path in (("normalize", run), ("rtg", run_rtg)):
    row = drivelab.evaluate(drivelab.load(path), episodes={"quick": 1, "full": 10}[BUDGET])
    print(f"{label:9s} route completion {row['route_completion']:.1%}, success {row['success_rate']:.0%}, "
          f"return {row['return_mean']:.1f}")

# %% [markdown]
# ## Exercises
#
# * Set `reinforce.ent_coef` to 0.01 and to 0.1: how does the entropy curve change, and the route?
# * Halve `batch_steps`: twice the gradient steps, each noisier. Which wins at 60,000 steps?
# * Lesson 3's A2C learns a state-value baseline V(s) instead of the batch mean.
