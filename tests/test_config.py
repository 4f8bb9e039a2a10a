import copy
from pathlib import Path

import pytest

from drivelab import api
from drivelab.cli import build_parser, cmd_train, parse_overrides, parse_value
from drivelab.api import build_config
from drivelab.config import TrainConfig, config_to_dict, merge_overrides, read_yaml, save_config
from drivelab.errors import DrivelabError
from drivelab.tools.sweep import Trial, plan, trial_config


def test_defaults_and_algo_section():
    cfg = build_config({"algo": "reinforce", "reinforce": {"lr": 1, "hidden": [32]}})
    assert isinstance(cfg, TrainConfig)
    assert cfg.algo_params.lr == 1.0 and isinstance(cfg.algo_params.lr, float)
    assert cfg.algo_params.hidden == [32]


def test_round_trip_through_yaml(tmp_path):
    cfg = build_config({"env": {"id": "MetaDrive-10env-v0", "action_grid": "3x3", "kwargs": {"traffic_density": 0.2}},
                        "steps": 123})
    save_config(cfg, tmp_path / "c.yaml")
    again = build_config(read_yaml(tmp_path / "c.yaml"))
    assert config_to_dict(again) == config_to_dict(cfg)


@pytest.mark.parametrize("data, fragment", [
    ({"stepz": 1}, "stepz"),
    ({"env": {"idd": "x"}}, "idd"),
    ({"reinforce": {"lrr": 0.1}}, "lrr"),
    ({"steps": "many"}, "steps"),
    ({"reinforce": {"gamma": "high"}}, "gamma"),
    ({"algo": "reinfroce"}, "reinfroce"),
    ({"env": {"action_grid": "3by3"}}, "action_grid"),
    ({"reinforce": {"advantage": "gae"}}, "advantage"),
    ({"env": {"num_envs": 0}}, "num_envs"),
    ({"env": {"num_envs": 2, "step_groups": 3}}, "step_groups"),
    ({"env": {"id": "CartPole-v1", "num_envs": 2, "step_groups": 2}}, "step_groups"),   # sync envs: no groups
    ({"algo": "ppo", "ppo": {"log_std_init": -1.0, "log_std_final": 0.0}}, "log_std_final"),
    ({"update_threads": 0}, "update_threads"),
])
def test_bad_fields_name_the_field(data, fragment):
    with pytest.raises(DrivelabError) as err:
        build_config(data)
    assert fragment in str(err.value)
    assert "\n" not in str(err.value)


def test_missing_and_invalid_yaml(tmp_path):
    with pytest.raises(DrivelabError, match="not found"):
        read_yaml(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("steps: [1,\n")
    with pytest.raises(DrivelabError, match="bad.yaml"):
        read_yaml(bad)


def test_cli_overrides_are_typed():
    assert parse_overrides(["--reinforce.lr", "1e-3", "--env.action_grid=3x3", "--env.kwargs.num_scenarios", "10",
                            "--reinforce.hidden", "[32, 32]", "--track.mlflow_uri", "null"]) == {
        "reinforce.lr": 1e-3, "env.action_grid": "3x3", "env.kwargs.num_scenarios": 10,
        "reinforce.hidden": [32, 32], "track.mlflow_uri": None}
    assert parse_value("true") is True
    with pytest.raises(DrivelabError, match="needs a value"):
        parse_overrides(["--reinforce.lr"])


def test_overrides_merge_deeply_whether_nested_or_dotted():
    data = {"env": {"id": "CartPole-v1", "kwargs": {"a": 0, "b": 2}}, "ppo": {"hidden": [64, 64]}}
    section = {"kwargs": {"a": 1}}
    nested = merge_overrides(copy.deepcopy(data), {"env": section, "ppo": {"hidden": [32]}})
    dotted = merge_overrides(copy.deepcopy(data), {"env.kwargs.a": 1, "ppo.hidden": [32]})
    assert nested == dotted == {"env": {"id": "CartPole-v1", "kwargs": {"a": 1, "b": 2}}, "ppo": {"hidden": [32]}}
    nested["env"]["kwargs"]["c"] = 3
    assert section == {"kwargs": {"a": 1}}, "the config shares no mapping with the caller's"
    assert merge_overrides({"env": {"reward": None}}, {"env.reward": {"cte": {}}}) == {"env": {"reward": {"cte": {}}}}
    with pytest.raises(DrivelabError, match="'steps' is not a section"):
        merge_overrides({"steps": 10}, {"steps.x": 1})


class _Stop(Exception):
    """Raised instead of starting the run: the test only wants the config it would train with."""


def _config_trained_with(monkeypatch, start):
    seen = []

    def no_run(cfg, **kwargs):
        seen.append(cfg)
        raise _Stop

    monkeypatch.setattr(api, "Run", no_run)
    with pytest.raises(_Stop):
        start()
    return seen[0]


def test_a_section_keyword_and_a_dotted_flag_override_the_config_file_alike(tmp_path, monkeypatch):
    """drivelab.train(env={"kwargs": {...}}) keeps the config file's other env kwargs, as --env.kwargs.KEY does."""
    config = tmp_path / "c.yaml"
    config.write_text("algo: ppo\nenv: {id: CartPole-v1, num_envs: 2, kwargs: {max_episode_steps: 50}}\n")
    python = _config_trained_with(monkeypatch, lambda: api.train(
        config=config, env={"kwargs": {"sutton_barto_reward": True}}, ppo={"lr": 1e-3}, run_dir=tmp_path / "run"))
    args, unknown = build_parser().parse_known_args(
        ["train", "--config", str(config), "--env.kwargs.sutton_barto_reward", "true", "--ppo.lr", "1e-3",
         "--run-dir", str(tmp_path / "run")])
    cli = _config_trained_with(monkeypatch, lambda: cmd_train(args, parse_overrides(unknown)))
    assert python.env.kwargs == {"max_episode_steps": 50, "sutton_barto_reward": True}
    assert config_to_dict(python) == config_to_dict(cli)


def test_resuming_reads_the_saved_config_and_lets_only_the_resumable_fields_change(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    save_config(build_config({"algo": "reinforce", "steps": 1000, "seed": 3, "run_dir": "elsewhere"}), run / "config.yaml")
    cfg = api.train_config({"steps": 5000, "eval": {"every": 100}, "seed": 3, "algo": "reinforce"}, resume=run)
    assert (cfg.steps, cfg.eval.every, cfg.seed, cfg.run_dir) == (5000, 100, 3, str(run))
    with pytest.raises(DrivelabError, match="'seed' cannot change"):
        api.train_config({"seed": 4}, resume=run)
    with pytest.raises(DrivelabError, match="'reinforce.lr' cannot change"):
        api.train_config({"reinforce": {"lr": 1.0}}, resume=run)
    with pytest.raises(DrivelabError, match="do not pass --config"):
        api.train_config({}, "ppo_cartpole", resume=run)
    with pytest.raises(DrivelabError, match="no config.yaml"):
        api.train(run_dir=tmp_path / "missing", resume=True, steps=10)


SHIPPED = sorted((Path(__file__).resolve().parent.parent / "drivelab" / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_config_builds(path):
    """A recipe a user copies must at least parse and validate (a typo in a field fails here)."""
    raw = read_yaml(path)
    sweep = raw.pop("sweep", None)
    if sweep is None:
        cfg = build_config(raw)
        assert cfg.algo == raw["algo"] and cfg.steps > 0
        return
    if "search" in sweep:                                 # a search: its space, and the config at a corner of it
        from drivelab.tools.sweep import load_search

        base, search, seed = load_search(path)
        corner = {key: spec[1] if spec[0] != "int" else int(spec[1]) for key, spec in search.space.items()}
        assert build_config(trial_config(base, Trial(corner, seed), Path("unused"))).steps > 0
        return
    for trial in plan(sweep["grid"], sweep["seeds"]):     # every run the sweep would start
        cfg = build_config(trial_config(raw, trial, Path("unused")))
        assert cfg.seed == trial.seed
