"""Tables for the terminal and for Markdown files: one formatter (:func:`format_table`) that every
table drivelab prints goes through (``drivelab eval``, ``drivelab reward compare``, ``drivelab
sweep``), and the evaluation tables built on it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

# The driving metrics of an evaluation summary (drivelab.training.collection.evaluation.EvalResult.summary),
# as (key, column label, row label); rates and route completion print as percentages.
DRIVING_METRICS = (("success_rate", "success", "success rate"), ("crash_rate", "crash", "crash rate"),
                   ("out_of_road_rate", "off road", "out-of-road rate"), ("timeout_rate", "timeout", "timeout rate"),
                   ("route_completion", "route", "route completion"))
# The cost of an env that reports one (drivelab.envs.costs), as (key, column label, row label, format):
# the mean episode cost, and the cost per step of all episodes together (Safety Gym's CostRate).
COST_METRICS = (("cost", "cost", "episode cost", "{:.2f}"), ("cost_rate", "cost/step", "cost rate", "{:.4f}"))


def evaluation_columns(rows: list[dict[str, Any]]) -> list[tuple[str, str, str]]:
    """The metric columns of an evaluation table, as (key, label, format): the driving metrics
    (as percentages) and the cost metrics right after success, each only when some row has it."""
    rates = [(key, label, "{:.1%}") for key, label, _ in DRIVING_METRICS]
    costs = [(key, label, fmt) for key, label, _, fmt in COST_METRICS]
    return [column for column in rates[:1] + costs + rates[1:] if any(column[0] in row for row in rows)]


def format_table(header: Sequence[str] | None, rows: Sequence[Sequence[Any]], *, align: str | None = None,
                 markdown: bool = False, indent: str = "") -> str:
    """Rows of cells as aligned text: every column as wide as its widest cell, two spaces between
    columns, each column aligned as ``align`` says (one letter a column, ``l`` left or ``r``
    right; default: the first column left, the others right, for a name and its numbers).
    ``markdown`` writes a Markdown table instead (pipes, and a separator row under the header),
    aligned the same so that it reads in a terminal too. ``header`` None: no header line."""
    lines = [[str(cell) for cell in row] for row in ([header] if header is not None else []) + list(rows)]
    widths = [max(len(line[i]) for line in lines if i < len(line)) for i in range(max(map(len, lines), default=0))]
    align = align or "l" + "r" * (len(widths) - 1)

    def cells(line: list[str]) -> list[str]:
        return [cell.ljust(widths[i]) if align[i] == "l" else cell.rjust(widths[i]) for i, cell in enumerate(line)]

    if markdown:
        out = ["| " + " | ".join(cells(line)) + " |" for line in lines]
        if header is not None:
            out.insert(1, "|" + "|".join("-" * (width + 2) if align[i] == "l" else "-" * (width + 1) + ":"
                                         for i, width in enumerate(widths)) + "|")
        return "\n".join(out)
    return "\n".join(indent + "  ".join(cells(line)).rstrip() for line in lines)


def format_evaluations(rows: list[dict[str, Any]], episodes: int, seed: int, sampled: bool = False) -> str:
    """One line per evaluated policy (a checkpoint's row from ``drivelab eval``, or a baseline's):
    return (mean ± standard deviation over the episodes) and the driving and cost metrics that the
    env reports (:func:`evaluation_columns`), under a line that says the protocol."""
    columns = evaluation_columns(rows)
    envs = sorted({row["env"] for row in rows})
    title = (f"{episodes} episodes each on {', '.join(envs)} (episode k: seed {seed}+k), "
             f"{'sampled actions' if sampled else 'deterministic'}")
    body = [[row.get("policy") or f"{row['checkpoint']} (step {row['step']})",
             f"{row['return_mean']:.1f} ± {row['return_std']:.1f}",
             *(fmt.format(row[key]) if key in row else "-" for key, _, fmt in columns)] for row in rows]
    return title + "\n" + format_table(["policy", "return (mean ± std)", *(label for _, label, _ in columns)], body)


# multi-agent scenes (drivelab.training.collection.scene_evaluation): key, label, format
SCENE_METRICS = (("agent_episodes", "cars' episodes", "{:.0f}"), ("live_agents", "cars on the road (mean)", "{:.1f}"),
                 ("crashes_per_episode", "crashes per scene episode", "{:.2f}"),
                 ("efficiency", "efficiency ((arrived - failed) / 1000 steps)", "{:.2f}"))


def format_evaluation(summary: dict[str, Any], env_id: str, what: str) -> str:
    """One evaluation, a metric a line: return, episode length, the driving metrics the env
    reports, its cost (episode cost, cost rate and the cost terms), the mean |CTE| and the reward terms."""
    rows = [["return (mean ± std)", f"{summary['return_mean']:.2f} ± {summary['return_std']:.2f}"],
            ["episode length", f"{summary['length_mean']:.1f}"]]
    rows += [[label, f"{100 * summary[key]:.1f} %"] for key, _, label in DRIVING_METRICS if key in summary]
    rows += [[label, fmt.format(summary[key])] for key, _, label, fmt in COST_METRICS if key in summary]
    rows += [[key, f"{value:.2f}"] for key, value in summary.items() if key.startswith("cost/")]
    if "mean_abs_cte" in summary:
        rows.append(["mean |CTE|", f"{summary['mean_abs_cte']:.3f} m"])
    rows += [[key, f"{value:.2f}"] for key, value in summary.items() if key.startswith("reward/")]
    rows += [[label, fmt.format(summary[key])] for key, label, fmt in SCENE_METRICS if key in summary]
    return f"evaluation of {what} on {env_id}: {summary['episodes']} episodes\n" + format_table(None, rows, indent="  ")
