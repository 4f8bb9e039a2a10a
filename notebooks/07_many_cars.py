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
# # Lesson 7: many cars learning together
#
# **What it teaches.** A scene where every car is a learning agent: MetaDrive's multi-agent
# Intersection, 30 cars at once, arriving, crashing and respawning during one episode. Its
# interface (PettingZoo's parallel API: a dict of observations in, a dict of actions out, agents
# that come and go); independent PPO with one policy shared by every car (IPPO), and how a
# car's experience becomes a batch; the metrics over cars and scenes; the learned policy driving
# every car of a scene.
#
# **The seed lesson.** None of the five seed notebooks has more than one learner: their cars drive
# alone (`000`, `003`) or among scripted traffic. This lesson takes lesson 1's MetaDrive and
# lesson 3's actor-critic into a scene of learners, as MetaDrive's multi-agent benchmark (Peng et
# al. 2021, "Learning to Simulate Self-Driven Particles", CoPO) poses it.
#
# **The result it reproduces.** IPPO starts to learn the Intersection: the share of cars that
# reach their destination climbs from 0. At the full budget (`BUDGET = "full"`: 40,960 scene steps,
# some 1.2 million car decisions, about 15 minutes on two cores) 15.7% of the last 300 cars'
# episodes arrived (0% until 20,480 steps), 52% crashed and 35% left the road (from 49% at the
# start). That is early: `benchmarks/multiagent.py` trains six times as many steps. Numbers and commit: `benchmarks/results/notebooks_full.json`. The quick budget
# (what CI runs, about a minute) runs every cell on one iteration.

# %%
import os
import shutil
from pathlib import Path

import imageio.v2 as imageio
import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Video, display

import drivelab
from drivelab.envs.multiagent import MultiAgentDrive
from drivelab.training.outputs.plots import read_metrics
from drivelab.training.outputs.statistics import rolling_mean

BUDGET = os.environ.get("DRIVELAB_NOTEBOOK_BUDGET", "quick")  # "quick" (a minute) or "full" (about 15 minutes)
STEPS = {"quick": 128, "full": 40_960}[BUDGET]            # scene steps: one step moves every car
ROLLOUT = {"quick": 64, "full": 256}[BUDGET]              # steps per scene and iteration (the config's: 256)
FILM_STEPS = {"quick": 30, "full": 400}[BUDGET]           # steps of the filmed scene
RUN = "runs/lesson7/ippo"
shutil.rmtree(Path(RUN).parent, ignore_errors=True)  # each run of the notebook starts afresh (runs/ holds its runs)

# %% [markdown]
# ## A scene of agents, through PettingZoo
#
# `MultiAgentDrive` is one MetaDrive scene behind PettingZoo's `ParallelEnv`: `reset` returns an
# observation per car, `step` takes an action per car in `env.agents` and returns dicts of
# observations, rewards, terminations and truncations. A car that arrives, crashes or leaves the
# road is done and leaves `env.agents`; a new car (a new agent name) takes its place. Every car
# sees what a single MetaDrive car sees (lidar, its state, the road ahead, 91 numbers here) and
# takes [steering, throttle].

# %%
scene = MultiAgentDrive("Intersection", num_agents=30)
observations, infos = scene.reset(seed=0)
print(len(scene.agents), "cars; observation", scene.observation_space(scene.agents[0]).shape,
      "action", scene.action_space(scene.agents[0]))
rng = np.random.default_rng(0)
seen, ended = set(scene.agents), 0
for _ in range(150):
    actions = {car: np.array([rng.uniform(-1, 1), 1.0], np.float32) for car in scene.agents}  # random steering, full throttle
    observations, rewards, terminations, truncations, infos = scene.step(actions)
    ended += sum(terminations[c] or truncations[c] for c in terminations)
    seen |= set(scene.agents)
print(f"150 steps (15 s) of random steering at full throttle: {ended} cars' episodes ended, {len(seen)} cars took part, {len(scene.agents)} on the road now")
scene.close()

# %% [markdown]
# ## IPPO: one policy for every car
#
# The cars are alike, so they share one actor-critic; each car's own observations, actions and
# rewards form its own trajectory, with its own GAE, and all trajectories of an iteration form
# one PPO batch (de Witt et al. 2020: independent PPO is a strong baseline on cooperative tasks).
# drivelab steps each scene as K *slots* (`AgentSlots`): a car keeps its slot from arrival to
# departure, a free slot is masked out of the loss, and a car that leaves ends its trajectory as
# terminated (a crash, an arrival) or truncated (its time ran out). `drivelab/algos/ippo.py` is
# the loop; MAPPO (`--config ma_intersection_mappo`) adds a critic that also sees the cars nearby.

# %%
print(open(os.path.join(os.path.dirname(drivelab.__file__), "configs", "ma_intersection.yaml")).read())

# %%
result = drivelab.train(config="ma_intersection", steps=STEPS, seed=0, run_dir=RUN, progress=False,
                        checkpoint_every=STEPS, log_every=min(5120, STEPS), ippo={"num_steps": ROLLOUT})
print({k: round(v, 3) for k, v in result.metrics.items() if k.startswith("episode/")})

# %% [markdown]
# ## What the cars learned
#
# Every finished car episode counts: success (arrived), crash, off road, over the last 300 cars.

# %%
logged = read_metrics(RUN)
fig, ax = plt.subplots(figsize=(8, 3.8))
for i, name in enumerate(("success_rate", "crash_rate", "out_of_road_rate")):
    if f"episode/{name}" in logged:
        steps, _, values = logged[f"episode/{name}"]
        ax.plot(steps, values, "o-", color=f"C{i}", label=name)
ax.set_xlabel("scene steps")
ax.set_ylabel("share of the last 300 cars' episodes")
ax.legend()
plt.show()

# %% [markdown]
# ## The policy driving every car
#
# The learned policy acts for a batch of observations at once: every car on the road, each step,
# with its deterministic action. The scene, filmed from above:

# %%
policy = drivelab.load(RUN)
scene = MultiAgentDrive("Intersection", num_agents=30, render_mode="rgb_array")
observations, _ = scene.reset(seed=100)
frames, outcomes = [], {"arrived": 0, "crashed": 0, "off road": 0}
for _ in range(FILM_STEPS):
    cars = list(scene.agents)
    if not cars:
        break
    actions = policy.act(np.stack([observations[c] for c in cars]))
    observations, rewards, terminations, truncations, infos = scene.step(dict(zip(cars, actions)))
    for car, done in terminations.items():
        if done:
            info = infos[car]
            key = "arrived" if info.get("arrive_dest") else "crashed" if info.get("crash") else "off road"
            outcomes[key] += 1
    frames.append(scene.render())
scene.close()
imageio.mimsave("scene.mp4", frames, fps=10)
print(f"{FILM_STEPS} steps: {outcomes}")
display(Video("scene.mp4", embed=True))

# %% [markdown]
# `drivelab eval RUN --episodes 5` plays whole scene episodes and reports the metrics over cars
# and CoPO's per-scene measures (crashes, efficiency, cars on the road); `benchmarks/multiagent.py`
# trains IPPO and MAPPO on several scenes and seeds and compares them with CoPO's published numbers
# (`docs/results.md`, "Multi-agent scenes").
#
# ## Exercises
#
# * Train MAPPO (`--config ma_intersection_mappo`) for the same steps: does the neighbours'
#   information help the critic, and the cars?
# * The Roundabout (`--env.id MultiAgentRoundabout-v0`) with the Intersection's policy: `drivelab
#   eval RUN --env MultiAgentRoundabout-v0`. What carries over?
# * Fewer cars (`--env.kwargs.num_agents 10`): an easier scene, or a different one?
