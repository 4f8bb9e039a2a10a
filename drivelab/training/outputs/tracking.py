"""Metrics tracking: TensorBoard and CSV always, MLflow and Weights & Biases when asked.

``metrics.csv`` is tidy (one row per value: ``step,time,name,value``), so a run's metrics load
with ``pandas.read_csv(...).pivot_table(index="step", columns="name", values="value")``.
On resume, rows and TensorBoard events written after the checkpoint are dropped first, so a
killed and resumed run has one clean history.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shlex
import shutil
import sys
import time
import uuid
from collections.abc import Mapping
from pathlib import Path

from drivelab.config import TrackConfig, config_to_dict
from drivelab.errors import DrivelabError
from drivelab.training.outputs.checkpoint import list_checkpoints
from drivelab.training.outputs.plots import plot_runs
from drivelab.version import __version__


def default_mlflow_uri(runs_root: Path) -> str:
    """The project's MLflow store: ``sqlite:///<runs root>/mlflow.db``."""
    return f"sqlite:///{(Path(runs_root) / 'mlflow.db').resolve()}"


def git_commit() -> str | None:
    """The commit of the code being run, when it runs from a git checkout."""
    import subprocess

    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True,
                             timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def fetch_mlflow_run(reference: str, tracking_uri: str | None, into: Path) -> Path:
    """``mlflow:RUN_ID`` -> a local run directory with the run's config, metrics and latest
    checkpoint (and best, if logged), downloaded from its artifacts (a local store or a server)."""
    try:
        import mlflow
    except ImportError:
        raise DrivelabError("mlflow: references need mlflow: pip install 'drivelab[mlflow]'") from None
    run_id = reference.split(":", 1)[1]
    client = mlflow.MlflowClient(tracking_uri=tracking_uri or os.environ.get("MLFLOW_TRACKING_URI")
                                 or default_mlflow_uri(Path("runs")))
    try:
        client.get_run(run_id)
    except Exception as exc:  # noqa: BLE001 - MLflow raises several types for a bad id or store
        raise DrivelabError(f"MLflow run {run_id} not found at {client.tracking_uri}: {str(exc).splitlines()[0]}") from None
    into.mkdir(parents=True, exist_ok=True)
    names = {a.path for a in client.list_artifacts(run_id)}
    for name in ("config.yaml", "metrics.csv"):
        if name in names:
            client.download_artifacts(run_id, name, str(into))
    if "checkpoints" not in names:
        raise DrivelabError(f"MLflow run {run_id} has no checkpoint artifacts (was it trained with --mlflow?)")
    client.download_artifacts(run_id, "checkpoints", str(into))
    latest = into / "checkpoints" / "latest"
    step = json.loads((latest / "state.json").read_text())["step"]
    target = into / "checkpoints" / f"step_{step:012d}"   # a run directory's layout
    shutil.rmtree(target, ignore_errors=True)            # fetched before: the download is the truth
    os.replace(latest, target)
    (into / "mlflow_run_id").write_text(run_id)
    return into


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
        resuming = resume_step is not None and self.csv_path.exists()
        if resuming:
            self._truncate_csv(resume_step)
        # A fresh run starts a fresh file: one may be there from a run killed before its first
        # checkpoint (empty, or a torn header), which is started afresh.
        self._csv_file = open(self.csv_path, "a" if resuming else "w", newline="")
        self._csv = csv.writer(self._csv_file)
        if not resuming:
            self._csv.writerow(["step", "time", "name", "value"])
        # purge what was logged after the checkpoint (the checkpoint's own step stays, as in the CSV)
        self.tb = SummaryWriter(str(self.run_dir / "tb"), purge_step=None if resume_step is None else resume_step + 1)
        self.mlflow = self.wandb = None
        if cfg.track.mlflow:
            self._start_mlflow(cfg.track, config_to_dict(cfg))
        if cfg.track.wandb:
            self._start_wandb(cfg.track, config_to_dict(cfg))

    def _truncate_csv(self, step: int) -> None:
        """Keep the header and the rows up to ``step``; a run killed mid-write may have left an
        empty file or a torn last line, which are dropped."""
        with open(self.csv_path, newline="") as f:
            rows = list(csv.reader(f))
        kept = [["step", "time", "name", "value"]] + [r for r in rows[1:] if len(r) == 4 and r[0].isdigit() and int(r[0]) <= step]
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
        # One store for the runs of a project: beside the run directories (`mlflow ui --backend-store-uri
        # sqlite:///runs/mlflow.db` compares them all), unless a tracking URI (a server) is given.
        uri = track.mlflow_uri or default_mlflow_uri(self.run_dir.parent)
        mlflow.set_tracking_uri(uri)
        if mlflow.get_experiment_by_name(track.experiment) is None:
            artifacts = (self.run_dir.parent / "mlartifacts").resolve().as_uri() if track.mlflow_uri is None else None
            mlflow.create_experiment(track.experiment, artifact_location=artifacts)
        mlflow.set_experiment(track.experiment)
        id_file = self.run_dir / "mlflow_run_id"
        run_id = id_file.read_text().strip() if id_file.exists() else None
        run = mlflow.start_run(run_id=run_id, run_name=None if run_id else self.run_dir.name)
        if run_id is None:
            id_file.write_text(run.info.run_id)
            # MLflow params are short strings; long lists are cut by MLflow's limit (6000 chars).
            mlflow.log_params({k: str(v)[:500] for k, v in _flatten(params).items()})
            mlflow.set_tags({"algo": params["algo"], "env": params["env"]["id"], "drivelab_version": __version__,
                             **({"git_commit": commit} if (commit := git_commit()) else {})})
            mlflow.log_artifact(str(self.run_dir / "config.yaml"))
        self.mlflow = mlflow

    def _start_wandb(self, track: TrackConfig, params: dict) -> None:
        """A W&B run in ``RUN/wandb``, whose id is kept in ``RUN/wandb_run_id`` so that a resumed
        run continues it (W&B ignores the steps it has already seen: the history between the
        checkpoint and the kill stays as first logged, unlike the CSV and TensorBoard)."""
        try:
            import wandb
        except ImportError:
            raise DrivelabError("track.wandb is on but wandb is not installed: pip install 'drivelab[wandb]'") from None
        mode = track.wandb_mode or os.environ.get("WANDB_MODE")
        if mode is None and not wandb.login(prompt=False, verify=False):
            mode = "offline"  # no key: never stop a run to ask for one
            print(f"drivelab: W&B has no API key here (wandb login), so it logs offline to {self.run_dir / 'wandb'}; "
                  f"upload later with: wandb sync {shlex.quote(str(self.run_dir / 'wandb'))}/offline-run-*",
                  file=sys.stderr)  # the directory shell-quoted, the glob left for the shell
        id_file = self.run_dir / "wandb_run_id"
        run_id = id_file.read_text().strip() if id_file.exists() else uuid.uuid4().hex[:8]
        id_file.write_text(run_id)
        tags = [params["algo"], str(params["env"]["id"])]
        self.wandb = wandb.init(project=track.wandb_project, entity=track.wandb_entity, name=self.run_dir.name,
                                id=run_id, resume="allow", dir=str(self.run_dir), mode=mode, config=params, tags=tags,
                                settings=wandb.Settings(silent=True, console="off"))
        self.wandb.config.update({"drivelab_version": __version__, "git_commit": git_commit()}, allow_val_change=True)

    def log(self, step: int, metrics: Mapping[str, float]) -> None:
        now = time.time()
        clean = {k: float(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}
        for name, value in clean.items():
            self.tb.add_scalar(name, value, step)
            self._csv.writerow([step, f"{now:.3f}", name, f"{value:.6g}"])
        self._csv_file.flush()
        if self.mlflow is not None:
            self.mlflow.log_metrics(clean, step=step)
        if self.wandb is not None:
            self.wandb.log(clean, step=step)

    def log_video(self, step: int, path: Path, strip=None) -> None:
        """A video file of the run: a strip of its frames in TensorBoard, the file in MLflow."""
        if strip is not None:
            self.tb.add_image("eval/video_frames", strip, step, dataformats="HWC")
            self.tb.flush()
        if self.mlflow is not None:
            self.mlflow.log_artifact(str(path), "videos")
        if self.wandb is not None:
            self.wandb.save(str(path), base_path=str(self.run_dir), policy="now")

    def close(self) -> None:
        self.tb.close()
        self._csv_file.close()
        if self.mlflow is not None:
            self._upload_run_files()
            self.mlflow.end_run()
            self.mlflow = None
        if self.wandb is not None:
            self.wandb.finish()
            self.wandb = None

    def _upload_run_files(self) -> None:
        """metrics.csv, the curves, and the latest and best checkpoints (``drivelab eval
        mlflow:RUN_ID`` and ``train --resume mlflow:RUN_ID`` fetch them from there)."""
        self.mlflow.log_artifact(str(self.csv_path))
        self.mlflow.log_artifact(str(self.run_dir / "config.yaml"))
        checkpoints = list_checkpoints(self.run_dir)
        if checkpoints:
            self.mlflow.log_artifacts(str(checkpoints[-1]), "checkpoints/latest")
        if (self.run_dir / "checkpoints" / "best").is_dir():
            self.mlflow.log_artifacts(str(self.run_dir / "checkpoints" / "best"), "checkpoints/best")
        try:
            self.mlflow.log_artifact(str(plot_runs([self.run_dir], self.run_dir / "curves.png")))
        except DrivelabError:  # nothing logged yet
            pass
