"""Reference policies for MetaDrive, evaluated exactly like trained checkpoints.

A number only means something next to a reference. This module gives three, each played on the
same env (drivelab's MetaDrive adapter, e.g. ``MetaDrive-validation-v0``), with the same seeds
(episode k is reset with seed k, i.e. scenario k) and the same metrics (``success``,
``route_completion``, ``crash``, ``out_of_road`` from the last step's ``info``):

* ``random``: actions drawn uniformly from the action space by a seeded generator. The floor.
* ``lane-keeping``: :func:`lane_keeping_controller`, a proportional
  controller that steers against the cross-track and heading errors that the MetaDrive adapter
  reports in ``info`` (``cte``, ``heading_error``) and holds the throttle at 0.5. It sees the lane
  geometry directly (privileged information a learned policy does not get) and ignores traffic.
* ``metadrive-expert``: MetaDrive's own PPO expert, shipped with MetaDrive as
  ``metadrive.examples.ppo_expert`` (an MLP 275 -> 256 -> 256 -> 4 with tanh, trained by the
  MetaDrive authors with RLlib; its numpy weights ``expert_weights.npz`` are in the wheel). We use
  its deterministic action (the Gaussian's mean). It does not read the env's observation: it
  builds its own 275-d observation from the ego vehicle (19 ego/navigation values, the 4 nearest
  vehicles as 4 x 4 values, 240 lidar rays to 50 m), so it needs the live MetaDrive vehicle and
  engine. To observe, it briefly switches the vehicle's sensor config to its own (lidar with
  ``num_others=4``) and back. It needs no 3D assets and downloads nothing. A strong reference:
  a trained agent that gets near it has learned to drive. With ``deterministic=False`` (``drivelab
  eval --stochastic``) it samples from its Gaussian instead, so that a trained policy whose actions
  are sampled is compared with a sampled expert.

Each is evaluated with the protocol of a trained checkpoint (deterministic unless asked, one
episode per scenario); ``drivelab eval --policy NAME`` prints its success, route completion,
crash and out-of-road rates (one episode can both crash and leave the road), and
docs/results.md records what each baseline scores. What to expect:
the lane keeper's constant throttle is a constant engine force on MetaDrive, so the car keeps
speeding up until it leaves the road in a curve or runs into traffic. The random policy's
throttle averages zero: the car creeps and its episodes run to the horizon.

How it works. MetaDrive runs in ``spawn``ed subprocesses (one engine per process), so a baseline
that needs the simulator's internals (the expert needs the vehicle, lane keeping needs ``info``)
cannot run in the main process, where the policy lives. Instead, a wrapper applied to each env
inside its process computes the baseline's action and returns it *as the observation*
(:class:`ExpertActionObservation`, :class:`LaneKeepingObservation`); the policy in the main
process, :class:`ObservationIsAction`, then just sends the observation back as the action. The
evaluation loop is the one trained policies use, unchanged::

    wrapper, policy = baseline("metadrive-expert", action_space)
    envs = make_vector_env(env_cfg, autoreset_mode=AutoresetMode.DISABLED, wrapper=wrapper)
    result = drivelab.training.collection.evaluation.run_episodes(envs, policy, episodes=30)

(:func:`drivelab.tools.policies.evaluate_baseline` does this; ``drivelab eval --policy metadrive-expert``.)
"""

from __future__ import annotations

import copy
import difflib
import functools
from typing import TYPE_CHECKING, Any, Callable

import gymnasium as gym
import numpy as np

from drivelab.errors import DrivelabError

if TYPE_CHECKING:  # torch is imported where a policy acts, so that the CLI's --help needs none
    import torch

BASELINES = ("random", "lane-keeping", "metadrive-expert")

__all__ = ["BASELINES", "baseline", "ExpertActionObservation", "LaneKeepingObservation", "ObservationIsAction",
           "RandomPolicy", "lane_keeping_controller"]


def lane_keeping_controller(info: dict, k_cte: float = 0.5, k_heading: float = 1.5, throttle: float = 0.5) -> tuple[float, float]:
    """A proportional lane keeper on privileged lane geometry: steer against the CTE and the
    heading error (both positive to the left, so steering right is negative); hold the throttle."""
    steering = float(np.clip(-(k_cte * info["cte"] + k_heading * info["heading_error"]), -1.0, 1.0))
    return steering, throttle


def _check_steering_throttle(space: gym.Space, who: str) -> None:
    """The expert and the lane keeper output [steering, throttle]: refuse any other action space."""
    if not (isinstance(space, gym.spaces.Box) and space.shape == (2,)):
        raise DrivelabError(f"the {who} baseline needs a Box(2,) [steering, throttle] action space, got {space}")


def _action_box(space: gym.spaces.Box) -> gym.spaces.Box:
    """A float32 Box with the bounds of the action space: the observation space of the wrappers."""
    return gym.spaces.Box(space.low.astype(np.float32), space.high.astype(np.float32), space.shape, np.float32)


class ExpertActionObservation(gym.Wrapper):
    """Replaces the observation by MetaDrive's PPO expert action for the current state.

    After ``reset`` and after every ``step`` the expert (``metadrive.examples.ppo_expert``: the
    mean of its Gaussian, or with ``deterministic=False`` a sample of it) is asked what to do in
    the ego vehicle's current state; that action, clipped to the action bounds, is returned as
    the observation. Observation: float32 (2,)
    [steering, throttle], the observation space is the env's action Box. Actions, rewards and
    ``info`` pass through unchanged.

    ``env`` must be drivelab's MetaDrive adapter (:class:`drivelab.envs.metadrive.MetaDriveGym`,
    possibly under other wrappers) with a Box(2,) [steering, throttle] action space. Building the
    wrapper starts no engine; the expert is imported and run only from ``reset`` on.

    MetaDrive's expert samples with numpy's global generator; this wrapper seeds it in ``reset``
    with the episode's seed (in the env's own process), so sampled episodes repeat too.
    """

    def __init__(self, env: gym.Env, deterministic: bool = True):
        from drivelab.envs.metadrive import MetaDriveGym

        super().__init__(env)
        self.deterministic = deterministic
        if not isinstance(env.unwrapped, MetaDriveGym):
            raise DrivelabError(f"the metadrive-expert baseline needs a MetaDrive env, got {_env_name(env)}")
        _check_steering_throttle(env.action_space, "metadrive-expert")
        self.observation_space = _action_box(env.action_space)

    def _expert_action(self) -> np.ndarray:
        """The expert's (2,) float32 action for the ego vehicle of the wrapped MetaDrive env."""
        # Importing metadrive.examples imports the torch variant too; we call the numpy one
        # explicitly, so that nothing runs on a GPU and the result does not depend on torch.
        from metadrive.examples.ppo_expert.numpy_expert import expert

        vehicle = self.env.unwrapped.metadrive.agent
        action = expert(vehicle, deterministic=self.deterministic)  # (2,) the Gaussian's mean, or a sample
        return np.clip(action, self.observation_space.low, self.observation_space.high).astype(np.float32)

    def reset(self, **kwargs: Any):
        _, info = self.env.reset(**kwargs)
        if not self.deterministic and kwargs.get("seed") is not None:
            np.random.seed(kwargs["seed"])
        return self._expert_action(), info

    def step(self, action):
        _, reward, terminated, truncated, info = self.env.step(action)
        return self._expert_action(), reward, terminated, truncated, info


class LaneKeepingObservation(gym.Wrapper):
    """Replaces the observation by the lane-keeping controller's action.

    The controller (:func:`lane_keeping_controller`) reads ``cte`` and
    ``heading_error`` from the ``info`` of ``reset`` and ``step``. Observation: float32 (2,)
    [steering, throttle]; the observation space is the env's action Box. Works on any env whose
    ``info`` carries the lane geometry (drivelab's MetaDrive adapter does) and whose action is a
    Box(2,) [steering, throttle].
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        _check_steering_throttle(env.action_space, "lane-keeping")
        self.observation_space = _action_box(env.action_space)

    def _controller_action(self, info: dict) -> np.ndarray:
        if "cte" not in info or "heading_error" not in info:
            raise DrivelabError(f"the lane-keeping baseline needs 'cte' and 'heading_error' in info; "
                                f"{_env_name(self.env)} does not report them (use a MetaDrive env)")
        action = np.array(lane_keeping_controller(info), np.float32)
        return np.clip(action, self.observation_space.low, self.observation_space.high)

    def reset(self, **kwargs: Any):
        _, info = self.env.reset(**kwargs)
        return self._controller_action(info), info

    def step(self, action):
        _, reward, terminated, truncated, info = self.env.step(action)
        return self._controller_action(info), reward, terminated, truncated, info


class ObservationIsAction:
    """The policy half of the wrapper baselines: the observation already is the action.

    Args:
        action_space: the env's Box action space; ``to_env`` clips to its bounds.
    """

    def __init__(self, action_space: gym.spaces.Box):
        self.low = np.asarray(action_space.low, np.float32)
        self.high = np.asarray(action_space.high, np.float32)

    def act(self, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        """(B, 2) observations -> (B, 2) float32 actions, the same values."""
        return obs.float()

    def to_env(self, action: torch.Tensor) -> np.ndarray:
        """(B, 2) actions -> (B, 2) float32 numpy array clipped to the action bounds."""
        return np.clip(action.cpu().numpy().astype(np.float32), self.low, self.high)


class RandomPolicy:
    """Uniformly random actions from a seeded copy of the action space (any Gymnasium space).

    The observation is only used for the batch size; ``deterministic`` is ignored (the sequence
    of actions is fixed by ``seed``).
    """

    # One generator for every env: the actions depend on the order the envs ask for them, which only
    # the evaluation loop in this process fixes (drivelab.training.collection.evaluation.plays_in_workers).
    shared_generator = True

    def __init__(self, action_space: gym.Space, seed: int = 0):
        self.space = copy.deepcopy(action_space)  # seeding the caller's space would change its samples
        self.space.seed(seed)
        self.discrete = isinstance(action_space, gym.spaces.Discrete)

    def act(self, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        """(B, ...) observations -> (B, *action_shape) actions, one independent sample per row."""
        import torch

        samples = np.stack([np.asarray(self.space.sample()) for _ in range(obs.shape[0])])
        return torch.as_tensor(samples)

    def to_env(self, action: torch.Tensor) -> np.ndarray:
        """(B, *action_shape) actions as a numpy array: ints for Discrete, clipped floats for Box."""
        array = action.cpu().numpy()
        if isinstance(self.space, gym.spaces.Box):
            return np.clip(array, self.space.low, self.space.high).astype(self.space.dtype)
        return array


def baseline(name: str, action_space: gym.Space, seed: int = 0, deterministic: bool = True
             ) -> tuple[Callable[[gym.Env], gym.Wrapper] | None, ObservationIsAction | RandomPolicy]:
    """A reference policy by name (one of :data:`BASELINES`).

    Args:
        name: ``"random"``, ``"lane-keeping"`` or ``"metadrive-expert"``.
        action_space: the action space of one env (``drivelab.envs.env_spaces``).
        seed: seed of the random policy's generator.
        deterministic: False samples the expert's actions (the random policy always samples,
            the lane keeper never does).

    Returns:
        ``(wrapper, policy)``: the wrapper (a class, or a partial of one) to apply to each env
        (inside its process), or None when the env needs none; and the policy, an object with
        ``act(obs, deterministic)`` and ``to_env(action)`` like a trained policy.
    """
    if name == "random":
        return None, RandomPolicy(action_space, seed)
    if name == "lane-keeping":
        _check_steering_throttle(action_space, name)
        return LaneKeepingObservation, ObservationIsAction(action_space)
    if name == "metadrive-expert":
        _check_steering_throttle(action_space, name)
        wrapper = functools.partial(ExpertActionObservation, deterministic=deterministic)
        return wrapper, ObservationIsAction(action_space)
    close = difflib.get_close_matches(name, BASELINES, n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    raise DrivelabError(f"unknown baseline '{name}'{hint}; choose from {', '.join(BASELINES)}")


def _env_name(env: gym.Env) -> str:
    return env.spec.id if env.spec is not None else type(env.unwrapped).__name__
