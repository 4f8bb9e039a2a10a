"""Deterministic evaluation of a policy or a checkpoint, with driving metrics.

Episode ``k`` (0-based) is reset with seed ``seed + k``, so an evaluation is reproducible and,
on MetaDrive, ``MetaDrive-validation-v0`` with ``seed=0`` visits scenarios 0, 1, ..., N-1.
Loading a checkpoint to evaluate it is :func:`drivelab.api.evaluate_checkpoint`. Evaluation during
training (:mod:`drivelab.training.run.periodic_evaluation`) plays :func:`evaluation_round`, in the trainer's
process or in an :class:`EvalActor` (``eval.backend: ray``): the same code either way.

:func:`play` (``drivelab eval``) plays deterministic episodes on subprocess envs inside the env
workers, each with a copy of the policy (:func:`run_episodes_in_workers`), as training's
collectors do: no round trip through this process per decision. An episode is reset with its own
seed either way, so the episodes are those :func:`run_episodes` plays, up to two things that
already make :func:`run_episodes`' numbers depend on ``--num-envs``: the float rounding of a batch
of one observation against a batch of N (a discrete action is the same; a continuous one may
differ in its last bits), and, on MetaDrive, the little history an engine carries from one
episode to the next (which episodes a worker played before: route completion may move by tenths
of a percent). ``benchmarks/eval_speed.py`` measures how far the two are apart on MetaDrive.
"""

from __future__ import annotations

import functools
import pickle
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from tqdm.auto import tqdm

from drivelab.config import EvalConfig
from drivelab.envs import EnvConfig, make_vector_env
from drivelab.envs.registration import is_multiagent
from drivelab.envs.supervised import SupervisedVectorEnv
from drivelab.errors import DrivelabError, kill_point
from drivelab.training.collection.scene_evaluation import SceneResult, play_scenes
from drivelab.training.collection.worker_rollouts import EpisodesInWorker
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.outputs.video import Recorder


@dataclass
class EvalResult:
    returns: np.ndarray                      # (episodes,)
    lengths: np.ndarray                      # (episodes,)
    metrics: dict[str, np.ndarray] = field(default_factory=dict)  # driving metric -> (episodes,)

    def summary(self) -> dict[str, float]:
        """Means over the episodes: return (with its std), length and each driving metric. An env
        with a cost adds ``cost_rate``, the cost per step of all episodes together (total cost over
        total steps, Safety Gym's CostRate), beside ``cost``, the mean episode cost."""
        out = {
            "episodes": int(len(self.returns)),
            "return_mean": float(np.mean(self.returns)),
            "return_std": float(np.std(self.returns)),
            "length_mean": float(np.mean(self.lengths)),
        }
        out.update({name: float(np.mean(values)) for name, values in self.metrics.items()})
        if "cost" in self.metrics:
            out["cost_rate"] = float(np.sum(self.metrics["cost"]) / max(int(np.sum(self.lengths)), 1))
        return out

    @classmethod
    def empty(cls, episodes: int) -> EvalResult:
        """Room for ``episodes`` episodes, filled by :meth:`add`."""
        if episodes < 1:
            raise DrivelabError(f"the number of evaluation episodes must be >= 1, got {episodes}")
        return cls(np.zeros(episodes), np.zeros(episodes, np.int64))

    def add(self, k: int, ret: float, length: int, metrics: dict[str, float]) -> None:
        """Store episode ``k``; a metric that only some episodes report is 0 for the others."""
        self.returns[k], self.lengths[k] = ret, length
        for name, value in metrics.items():
            self.metrics.setdefault(name, np.zeros(len(self.returns)))[k] = value


@torch.no_grad()
def run_episodes(envs: VectorEnv, policy, episodes: int, seed: int = 0, deterministic: bool = True,
                 device: torch.device | str = "cpu", recorder=None, bar=None) -> EvalResult:
    """Play exactly ``episodes`` episodes (episode k with seed ``seed + k``) on ``envs``, which must
    use ``AutoresetMode.DISABLED``. ``policy`` has ``act(obs, deterministic)`` and ``to_env(action)``.
    ``recorder`` (:class:`drivelab.training.outputs.video.Recorder`) films env 0's episodes: it is handed the
    envs after every reset and step. ``bar`` (a tqdm bar, or None) advances by one per episode."""
    result = EvalResult.empty(episodes)
    n = envs.num_envs
    episode_of = np.arange(n)                  # which episode env i is playing (>= episodes: idle)
    next_episode = n
    tracker = EpisodeTracker(n)
    finished = 0
    obs, info = envs.reset(seed=[seed + i for i in range(n)])
    if recorder is not None:
        recorder.start(envs, info, episode_of[0])
    while finished < episodes:
        action = policy.act(torch.as_tensor(obs, device=device), deterministic=deterministic)
        env_action = policy.to_env(action)
        obs, reward, terminated, truncated, info = envs.step(env_action)
        done = terminated | truncated
        if recorder is not None:
            recorder.step(envs, env_action[0], reward[0], info, bool(done[0]))
        ended = tracker.step(reward, done, info)
        if not ended:
            continue
        reset_seeds: list[int | None] = [None] * n
        for episode in ended:
            k = episode_of[episode.env]
            if k < episodes:
                result.add(k, episode.ret, episode.length, episode.metrics)
                finished += 1
                if bar is not None:
                    bar.update(1)
                kill_point("mid-video" if recorder is not None else "mid-evaluation")
            episode_of[episode.env] = next_episode
            reset_seeds[episode.env] = seed + next_episode
            next_episode += 1
        if finished < episodes:
            obs, info = envs.reset(seed=reset_seeds, options={"reset_mask": done})
            if recorder is not None and done[0]:
                recorder.start(envs, info, episode_of[0])
    if recorder is not None:
        recorder.close()
    return result


# Each worker plays T decisions per call, with two calls queued: it starts the next as soon as it
# has answered one, and this process hears of finished episodes (the progress bar) every T decisions.
WORKER_CALL_STEPS, WORKER_CALLS_IN_FLIGHT = 64, 2


def run_episodes_in_workers(envs: SupervisedVectorEnv, policy, episodes: int, seed: int = 0,
                            deterministic: bool = True, bar=None) -> EvalResult:
    """:func:`run_episodes`' episodes, each played whole inside one env worker with a copy of
    ``policy`` (``envs`` built with the :class:`EpisodesInWorker` wrapper): worker i plays episodes
    i, i + N, i + 2N, ... When a worker fails, the workers restart (within the env's restart
    budget) and the episodes not yet finished are played again from their start."""
    result = EvalResult.empty(episodes)
    todo = list(range(episodes))
    policy_bytes = pickle.dumps(policy)
    while todo:
        n = envs.num_envs
        shares = [([seed + k for k in todo[i::n]],) for i in range(n)]
        envs.call_queue("start_episodes", policy_bytes, deterministic, each=shares, steps=0)
        if envs.call_next() is None:  # a worker failed before playing: start again
            continue
        todo = _collect_worker_episodes(envs, result, todo, seed, bar)
    return result


def _collect_worker_episodes(envs: SupervisedVectorEnv, result: EvalResult, todo: list[int], seed: int,
                             bar=None) -> list[int]:
    """Keep the workers playing their shares of ``todo`` and store each episode they finish in
    ``result``; returns the episodes left to play: none, or those unfinished when a worker failed."""
    left = set(todo)
    queued = 0
    timeout = envs.step_timeout and envs.step_timeout * WORKER_CALL_STEPS
    while left or queued:  # once every episode is in, the calls still queued are read (they play nothing)
        while left and queued < WORKER_CALLS_IN_FLIGHT:
            envs.call_queue("play_episodes", WORKER_CALL_STEPS, steps=WORKER_CALL_STEPS)
            queued += 1
        answers = envs.call_next(timeout)
        queued -= 1
        if answers is None:  # the workers restarted: the calls queued are gone, and the episodes in play
            return sorted(left)
        for episode in (episode for ended in answers for episode in ended):
            k = episode.seed - seed
            result.add(k, episode.ret, episode.length, episode.metrics)
            left.discard(k)
            if bar is not None:
                bar.update(1)
            kill_point("mid-evaluation")
    return []


def plays_in_workers(env_cfg: EnvConfig, policy, deterministic: bool, recorder=None) -> bool:
    """Whether :func:`play` plays its episodes inside the env workers: for deterministic actions
    on subprocess envs, without a video (frames are filmed in this process), and for a policy
    that can be pickled and that draws from no generator shared by every env (the random
    baseline: its actions depend on the order the envs ask for them)."""
    if recorder is not None or not deterministic or env_cfg.resolved_backend() != "async":
        return False
    if getattr(policy, "shared_generator", False):
        return False
    try:
        pickle.dumps(policy)
    except Exception:  # noqa: BLE001 - a policy that cannot travel (a lambda, a handle) plays here
        return False
    return True


def play(env_cfg: EnvConfig, policy, episodes: int, seed: int = 0, deterministic: bool = True,
         wrapper=None, recorder=None, progress: str | None = None) -> EvalResult | SceneResult:
    """``episodes`` episodes of ``policy`` on a vector env built from ``env_cfg`` (then closed):
    inside the env workers where :func:`plays_in_workers` says so, else stepped from this process;
    with a ``recorder``, the envs render ``rgb_array`` frames for it. Sampled actions
    (``deterministic=False``) come from torch's generator seeded with ``seed``, forked so that the
    caller's generator is left as it was: the same seed gives the same episodes. ``progress`` (a
    label, e.g. the checkpoint) shows the episodes done, and the time left, on a bar (stderr).
    On a multi-agent scene the policy drives every car and ``episodes`` counts scene episodes
    (:func:`drivelab.training.collection.scene_evaluation.play_scenes`)."""
    if is_multiagent(env_cfg.id):
        if wrapper is not None:
            raise DrivelabError(f"the reference policies drive one car; '{env_cfg.id}' is a multi-agent scene")
        return play_scenes(env_cfg, policy, episodes, seed, deterministic, recorder, progress)
    in_workers = plays_in_workers(env_cfg, policy, deterministic, recorder)
    if in_workers:
        wrapper = functools.partial(EpisodesInWorker, inner=wrapper)
    envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED, wrapper=wrapper,
                           render_mode="rgb_array" if recorder is not None else None)
    # as training's bar (drivelab.training.run.metrics), in episodes
    bar = tqdm(total=episodes, desc=progress, unit="episode", dynamic_ncols=True, disable=progress is None,
               mininterval=0.5, smoothing=0.1)
    try:
        if in_workers:
            return run_episodes_in_workers(envs, policy, episodes, seed=seed, deterministic=deterministic, bar=bar)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            return run_episodes(envs, policy, episodes, seed=seed, deterministic=deterministic, recorder=recorder,
                                bar=bar)
    finally:
        bar.close()
        envs.close()


def evaluate_policy(envs: VectorEnv, policy: torch.nn.Module, episodes: int, seed: int,
                    device: torch.device | str = "cpu") -> dict[str, float]:
    """The summary of ``episodes`` deterministic episodes of ``policy`` in eval mode on ``envs``
    (``AutoresetMode.DISABLED``); the policy goes back to the mode it was in."""
    was_training = policy.training
    policy.eval()
    try:
        return run_episodes(envs, policy, episodes, seed=seed, device=device).summary()
    finally:
        policy.train(was_training)


def new_best(summary: dict[str, float], metric: str, best: list[float] | None,
             cost_limit: float | None = None) -> list[float] | None:
    """The score ``[metric, return_mean]`` of ``summary`` when it beats ``best`` (ties, frequent
    for rates over few episodes, go to the higher return), else None; None too when the env does
    not report ``metric``.

    With a ``cost_limit`` (``eval.cost_limit``) the score is ``[feasible, metric, -cost,
    return_mean]``: an evaluation whose mean episode cost is within the limit beats any that is
    not, then the metric decides, then the lower cost. An env without a cost counts as feasible.
    A ``best`` scored by the other rule (the limit set or unset on ``--resume``) cannot be
    compared: the first evaluation under the new rule replaces it."""
    if metric not in summary:
        return None
    score = [summary[metric], summary["return_mean"]]
    if cost_limit is not None:
        cost = summary.get("cost", 0.0)
        score = [float(cost <= cost_limit), summary[metric], -cost, summary["return_mean"]]
    if best is not None and len(best) == len(score) and score <= best:
        return None
    return score


def film_episode(env_cfg: EnvConfig, policy: torch.nn.Module, seed: int, path: Path,
                 device: torch.device | str = "cpu") -> tuple[Path, np.ndarray | None]:
    """Film one deterministic episode (seed ``seed``) of ``policy`` into ``path`` on a fresh
    rendering env; returns the file and a strip of its frames (for TensorBoard)."""
    recorder = Recorder(path, max_episodes=1, thumbnails=8)
    envs = make_vector_env(env_cfg, num_envs=1, autoreset_mode=AutoresetMode.DISABLED, render_mode="rgb_array")
    was_training = policy.training
    policy.eval()
    try:
        run_episodes(envs, policy, 1, seed=seed, device=device, recorder=recorder)
    finally:
        envs.close()
        policy.train(was_training)
    return recorder.paths[0], recorder.strip()


def evaluation_round(envs: VectorEnv, env_cfg: EnvConfig, policy: torch.nn.Module, spec: EvalConfig,
                     best: list[float] | None, video_path: Path, device: torch.device | str = "cpu"
                     ) -> tuple[dict[str, float], tuple[Path, np.ndarray | None] | None]:
    """One periodic evaluation: the summary of ``spec.episodes`` episodes on ``envs`` and, when it
    beats ``best`` and ``spec.video`` is on, (file, frame strip) of one episode filmed into
    ``video_path`` (else None)."""
    summary = evaluate_policy(envs, policy, spec.episodes, spec.seed, device)
    if not spec.video or new_best(summary, spec.best_metric, best, spec.cost_limit) is None:
        return summary, None
    return summary, film_episode(env_cfg, policy, spec.seed, video_path, device)


class EvalActor:
    """The body of the evaluation actor (``eval.backend: ray``): plays :func:`evaluation_round` with
    a copy of the policy on its own envs while the trainer goes on training."""

    def __init__(self, env_cfg: EnvConfig, num_envs: int):
        self.env_cfg = env_cfg
        self.envs = make_vector_env(env_cfg, num_envs=num_envs, autoreset_mode=AutoresetMode.DISABLED)

    def evaluate(self, policy: torch.nn.Module, spec: EvalConfig, best: list[float] | None
                 ) -> tuple[dict[str, float], bytes | None, np.ndarray | None]:
        """(summary, the filmed episode's MP4 bytes or None, its frame strip or None): the actor
        may run on another machine, so the video travels as bytes."""
        with tempfile.TemporaryDirectory() as tmp:
            summary, film = evaluation_round(self.envs, self.env_cfg, policy, spec, best, Path(tmp) / "best.mp4")
            if film is None:
                return summary, None, None
            return summary, film[0].read_bytes(), film[1]

    def close(self) -> None:
        self.envs.close()
