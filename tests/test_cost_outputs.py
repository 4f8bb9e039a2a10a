"""The cost wherever a user reads results: evaluation summaries, ``drivelab eval`` tables and
--json, the best checkpoint under ``eval.cost_limit``, the training logs, plots, reports and model
cards; and for envs without a cost, all of these as they were."""

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import drivelab
from drivelab.envs import EnvConfig
from drivelab.errors import DrivelabError
from drivelab.tools.drivers import CARD_METRICS, card_metrics, format_card
from drivelab.tools.report import _table
from drivelab.tools.tables import format_evaluation, format_evaluations
from drivelab.training.collection.evaluation import EvalResult, new_best, play
from drivelab.training.outputs.episodes import EpisodeTracker
from drivelab.training.outputs.plots import default_panels, read_metrics
from drivelab.training.run.metrics import RunMetrics

THREE_LANES = "constrained_env:ThreeLanes-v0"  # tests/constrained_env.py: the middle lane costs 0.25 a step


def _result(costs=None) -> EvalResult:
    """Three fake episodes of lengths 4, 6 and 10, with a cost per episode when ``costs`` is given."""
    result = EvalResult.empty(3)
    for k, (ret, length) in enumerate([(1.0, 4), (2.0, 6), (3.0, 10)]):
        metrics = {"success_rate": float(k > 0)}
        if costs is not None:
            metrics["cost"] = costs[k]
        result.add(k, ret, length, metrics)
    return result


def _row(result: EvalResult, name: str) -> dict:
    return {**result.summary(), "env": "E-v0", "policy": name}


def test_summary_adds_the_cost_rate_as_total_cost_over_total_steps():
    summary = _result([1.0, 0.0, 5.0]).summary()
    assert summary["cost"] == pytest.approx(2.0)            # the mean episode cost
    assert summary["cost_rate"] == pytest.approx(6.0 / 20)  # not the mean of per-episode rates (0.1833)
    assert "cost" not in _result().summary() and "cost_rate" not in _result().summary()


def test_eval_table_shows_cost_beside_success_only_when_some_row_has_it():
    plain = format_evaluations([_row(_result(), "a"), _row(_result(), "b")], 3, 0)
    # an env without a cost: the table of before, header and cells
    assert plain.splitlines()[1].split() == ["policy", "return", "(mean", "±", "std)", "success"]
    assert plain.splitlines()[2].split() == ["a", "2.0", "±", "0.8", "66.7%"]
    table = format_evaluations([_row(_result([1.0, 0.0, 5.0]), "safe"), _row(_result(), "plain")], 3, 0)
    header, safe, other = table.splitlines()[1:]
    assert "return (mean ± std)" in header
    assert header.split()[-3:] == ["success", "cost", "cost/step"]
    assert safe.split()[-3:] == ["66.7%", "2.00", "0.3000"]
    assert other.split()[-3:] == ["66.7%", "-", "-"]  # a row without cost: a dash, cells not shifted
    single = format_evaluation({**_result([1.0, 0.0, 5.0]).summary(), "cost/crash": 0.5}, "E-v0", "x")
    assert re.search(r"episode cost +2\.00", single) and re.search(r"cost rate +0\.3000", single)
    assert re.search(r"cost/crash +0\.50", single)
    assert "cost" not in format_evaluation(_result().summary(), "E-v0", "x")


class MiddleLane(torch.nn.Module):
    """Always the middle lane of ThreeLanes (action 0): reward 2 and cost 0.25 a step."""

    def act(self, obs, deterministic=True):
        return torch.zeros(len(obs), 1)

    def to_env(self, action):
        return action.numpy()


def test_a_real_evaluation_measures_the_cost_of_the_lane_it_drives():
    result = play(EnvConfig(id=THREE_LANES, num_envs=2), MiddleLane(), episodes=3)
    summary = result.summary()
    assert summary["return_mean"] == 8.0 and summary["cost"] == 1.0 and summary["cost_rate"] == 0.25
    np.testing.assert_array_equal(result.metrics["cost"], [1.0, 1.0, 1.0])


def test_new_best_prefers_feasible_evaluations_under_a_cost_limit():
    def summary(success, cost, ret=0.0):
        return {"success_rate": success, "cost": cost, "return_mean": ret}

    # without a limit: as before, the metric then the return, the cost ignored
    assert new_best(summary(0.9, 5.0, 1.0), "success_rate", None) == [0.9, 1.0]
    assert new_best(summary(0.8, 0.0), "success_rate", [0.9, 1.0]) is None
    best = new_best(summary(0.9, 5.0), "success_rate", None, cost_limit=1.0)   # infeasible, but the first
    assert best is not None and best[0] == 0.0
    best = new_best(summary(0.2, 1.0), "success_rate", best, cost_limit=1.0)   # feasible (<=) beats it
    assert best == [1.0, 0.2, -1.0, 0.0]
    assert new_best(summary(0.95, 3.0), "success_rate", best, cost_limit=1.0) is None  # more success, too costly
    assert new_best(summary(0.2, 1.0), "success_rate", best, cost_limit=1.0) is None   # a tie is no new best
    assert new_best(summary(0.2, 0.5), "success_rate", best, cost_limit=1.0) == [1.0, 0.2, -0.5, 0.0]
    assert new_best(summary(0.3, 0.9), "success_rate", best, cost_limit=1.0) == [1.0, 0.3, -0.9, 0.0]
    # the limit set on --resume: the first evaluation under the new rule replaces the old best
    assert new_best(summary(0.1, 0.0), "success_rate", [0.9, 1.0], cost_limit=1.0) is not None
    # an env without a cost is feasible under any limit
    assert new_best({"return_mean": 3.0}, "return_mean", None, cost_limit=0.0) == [1.0, 3.0, -0.0, 3.0]


def test_periodic_evaluation_passes_its_cost_limit_to_the_best_checkpoint(tmp_path):
    from drivelab.config import TrainConfig
    from drivelab.training.run.periodic_evaluation import RunEvaluation

    cfg = TrainConfig(algo="ppo", env=EnvConfig(id=THREE_LANES))
    cfg.eval.cost_limit, cfg.eval.best_metric = 1.0, "success_rate"
    kept = []

    def keep():
        kept.append(len(kept))
        (tmp_path / str(len(kept))).mkdir()
        return tmp_path / str(len(kept))

    evaluation = RunEvaluation(cfg, tmp_path, SimpleNamespace(log=lambda step, metrics: None), torch.device("cpu"),
                               save=None, on_restart=None)
    for step, (success, cost) in enumerate([(0.5, 2.0), (0.3, 0.5), (1.0, 4.0), (0.4, 1.0)]):
        evaluation._finish(step, {"success_rate": success, "cost": cost, "return_mean": 0.0}, None, keep=keep)
    assert len(kept) == 3 and json.loads((tmp_path / "3" / "eval.json").read_text())["step"] == 3


@pytest.mark.parametrize("limit", [-0.5, float("nan"), float("inf")])
def test_cost_limit_must_be_a_finite_number_at_least_zero(tmp_path, limit):
    with pytest.raises(DrivelabError, match=r"^config field 'eval.cost_limit' must be a finite number >= 0$"):
        drivelab.train("ppo", THREE_LANES, steps=256, run_dir=tmp_path / "r", progress=False,
                       eval={"cost_limit": limit})
    assert not (tmp_path / "r").exists()


def test_training_logs_the_cumulative_cost_only_for_envs_with_a_cost():
    tracker = EpisodeTracker(1)
    assert RunMetrics.cost_totals(SimpleNamespace(episodes=tracker), 100) == {}
    tracker.cost_total, tracker.cost_episodes = 0.0, 3  # three episodes that cost nothing are still logged
    assert RunMetrics.cost_totals(SimpleNamespace(episodes=tracker), 100) == {
        "charts/cumulative_cost": 0.0, "charts/cost_rate": 0.0}


@pytest.fixture(scope="module")
def three_lanes_run(tmp_path_factory):
    """A short PPO run on ThreeLanes (seconds), evaluated twice with a cost limit."""
    run_dir = tmp_path_factory.mktemp("runs") / "lanes"
    drivelab.train("ppo", THREE_LANES, steps=1024, seed=0, num_envs=2, run_dir=run_dir, progress=False,
                   log_every=256, ppo={"num_steps": 128},
                   eval={"every": 512, "episodes": 2, "cost_limit": 1.0, "video": False})
    return run_dir


def test_metrics_csv_holds_the_cumulative_cost_of_a_ppo_run(three_lanes_run):
    metrics = read_metrics(three_lanes_run)
    steps, _, total = metrics["charts/cumulative_cost"]
    _, _, rate = metrics["charts/cost_rate"]
    assert len(steps) >= 3 and np.all(np.diff(total) >= 0) and total[-1] > 0
    np.testing.assert_allclose(rate, total / steps, rtol=1e-5)
    # the sum of every finished episode's cost: the tracker's, saved in the last checkpoint
    state = json.loads(sorted((three_lanes_run / "checkpoints").glob("step_*"))[-1].joinpath("state.json").read_text())
    assert total[-1] == pytest.approx(state["episodes"]["cost_total"], rel=1e-5)
    assert {"episode/cost", "eval/cost", "eval/cost_rate"} <= set(metrics)
    assert {"episode cost", "evaluation cost"} <= set(default_panels([metrics]))
    assert "Lagrange multiplier" not in default_panels([metrics])  # PPO logs no multiplier
    plain = default_panels([{"episode/return": None, "eval/return_mean": None}])
    assert list(plain) == ["episode return", "evaluation return"]


def test_eval_json_and_table_of_a_run_show_its_cost(three_lanes_run, run_cli):
    out = run_cli("eval", three_lanes_run, "--episodes", "2", "--policy", "random", "--json", "--no-progress")
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout.strip().splitlines()[-1])
    for row in rows:
        assert row["cost_rate"] == pytest.approx(row["cost"] / row["length_mean"])
    out = run_cli("eval", three_lanes_run, "--episodes", "2", "--policy", "random", "--no-progress")
    assert out.returncode == 0, out.stderr
    header = next(line for line in out.stdout.splitlines() if line.startswith("policy"))
    assert header.split()[-4:] == ["success", "cost", "cost/step", "route"]
    policy = drivelab.load(three_lanes_run)
    assert set(drivelab.evaluate(policy, episodes=2)) >= {"cost", "cost_rate", "success_rate", "env", "step"}


def _card(policies: dict) -> dict:
    return {"name": "d", "summary": "s", "training": {"steps": 1, "steps_trained": 1}, "observation": "o",
            "observation_shape": [3], "evaluation": {"protocol": "p", "policies": policies}}


def _card_rows(text: str) -> list[list[str]]:
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith("policy"))
    return [re.split(r" {2,}", line.strip()) for line in lines[start:]]


def test_card_shows_the_cost_with_its_ci_and_a_dash_where_a_policy_lacks_it():
    per_episode = {"success_rate": [1, 0, 1, 1], "crash_rate": [0, 1, 0, 0], "out_of_road_rate": [0, 0, 0, 0],
                   "route_completion": [1, 0.5, 1, 1], "cost": [0.0, 3.0, 1.0, 0.0]}
    mine = card_metrics(per_episode)
    assert set(mine) == {*CARD_METRICS, "cost"} and mine["cost"]["mean"] == 1.0 and mine["cost"]["ci95"] > 0
    expert = card_metrics({k: v for k, v in per_episode.items() if k != "cost"})
    rows = _card_rows(format_card(_card({"safe": mine, "metadrive-expert": expert})))
    assert rows[0][:6] == ["policy", *CARD_METRICS, "cost"]
    assert rows[1][0] == "safe" and rows[1][5] == "1.000 ± " + f"{mine['cost']['ci95']:.3f}"
    assert rows[2][0] == "metadrive-expert" and rows[2][5] == "-" and len(rows[2]) == 6
    # with the episodes' lengths the cost rate too: 4 cost over 300 steps, its CI by the delta method
    # (by hand: cost - rate x length = -4/3, 7/3, -1/3, -2/3; sample std 1.6102, t(0.975, 3) = 3.1824,
    # over sqrt(4) and the mean length 75)
    rated = card_metrics({**per_episode, "length": [100, 50, 100, 50]})
    assert rated["cost_rate"]["mean"] == pytest.approx(4 / 300, abs=1e-6)
    assert rated["cost_rate"]["ci95"] == pytest.approx(3.1824 * 1.6102 / 2 / 75, rel=1e-3)
    rows = _card_rows(format_card(_card({"safe": rated, "metadrive-expert": expert})))
    assert rows[0][5:7] == ["cost", "cost_rate"] and rows[1][6] == "0.0133 ± " + f"{rated['cost_rate']['ci95']:.4f}"
    assert rows[2][6] == "-"
    # a card without cost: no cost column, every cell under its own header
    rows = _card_rows(format_card(_card({"old": expert, "metadrive-expert": expert})))
    assert rows[0][:5] == ["policy", *CARD_METRICS] and "cost" not in rows[0]
    assert all(len(row) == 5 for row in rows[1:])
    # a policy missing a metric keeps the cells after it in place
    partial = {k: v for k, v in expert.items() if k != "crash_rate"}
    rows = _card_rows(format_card(_card({"a": expert, "b": partial})))
    assert rows[2][2] == "-" and rows[2][4] == rows[1][4]


def test_report_table_puts_cost_after_success_when_present():
    with_cost = _table([("safe", _result([1.0, 0.0, 5.0]).summary()), ("plain", _result().summary())])
    heads = re.findall(r"<th>([^<]*)</th>", with_cost)
    assert heads[heads.index("success") + 1:heads.index("success") + 3] == ["cost", "cost/step"]
    cells = re.findall(r'<td class="num">([^<]*)</td>', with_cost)
    assert cells[:5] == ["2.00 ± 0.8", "6.67", "66.7%", "2.00", "0.3000"]
    assert cells[5:10] == ["2.00 ± 0.8", "6.67", "66.7%", "–", "–"]
    plain = _table([("plain", _result().summary())])
    assert re.findall(r"<th>([^<]*)</th>", plain) == ["policy", "return", "length", "success"]
