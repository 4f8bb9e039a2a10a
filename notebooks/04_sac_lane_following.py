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
# # Lesson 4: SAC for lane following, with a cross-track-error reward
#
# **What it teaches.** Soft Actor-Critic steering a car along its lane: observation filters for
# camera-like images, a reward built from the cross-track error (CTE) and the heading error,
# fixed throttle so that the agent only steers, a random heat-up before learning, evaluation
# periods on roads kept apart, MLflow tracking of parameters, metrics and checkpoints, and
# resuming a run from MLflow.
#
# **The seed lesson.** The course's fourth notebook (`003`: SAC on a Donkey-car lane-following
# simulator, with uint8-to-float, grayscale, crop, Sobel and binarise filters, a quadratic CTE
# reward with a crash penalty and an episode end beyond a maximum CTE, fixed throttle, heat-up,
# evaluation periods, video dumps, MLflow, resume from a checkpoint). Here the car is MetaDrive's,
# on empty roads: drivelab's `drivelab/MetaDriveLaneFollow-v0` task.
#
# **The result it reproduces.** SAC learns to steer along its lane within minutes. At the full
# budget (`BUDGET = "full"`: 30,000 env steps, about 12 minutes on two cores, evaluations
# included) the evaluation periods on unseen roads went from 1.7% of the route (5,000 steps) to
# 52.1% (15,000 steps, the checkpoint kept as `best`); that checkpoint, on 10 other unseen roads,
# drove 40.6% of the route on average with a mean |CTE| of 0.46 m, finishing 2 of the 10 routes and
# leaving the road on 1. Numbers and commit: `benchmarks/results/notebooks_full.json`. The quick
# budget (what CI runs, under a minute) runs every cell on 600 steps, without evaluation periods.

# %%
import os
import shutil
from pathlib import Path

import matplotlib.pyplot as plt
import mlflow
import numpy as np
from IPython.display import Image, Video, display

import drivelab
from drivelab.cli import run as drivelab_cli  # drivelab_cli("eval", RUN) is `drivelab eval RUN`, in this kernel
from drivelab.envs import filters
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.outputs.statistics import rolling_mean

BUDGET = os.environ.get("DRIVELAB_NOTEBOOK_BUDGET", "quick")  # "quick" (a minute) or "full" (about 12 minutes)
STEPS = {"quick": 600, "full": 30_000}[BUDGET]
HEAT_UP = {"quick": 250, "full": 2_000}[BUDGET]        # random actions before the first update
EVAL_EVERY = {"quick": 0, "full": 5_000}[BUDGET]       # an evaluation period every this many steps (0: none)
ENVS = {"quick": 1, "full": 2}[BUDGET]                 # simulator processes (the quick budget saves starting more)
RUNS = Path("runs") / "lesson4"
shutil.rmtree(RUNS, ignore_errors=True)  # each run of the notebook starts afresh (runs/ holds its runs)
SHIPPED = Path(drivelab.__file__).with_name("configs")  # the configs that come with drivelab


# %% [markdown]
# ## Observation filters
#
# The seed lesson's car saw the road through a camera, and filtered each frame before the network
# saw it: to float, grayscale, crop the sky, Sobel edges, binarise. drivelab has the same filters
# as `env.obs_filters`, applied in order to any image observation. MetaDrive's bird's-eye
# observation (`drivelab/MetaDriveTopDown-v0`: 84 x 84 pixels, 5 channels of road, lane lines and
# traffic over the last frames) shows what each does.

# %%
env = drivelab.make_env("drivelab/MetaDriveTopDown-v0")
obs, _ = env.reset(seed=1000)
for _ in range(20):  # drive a little, so that the frames have history
    obs, *_ = env.step(np.array([0.0, 0.5]))
env.close()
# The functions behind env.obs_filters, applied in turn to that observation:
stages = {"raw (uint8)": obs}
stages["to_float"] = filters.to_float(obs)
stages["+ crop"] = filters.crop(stages["to_float"], top=12, bottom=12)
stages["+ sobel"] = filters.sobel(stages["+ crop"])
stages["+ binarize"] = filters.binarize(stages["+ sobel"], threshold=0.1)
fig, axes = plt.subplots(1, len(stages), figsize=(15, 3.2))
for ax, (name, image) in zip(axes, stages.items()):
    ax.imshow(image[..., 0], cmap="gray")
    ax.set_title(name, fontsize=9)
    ax.set_xlabel(f"{image.shape} {image.dtype}", fontsize=8)
plt.show()

# %% [markdown]
# In a config the same chain is one line, applied to every observation the agent sees:
# `env: {id: drivelab/MetaDriveTopDown-v0, obs_filters: [to_float, {crop: {top: 12, bottom: 12}},
# sobel, {binarize: {threshold: 0.1}}]}`; the observation space follows (here 60 x 84 x 5 floats).
#
# The rest of the lesson steers from MetaDrive's state vector (lidar, the car's state, the road
# ahead), which SAC learns from in minutes on a CPU; an image agent (`algo: sac` with
# `drivelab/MetaDriveTopDown-v0` and these filters) takes hours.
#
# ## The cross-track-error reward
#
# The CTE is the car's distance from its lane's centre line. The reward term `cte` pays
# 1 - (CTE / scale)^2 per metre of route progress (so that driving slowly earns nothing extra),
# a crash penalty, and ends the episode when the CTE passes `max_cte`. drivelab's lane-following
# task uses it; `drivelab reward plot` draws it against CTE and heading error.

# %%
print((SHIPPED / "rewards" / "cte.yaml").read_text())
drivelab_cli("reward", "plot", "--reward", str(SHIPPED / "rewards" / "cte.yaml"), "--out", "cte_reward.png")
display(Image(filename="cte_reward.png"))

# %% [markdown]
# ## Training, tracked with MLflow
#
# `env.fixed_throttle: 0.3` holds the throttle, so SAC's action is the steering alone, in [-1, 1].
# `sac.learning_starts` is the heat-up: uniformly random steering fills the replay buffer before
# the first update. `eval.every` sets the evaluation periods: deterministic episodes on scenarios
# the training never sees, and `checkpoints/best` keeps the best of them. With `track.mlflow`
# the run logs its config as MLflow parameters, every metric, and its checkpoints as artifacts
# into an MLflow store beside the run, `runs/lesson4/mlflow.db` (`mlflow ui --backend-store-uri
# sqlite:///runs/lesson4/mlflow.db` shows them).

# %%
config = dict(
    env={"id": "drivelab/MetaDriveLaneFollow-v0", "num_envs": ENVS, "fixed_throttle": 0.3},
    sac={"learning_starts": HEAT_UP, "batch_size": {"quick": 64, "full": 256}[BUDGET], "hidden": [128, 128], "init_alpha": 0.05, "utd": 1.0},
    eval={"every": EVAL_EVERY, "episodes": {"quick": 1, "full": 4}[BUDGET], "num_envs": ENVS},
    track={"mlflow": True},
    checkpoint_every=EVAL_EVERY or STEPS // 2,
)
first_half = drivelab.train("sac", steps=STEPS // 2, seed=0, run_dir=RUNS / "sac", progress=False, **config)
if "eval/route_completion" in first_half.metrics:
    print(f"after {STEPS // 2:,} steps: evaluation route completion {first_half.metrics['eval/route_completion']:.1%}")

# %% [markdown]
# ## Resuming from MLflow
#
# A run on another machine (or a deleted run directory) can continue from its MLflow record:
# `drivelab train --resume mlflow:RUN_ID` fetches the latest checkpoint artifact, config
# included, and continues exactly where it stopped: the replay buffer, the optimisers, the
# temperature, the env seeds. Here the local run directory is deleted first, to show that nothing
# else is needed.

# %%
mlflow.set_tracking_uri(f"sqlite:///{(RUNS / 'mlflow.db').resolve()}")
(mlflow_run,) = mlflow.search_runs(search_all_experiments=True, output_format="list")
print("MLflow run", mlflow_run.info.run_id, "params:", {k: v for k, v in list(mlflow_run.data.params.items())[:5]}, "...")
shutil.rmtree(RUNS / "sac")
drivelab_cli("train", "--resume", f"mlflow:{mlflow_run.info.run_id}", "--mlflow-uri", mlflow.get_tracking_uri(),
             "--run-dir", str(RUNS / "sac"),
             "--steps", str(STEPS), "--no-progress")

# %% [markdown]
# ## Learning curves
#
# Training episodes (sampled steering, dots and a rolling mean) and the evaluation periods
# (deterministic steering on unseen roads, squares).

# %%
logged = read_metrics(RUNS / "sac")
fig, axes = plt.subplots(1, 3, figsize=(15, 3.6))
for ax, name in zip(axes, ("return", "route_completion", "mean_abs_cte")):
    if f"episode/{name}" in logged:
        steps, _, values = logged[f"episode/{name}"]
        ax.plot(steps, values, ".", alpha=0.2, color="C0")
        ax.plot(steps, rolling_mean(values, 20), color="C0", label="training (sampled)")
    if f"eval/{name}" in logged:
        steps, _, values = logged[f"eval/{name}"]
        ax.plot(steps, values, "s-", color="C1", label="evaluation (deterministic, unseen roads)")
    ax.axvline(HEAT_UP, color="gray", ls=":", lw=1)
    ax.set_xlabel("env steps (dotted: end of the heat-up)")
    ax.set_title(name)
axes[0].legend(fontsize=8)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## The result, and the car on video
#
# The best checkpoint (chosen by the evaluation periods) on 10 roads it was neither trained nor
# chosen on (the task's scenarios start at seed 1000; these start at 0; `drivelab eval RUN/best
# --env drivelab/MetaDriveLaneFollow-v0 --episodes 10` prints the same), then one episode filmed.

# %%
chosen = RUNS / "sac" / "best" if EVAL_EVERY else RUNS / "sac"   # the quick budget has no evaluation periods
row = drivelab.evaluate(drivelab.load(chosen), "drivelab/MetaDriveLaneFollow-v0",
                        episodes={"quick": 1, "full": 10}[BUDGET], seed=0, num_envs=ENVS)
print(f"unseen roads: route completion {row['route_completion']:.1%}, mean |CTE| {row['mean_abs_cte']:.2f} m, "
      f"success {row['success_rate']:.0%}, out of road {row['out_of_road_rate']:.0%}")
drivelab_cli("eval", str(chosen), "--episodes", "1", "--seed", "0", "--video", str(RUNS / "sac.mp4"),
             "--no-progress")
display(Video(str(RUNS / "sac.mp4"), embed=True))

# %% [markdown]
# ## Exercises
#
# * Replace the fixed throttle by a speed controller (`env.kwargs: {target_speed: 8.0}` instead of
#   `env.fixed_throttle`): is the
#   steering easier to learn at a constant speed?
# * Change the reward's `scale` in a copy of `cte.yaml` and compare the two on the same episodes
#   with `drivelab reward compare` (lesson 5 does this).
# * Set `sac.learning_starts` to 0: what does learning from the first, almost empty buffer do?
