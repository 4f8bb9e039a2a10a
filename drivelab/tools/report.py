"""``drivelab report RUN [RUN ...]``: one self-contained HTML file per report (no network needed
to open it: images and the video are embedded as data URIs, the style is inline).

What a student hands in and a researcher links: what was trained (algorithm, env, key
hyperparameters, the full config folded away), the training curves, an evaluation table of the
latest and best checkpoints beside reference policies on the same episodes, a video of the
agent, the checkpoints and the wall time. Several runs are compared side by side.
"""

from __future__ import annotations

import base64
import html
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml
from tqdm.auto import tqdm

from drivelab.tools.baselines import BASELINES
from drivelab.tools.policies import baseline_env, evaluate_baseline, evaluate_checkpoint
from drivelab.training.outputs.checkpoint import checkpoint_step, list_checkpoints, resolve_checkpoint
from drivelab.training.outputs.plots import plot_runs, read_metrics
from drivelab.training.outputs.tracking import default_mlflow_uri
from drivelab.training.outputs.video import Recorder
from drivelab.version import __version__

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; } td, th { padding: 4px 10px; border-bottom: 1px solid #ddd; }
th { text-align: left; background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
img, video { max-width: 100%; } pre { background: #f6f6f6; padding: 1em; overflow-x: auto; }
h1 { margin-bottom: 0.2em; } .muted { color: #777; } section { margin-bottom: 3em; }
"""
# The evaluation table's columns, as (summary key, label, format), each shown when some row has it:
# rates as percentages, and for an env with a cost its mean episode cost and cost per step.
COLUMNS = [("return_mean", "return", "{:.2f}"), ("length_mean", "length", "{:.2f}"),
           ("success_rate", "success", "{:.1%}"), ("cost", "cost", "{:.2f}"), ("cost_rate", "cost/step", "{:.4f}"),
           ("crash_rate", "crash", "{:.1%}"), ("out_of_road_rate", "out of road", "{:.1%}"),
           ("timeout_rate", "timeout", "{:.1%}"),
           ("route_completion", "route completion", "{:.1%}"), ("mean_abs_cte", "mean |CTE| (m)", "{:.2f}")]


def _data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(path.read_bytes()).decode()}"


def _table(rows: list[tuple[str, dict[str, float]]]) -> str:
    columns = [c for c in COLUMNS if any(c[0] in row for _, row in rows)]
    head = "".join(f"<th>{label}</th>" for _, label, _ in columns)
    body = ""
    for name, row in rows:
        cells = ""
        for key, _, fmt in columns:
            value = row.get(key)
            text = "–" if value is None else fmt.format(value)
            if key == "return_mean" and value is not None:
                text += f" ± {row['return_std']:.1f}"
            cells += f'<td class="num">{text}</td>'
        body += f"<tr><td>{html.escape(name)}</td>{cells}</tr>"
    return f"<table><tr><th>policy</th>{head}</tr>{body}</table>"


class ReportProgress:
    """The report's progress bar (stderr): one job per policy evaluated and per video filmed,
    the current one named, as each takes seconds to minutes. A run adds its jobs when it knows
    them (its baselines follow its env); ``progress=False`` shows nothing."""

    def __init__(self, progress: bool = True):
        self.bar = tqdm(total=0, desc="report", unit="job", dynamic_ncols=True, disable=not progress)

    def expect(self, jobs: int) -> None:
        self.bar.total += jobs
        self.bar.refresh()

    def start(self, what: str) -> None:
        self.bar.set_postfix_str(what)  # shown now: the job about to take the time

    def finish(self) -> None:
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def evaluate_for_report(run: Path, episodes: int, baselines: bool, video: bool,
                        progress: ReportProgress | None = None) -> dict[str, Any]:
    """Evaluate the run's latest and best checkpoints and the baselines on the same episodes; film
    the best policy if the run has no video yet. ``progress`` counts each evaluation and the video."""
    if progress is None:
        progress = ReportProgress(progress=False)
    rows, env_cfg = [], None
    targets = [("latest", run)] + ([("best", run / "checkpoints" / "best")] if (run / "checkpoints" / "best").is_dir() else [])
    videos = sorted((run / "videos").glob("*.mp4")) if (run / "videos").is_dir() else []
    film = video and not videos
    progress.expect(len(targets) + int(film))
    for label, path in targets:
        progress.start(f"{run.name}: {label} checkpoint")
        result, env_cfg, ckpt = evaluate_checkpoint(path, episodes)
        rows.append((f"{label} checkpoint (step {checkpoint_step(ckpt)})", result.summary()))
        progress.finish()
    if baselines and env_cfg is not None:
        base = baseline_env(env_cfg, num_envs=env_cfg.num_envs)
        names = BASELINES if env_cfg.id.startswith(("MetaDrive", "SafeMetaDrive")) else ("random",)
        # lane-keeping is a crude controller: the expert and random bracket the range
        names = [name for name in names if name != "lane-keeping"]
        progress.expect(len(names))
        for name in names:
            progress.start(f"{run.name}: {name} baseline")
            rows.append((f"{name} baseline", evaluate_baseline(name, base, episodes).summary()))
            progress.finish()
    if film:
        progress.start(f"{run.name}: video")
        recorder = Recorder(run / "videos" / "report.mp4", max_episodes=1)
        evaluate_checkpoint(targets[-1][1], 1, recorder=recorder)
        videos = recorder.paths
        progress.finish()
    return {"rows": rows, "video": videos[-1] if videos else None}


def _run_section(run: Path, evaluation: dict[str, Any], curves: Path) -> str:
    config = yaml.safe_load((run / "config.yaml").read_text())
    algo, env = config.get("algo"), config.get("env", {})
    metrics = read_metrics(run)
    wall = max((float(t[-1]) for _, t, _ in metrics.values() if len(t)), default=0.0)
    steps = max((int(s[-1]) for s, _, _ in metrics.values() if len(s)), default=0)
    params = config.get(algo, {})
    key_params = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(json.dumps(v))}</td></tr>"
                         for k, v in params.items())
    checkpoints = list_checkpoints(run) + ([run / "checkpoints" / "best"] if (run / "checkpoints" / "best").is_dir() else [])
    ckpt_rows = "".join(
        f"<tr><td>{p.name}</td><td class='num'>{checkpoint_step(p)}</td>"
        f"<td class='num'>{sum(f.stat().st_size for f in p.iterdir()) / 2**20:.1f} MiB</td></tr>" for p in checkpoints)
    video = evaluation["video"]
    video_html = (f'<video controls muted src="{_data_uri(video, "video/mp4")}"></video>'
                  f'<p class="muted">{html.escape(video.name)}</p>') if video else "<p class='muted'>no video</p>"
    extra = ""
    if (run / "generalization.png").is_file():
        extra = (f"<h3>Generalisation (benchmarks/metadrive_generalization.py)</h3>"
                 f'<img alt="generalization" src="{_data_uri(run / "generalization.png", "image/png")}">')
    return f"""<section>
<h2>{html.escape(run.name)}: {html.escape(str(algo))} on {html.escape(str(env.get('id')))}</h2>
<p>{steps:,} env steps in {wall / 60:.1f} minutes of logged training ({steps / max(wall, 1e-9):.0f} steps/s),
{env.get('num_envs')} envs, seed {config.get('seed')}.</p>
<h3>Evaluation</h3>
<p class="muted">deterministic, the same episodes for every policy (episode k: seed k)</p>
{_table(evaluation['rows'])}
<h3>Training curves</h3>
<img alt="training curves" src="{_data_uri(curves, 'image/png')}">
<h3>The agent</h3>
{video_html}
{extra}
<h3>Hyperparameters ({html.escape(str(algo))})</h3>
<table>{key_params}</table>
<details><summary>full config</summary><pre>{html.escape(yaml.safe_dump(config, sort_keys=False))}</pre></details>
<h3>Checkpoints</h3>
<table><tr><th>checkpoint</th><th>step</th><th>size</th></tr>{ckpt_rows}</table>
</section>"""


def write_report(runs: list[str | Path], out: str | Path | None = None, episodes: int = 10, baselines: bool = True,
                 video: bool = True, progress: bool = True) -> Path:
    """Write the report of ``runs`` (default file: ``RUN/report.html`` for one run); ``progress``:
    a progress bar on stderr (:class:`ReportProgress`)."""
    runs = [Path(r) for r in runs]
    for run in runs:
        resolve_checkpoint(run)  # a one-line error for anything that is not a run with a checkpoint
    out = Path(out) if out else runs[0] / "report.html" if len(runs) == 1 else Path("report.html")
    bar = ReportProgress(progress)
    with tempfile.TemporaryDirectory() as tmp:
        sections, summary_rows = [], []
        try:
            for i, run in enumerate(runs):
                evaluation = evaluate_for_report(run, episodes, baselines, video, bar)
                sections.append(_run_section(run, evaluation, plot_runs([run], Path(tmp) / f"curves_{i}.png")))
                summary_rows.append((f"{run.name}: {evaluation['rows'][0][0]}", evaluation["rows"][0][1]))
        finally:
            bar.close()
        comparison = ""
        if len(runs) > 1:
            together = plot_runs(runs, Path(tmp) / "together.png")
            comparison = (f"<section><h2>Side by side</h2>{_table(summary_rows)}"
                          f'<img alt="curves of all runs" src="{_data_uri(together, "image/png")}"></section>')
        title = "drivelab report: " + ", ".join(run.name for run in runs)
        page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
                f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
                f"<p class='muted'>drivelab {__version__}, {time.strftime('%Y-%m-%d %H:%M')}</p>"
                f"{comparison}{''.join(sections)}</body></html>")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(page)
    for run in runs:
        _attach_to_mlflow(run, out)
    return out


def _attach_to_mlflow(run: Path, report: Path) -> None:
    """A run tracked with MLflow gets its report as an artifact of its MLflow run."""
    config = yaml.safe_load((run / "config.yaml").read_text())
    track = config.get("track") or {}
    if not track.get("mlflow") or not (run / "mlflow_run_id").is_file():
        return
    import mlflow

    client = mlflow.MlflowClient(tracking_uri=track.get("mlflow_uri") or default_mlflow_uri(run.parent))
    client.log_artifact((run / "mlflow_run_id").read_text().strip(), str(report))
