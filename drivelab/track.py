"""Metrics tracking: TensorBoard and CSV always, MLflow when asked.

``metrics.csv`` is tidy (one row per value: ``step,time,name,value``), so a run's metrics load
with ``pandas.read_csv(...).pivot_table(index="step", columns="name", values="value")``.
On resume, rows and TensorBoard events written after the checkpoint are dropped first, so a
killed and resumed run has one clean history.
"""

from __future__ import annotations

import csv
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

from drivelab.config import TrackConfig, config_to_dict
from drivelab.errors import DrivelabError


def _flatten(data: Mapping, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out.update(_flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


class Tracker:
    def __init__(self, run_dir: str | Path, cfg, resume_step: int | None = None):
        from torch.utils.tensorboard import SummaryWriter

        self.run_dir = Path(run_dir)
        self.csv_path = self.run_dir / "metrics.csv"
        if resume_step is not None and self.csv_path.exists():
            self._truncate_csv(resume_step)
        new_file = not self.csv_path.exists()
        self._csv_file = open(self.csv_path, "a", newline="")
        self._csv = csv.writer(self._csv_file)
        if new_file:
            self._csv.writerow(["step", "time", "name", "value"])
        self.tb = SummaryWriter(str(self.run_dir / "tb"), purge_step=resume_step)
        self.mlflow = None
        if cfg.track.mlflow:
            self._start_mlflow(cfg.track, config_to_dict(cfg))

    def _truncate_csv(self, step: int) -> None:
        with open(self.csv_path, newline="") as f:
            rows = list(csv.reader(f))
        kept = [rows[0]] + [r for r in rows[1:] if r and int(r[0]) <= step]
        tmp = self.csv_path.with_suffix(".tmp")
        with open(tmp, "w", newline="") as f:
            csv.writer(f).writerows(kept)
        os.replace(tmp, self.csv_path)

    def _start_mlflow(self, track: TrackConfig, params: dict) -> None:
        try:
            import mlflow
        except ImportError:
            raise DrivelabError("track.mlflow is on but mlflow is not installed: pip install 'drivelab[mlflow]'") from None
        import logging

        logging.getLogger("mlflow").setLevel(logging.WARNING)
        logging.getLogger("alembic").setLevel(logging.WARNING)
        uri = track.mlflow_uri or f"sqlite:///{(self.run_dir / 'mlflow.db').resolve()}"
        mlflow.set_tracking_uri(uri)
        if mlflow.get_experiment_by_name(track.experiment) is None:
            artifacts = (self.run_dir / "mlartifacts").resolve().as_uri() if track.mlflow_uri is None else None
            mlflow.create_experiment(track.experiment, artifact_location=artifacts)
        mlflow.set_experiment(track.experiment)
        id_file = self.run_dir / "mlflow_run_id"
        run_id = id_file.read_text().strip() if id_file.exists() else None
        run = mlflow.start_run(run_id=run_id, run_name=None if run_id else self.run_dir.name)
        if run_id is None:
            id_file.write_text(run.info.run_id)
            # MLflow params are short strings; long lists are cut by MLflow's limit (6000 chars).
            mlflow.log_params({k: str(v)[:500] for k, v in _flatten(params).items()})
            mlflow.log_artifact(str(self.run_dir / "config.yaml"))
        self.mlflow = mlflow

    def log(self, step: int, metrics: Mapping[str, float]) -> None:
        now = time.time()
        clean = {k: float(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}
        for name, value in clean.items():
            self.tb.add_scalar(name, value, step)
            self._csv.writerow([step, f"{now:.3f}", name, f"{value:.6g}"])
        self._csv_file.flush()
        if self.mlflow is not None:
            self.mlflow.log_metrics(clean, step=step)

    def close(self) -> None:
        self.tb.close()
        self._csv_file.close()
        if self.mlflow is not None:
            self.mlflow.log_artifact(str(self.csv_path))
            self.mlflow.end_run()
            self.mlflow = None
