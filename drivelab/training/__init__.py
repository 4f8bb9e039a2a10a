"""What every algorithm's loop uses, in four rooms (each imports only the rooms before it):

* :mod:`~drivelab.training.learning`: the maths of learning: returns and advantages, losses,
  optimisers, networks, normalisation, rollout and replay storage, hyperparameters.
* :mod:`~drivelab.training.outputs`: what a run records and writes: episode statistics,
  checkpoints, metrics (CSV, TensorBoard, MLflow, W&B), plots, videos, statistics.
* :mod:`~drivelab.training.collection`: playing the envs: the on-policy and replay collectors,
  exploration, rollouts played in the env workers, evaluation episodes.
* :mod:`~drivelab.training.run`: :class:`~drivelab.training.run.Run`, the services a loop calls
  (run directory, metrics, periodic evaluation, checkpoints and resume, timing).
"""
