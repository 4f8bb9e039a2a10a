from pathlib import Path

import pytest

from drivelab.cli import parse_overrides, parse_value
from drivelab.api import build_config
from drivelab.config import TrainConfig, config_to_dict, read_yaml, save_config
from drivelab.errors import DrivelabError
from drivelab.tools.sweep import plan, trial_config


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
    ({"algo": "ppo", "update_threads": 2, "ppo": {"overlap_update": True}}, "update_threads"),
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
    for trial in plan(sweep["grid"], sweep["seeds"]):     # every run the sweep would start
        cfg = build_config(trial_config(raw, trial, Path("unused")))
        assert cfg.seed == trial.seed
