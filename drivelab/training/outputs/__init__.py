"""What a run records and writes: episode statistics and driving metrics, checkpoints
(safetensors + JSON), metrics (CSV, TensorBoard, MLflow, W&B), plots, videos, and the small
statistics they share."""
