"""drivelab: reinforcement learning for driving simulators.

Importing drivelab registers its Gymnasium ids (the MetaDrive ids the course notebooks use,
``MetaDrive-validation-v0`` and friends), so ``gym.make("MetaDrive-validation-v0")`` works.
"""

from drivelab.envs.registration import register_envs

__version__ = "0.1.0"

register_envs()
