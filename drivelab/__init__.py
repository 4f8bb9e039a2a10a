"""drivelab: reinforcement learning for driving simulators.

    import drivelab
    result = drivelab.train("ppo", "CartPole-v1", steps=50_000)
    policy = drivelab.load(result.run_dir)
    drivelab.evaluate(policy, episodes=10)

Importing drivelab registers its Gymnasium ids (MetaDrive's scenario sets such as
``MetaDrive-10env-v0`` and ``MetaDrive-validation-v0``, and drivelab's tasks), so
``gym.make("MetaDrive-validation-v0")`` works.
"""

from drivelab.envs.registration import register_envs
from drivelab.version import __version__

__all__ = ["__version__", "train", "load", "evaluate", "make_env", "build_config"]

register_envs()

_API = ("train", "load", "evaluate", "make_env", "build_config")


def __getattr__(name: str):
    """``drivelab.train``, ``drivelab.load``, ``drivelab.evaluate``, ``drivelab.make_env``,
    ``drivelab.build_config`` (:mod:`drivelab.api`), imported on first use so that ``import
    drivelab`` stays light."""
    if name in _API:
        from drivelab import api

        return getattr(api, name)
    raise AttributeError(f"module 'drivelab' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The lazy API too, so that tab completion in a notebook shows ``drivelab.train`` & co."""
    return sorted({*globals(), *_API})
