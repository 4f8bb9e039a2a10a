"""Record a reference policy's transitions as prior data for an off-policy learner
(``drivelab demos``; :mod:`drivelab.training.outputs.demonstrations` holds the file format).

The policy (a run, a checkpoint or a shipped driver) plays the *learner's* env, as the learner's
config builds it (reward terms, action repeat, observation filters), so that every stored row is
one the learner could have stored itself: observation, action in the learner's [-1, 1] units,
reward, next observation (the final one at an episode's end), terminated and truncated kept
apart, and the step's cost. Each env is reset from a seed drawn from ``seed``; what collecting
took (env steps, seconds) goes into the file, for the budget of a run that learns from it.
"""

from __future__ import annotations

import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from tqdm.auto import tqdm

from drivelab.envs import make_vector_env
from drivelab.envs.config import EnvConfig
from drivelab.errors import DrivelabError
from drivelab.tools.policies import TrainedPolicy, check_fits_env
from drivelab.training.outputs.demonstrations import save_demonstrations
from drivelab.training.outputs.episodes import step_costs


def to_unit_actions(actions: np.ndarray, space: gym.spaces.Box) -> np.ndarray:
    """Simulator actions -> the learner's [-1, 1] units (the inverse of its affine ``to_env``), clipped."""
    low, high = space.low.astype(np.float64), space.high.astype(np.float64)
    return np.clip(2.0 * (actions - low) / (high - low) - 1.0, -1.0, 1.0).astype(np.float32)


def record_demonstrations(policy: TrainedPolicy, env_cfg: EnvConfig, steps: int, out: str | Path, seed: int = 0,
                          deterministic: bool = True, progress: bool = True) -> Path:
    """Play ``policy`` in ``env_cfg``'s envs for at least ``steps`` env steps (whole vector steps)
    and write the transitions to ``out``; returns the file's path."""
    if steps < 1:
        raise DrivelabError(f"steps: expected an integer >= 1, got {steps}")
    envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED)
    try:
        obs_space, act_space = envs.single_observation_space, envs.single_action_space
        if not isinstance(act_space, gym.spaces.Box):
            raise DrivelabError(f"env: {env_cfg.id} has {act_space} actions; prior data are for the off-policy "
                                "learners, whose actions are continuous (Box)")
        check_fits_env(policy, (obs_space, act_space), env_cfg.id)
        n = envs.num_envs
        rows = -(-steps // n) * n
        data = {"obs": np.zeros((rows, *obs_space.shape), obs_space.dtype),
                "next_obs": np.zeros((rows, *obs_space.shape), obs_space.dtype),
                "actions": np.zeros((rows, int(np.prod(act_space.shape))), np.float32),
                "rewards": np.zeros(rows, np.float32), "terminated": np.zeros(rows, bool),
                "truncated": np.zeros(rows, bool), "costs": np.zeros(rows, np.float32)}
        rng = np.random.default_rng(seed)
        started, episodes = time.perf_counter(), 0
        obs, _ = envs.reset(seed=rng.integers(0, 2**31 - 1, size=n).tolist())
        with tqdm(total=rows, desc="demonstrations", unit="step", disable=not progress, dynamic_ncols=True) as bar:
            for row in range(0, rows, n):
                action = policy.act(obs, deterministic=deterministic)
                next_obs, reward, terminated, truncated, info = envs.step(action)
                done = terminated | truncated
                block = slice(row, row + n)
                data["obs"][block], data["next_obs"][block] = obs, next_obs
                data["actions"][block] = to_unit_actions(np.asarray(action, np.float64).reshape(n, -1), act_space)
                data["rewards"][block], data["costs"][block] = reward, step_costs(info, done)
                data["terminated"][block], data["truncated"][block] = terminated, truncated
                obs = next_obs
                if done.any():  # with autoreset disabled, reset the envs that ended, each from a fresh seed
                    episodes += int(done.sum())
                    seeds = [int(rng.integers(0, 2**31 - 1)) if d else None for d in done]
                    obs, _ = envs.reset(seed=seeds, options={"reset_mask": done})
                bar.update(n)
        seconds = time.perf_counter() - started
    finally:
        envs.close()
    return save_demonstrations(out, data, obs_space, act_space, env=env_cfg.id, policy=str(policy.checkpoint),
                               deterministic=deterministic, seed=seed, env_steps=rows, episodes=episodes,
                               seconds=round(seconds, 1))
