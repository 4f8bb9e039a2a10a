"""``drivelab reward plot`` and ``drivelab reward compare``: look at reward functions before
training on them. ``plot`` draws one config's reward against the cross-track and heading errors;
``compare`` scores the same recorded episodes under several configs, to see which one ranks good
driving (route completion) highest.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import numpy as np

from drivelab.envs.rewards import TERMS, score, validate_reward_config
from drivelab.errors import DrivelabError
from drivelab.tools.baselines import lane_keeping_controller
from drivelab.tools.tables import format_table


def load_reward_config(path: str | Path) -> dict[str, dict]:
    """A reward config file: either {term: params} or a training config with env.reward."""
    from drivelab.config import read_yaml

    data = read_yaml(path)
    if "env" in data and isinstance(data["env"], dict) and "reward" in data["env"]:
        data = data["env"]["reward"]
    return validate_reward_config(data, where=str(path))


def _step_info(cte: float = 0.0, heading_error: float = 0.0, speed: float = 10.0) -> dict:
    return {"cte": cte, "heading_error": heading_error, "speed": speed,
            "speed_along_lane": speed * np.cos(heading_error), "collided": False, "out_of_road": False,
            "route_completion": 0.0, "native_reward": 0.0}


def plot_reward(config: dict[str, dict], out: str | Path, max_cte: float = 3.0, speed: float = 10.0) -> Path:
    """Reward of one step against CTE (heading error 0) and against heading error (CTE 0), at a
    fixed speed, total and per term; written to ``out`` as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ctes = np.linspace(-max_cte, max_cte, 241)
    headings = np.linspace(-np.pi / 2, np.pi / 2, 181)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, xs, make, label in ((axes[0], ctes, lambda x: _step_info(cte=x, speed=speed), "cross-track error (m), + = left of centre"),
                                (axes[1], headings, lambda x: _step_info(heading_error=x, speed=speed), "heading error (rad), + = pointing left")):
        rows = [score(config, make(x), None) for x in xs]
        ax.plot(xs, [r[0] for r in rows], color="black", linewidth=2.5, label="total")
        if len(config) > 1:
            for name in config:
                ax.plot(xs, [r[1][name] for r in rows], "--", label=name)
        ends = np.array([r[2] for r in rows])
        if ends.any():
            low, high = ax.get_ylim()
            ax.fill_between(xs, low, high, where=ends, color="red", alpha=0.12, step="mid", label="episode ends")
            ax.set_ylim(low, high)
        ax.set_xlabel(label)
        ax.set_ylabel("reward per step")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(f"reward terms: {', '.join(config)} (speed {speed} m/s)")
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def record_episodes(env_id: str, policy: str, episodes: int, seed: int = 0, env_kwargs: dict | None = None,
                    max_steps: int = 1000) -> list[list[dict]]:
    """Play ``episodes`` episodes with ``policy`` ('random', 'lane-keeping', or a run/checkpoint
    directory) and return each step's info (the lane geometry the reward terms read)."""
    if episodes < 1:
        raise DrivelabError(f"--episodes (episodes to record) must be >= 1, got {episodes}")
    import gymnasium as gym
    import torch

    from drivelab.config import EnvConfig
    from drivelab.envs import make_env

    act: Callable[[Any, dict], Any]
    if policy in ("random", "lane-keeping"):
        env = make_env(EnvConfig(id=env_id, kwargs=dict(env_kwargs or {})))
        space = env.action_space
        if policy == "random":
            space.seed(seed)
            act = lambda obs, info: space.sample()  # noqa: E731
        else:
            if not (isinstance(space, gym.spaces.Box) and space.shape in ((1,), (2,))):
                env.close()
                raise DrivelabError(f"the lane-keeping controller needs [steering] or [steering, throttle] actions; {env_id} has {space}")
            act = lambda obs, info: np.array(lane_keeping_controller(info)[: space.shape[0]], np.float32)  # noqa: E731
    else:
        from drivelab.tools.policies import checkpoint_config, policy_from_checkpoint
        from drivelab.training.outputs.checkpoint import load_checkpoint

        ckpt = load_checkpoint(policy)
        cfg = checkpoint_config(ckpt)
        if env_id == cfg.env.id:  # the training env's kwargs may shape the action space (target_speed)
            env_kwargs = {**cfg.env.kwargs, **(env_kwargs or {})}
        # The checkpoint's action and observation adapters; its reward shaping is what is compared.
        env_cfg = dataclasses.replace(cfg.env, id=env_id, kwargs=dict(env_kwargs or {}), reward=None)
        env = make_env(env_cfg)
        net = policy_from_checkpoint(ckpt, cfg, env_cfg)
        act = lambda obs, info: net.to_env(net.act(torch.as_tensor(obs)[None], deterministic=True))[0]  # noqa: E731
    trajectories = []
    try:
        for k in range(episodes):
            obs, info = env.reset(seed=seed + k)
            steps = [info]
            for _ in range(max_steps):
                obs, _, terminated, truncated, info = env.step(act(obs, info))
                steps.append(info)
                if terminated or truncated:
                    break
            if "cte" not in info:
                raise DrivelabError(f"{env_id} reports no lane geometry ('cte' in info): use a driving env")
            trajectories.append(steps)
    finally:
        env.close()
    return trajectories


def compare_rewards(trajectories: list[list[dict]], configs: dict[str, dict[str, dict]]) -> dict[str, dict[str, float]]:
    """Score the same trajectories under each reward config. A config that would have ended an
    episode earlier (e.g. beyond max_cte) stops counting there, as it would have in training."""
    table = {}
    for name, config in configs.items():
        totals, lengths, per_term = [], [], {t: [] for t in config}
        for steps in trajectories:
            total, term_sums, n = 0.0, dict.fromkeys(config, 0.0), 0
            for prev, info in zip(steps[:-1], steps[1:]):
                reward, parts, end = score(config, info, prev)
                total += reward
                n += 1
                for t, v in parts.items():
                    term_sums[t] += v
                if end:
                    break
            totals.append(total)
            lengths.append(n)
            for t, v in term_sums.items():
                per_term[t].append(v)
        completion = [steps[-1].get("route_completion", 0.0) for steps in trajectories]
        corr = float(np.corrcoef(totals, completion)[0, 1]) if len(totals) > 1 and np.std(totals) > 0 and np.std(completion) > 0 else float("nan")
        table[name] = {"return_mean": float(np.mean(totals)), "return_std": float(np.std(totals)),
                       "steps_counted": float(np.mean(lengths)), "corr_with_route_completion": corr,
                       **{f"term/{t}": float(np.mean(v)) for t, v in per_term.items()}}
    return table


def format_comparison(table: dict[str, dict[str, float]]) -> str:
    """The table of :func:`compare_rewards`, one line per reward config: the episodes' reward
    (mean ± std), the steps counted, its correlation with route completion, and each term's sum."""
    rows = [[name, f"{row['return_mean']:.2f} ± {row['return_std']:.2f}", f"{row['steps_counted']:.0f}",
             f"{row['corr_with_route_completion']:.2f}",
             ", ".join(f"{k[5:]}={v:.1f}" for k, v in row.items() if k.startswith("term/"))] for name, row in table.items()]
    return format_table(["reward config", "episode reward (mean ± std)", "steps", "corr(route)", "terms"], rows, align="lrrrl")


def plot_comparison(trajectories: list[list[dict]], configs: dict[str, dict[str, dict]], out: str | Path) -> Path:
    """Cumulative reward along the first trajectory under each config, and |CTE| along it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = trajectories[0]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for name, config in configs.items():
        cumulative, total = [], 0.0
        for prev, info in zip(steps[:-1], steps[1:]):
            total += score(config, info, prev)[0]
            cumulative.append(total)
        ax1.plot(cumulative, label=name)
    ax1.set_ylabel("cumulative reward")
    ax1.legend()
    ax1.grid(alpha=0.3)
    ax2.plot([abs(s["cte"]) for s in steps[1:]], color="gray")
    ax2.set_ylabel("|CTE| (m)")
    ax2.set_xlabel("step (episode 0)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


__all__ = ["TERMS", "load_reward_config", "plot_reward", "record_episodes", "compare_rewards", "format_comparison",
           "plot_comparison", "lane_keeping_controller"]
