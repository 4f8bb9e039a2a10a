"""A run's services: :class:`Run` (composed of the run directory, metrics, periodic evaluation,
checkpoints and timing), which every algorithm's loop calls."""

from drivelab.training.run.run import Callback, Run, RunEvent

__all__ = ["Callback", "Run", "RunEvent"]
