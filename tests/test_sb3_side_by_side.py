"""benchmarks/sb3_side_by_side.py: Stable-Baselines3 is a benchmark's tool, not a dependency, and
the settings it gets are the closest to drivelab's recipe (pinned here; SB3 need not be installed)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from drivelab.api import build_config
from drivelab.config import read_yaml

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def side_by_side(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))   # the script imports its neighbours by name
    import sb3_side_by_side

    yield sb3_side_by_side
    sys.modules.pop("sb3_side_by_side", None)


def test_stable_baselines3_is_not_a_dependency_of_drivelab_or_its_tests():
    for path in ("pyproject.toml", "Makefile", ".ci/run"):
        assert "stable-baselines3" not in (ROOT / path).read_text() and "stable_baselines3" not in (ROOT / path).read_text()


def test_sb3_gets_the_drive_recipes_settings_and_what_it_cannot_match_is_listed(side_by_side, tmp_path):
    cfg = build_config({**read_yaml(ROOT / "configs" / "drive.yaml"), "run_dir": str(tmp_path)})
    hp = cfg.algo_params.__dict__

    def sb3_init(self, policy, env, learning_rate, n_steps=1):  # what SB3 2.7's SAC takes, in part
        pass

    kwargs, unmatched = side_by_side.sb3_settings("sac", hp, cfg.env.num_envs, sb3_init)
    assert kwargs["gradient_steps"] == 1          # utd 0.5 x 2 envs: one gradient step per step of both envs
    assert kwargs["n_steps"] == 3 and kwargs["ent_coef"] == "auto_0.05" and kwargs["batch_size"] == 256
    assert kwargs["learning_starts"] == 10_000 and kwargs["policy_kwargs"] == {"net_arch": [128, 128]}
    assert any("LayerNorm" in u for u in unmatched) and any("actor_every 2" in u for u in unmatched)
    assert any("env workers acting" in u for u in unmatched)
    _, unmatched = side_by_side.sb3_settings("sac", hp, 2, lambda self, policy, env: None)
    assert any("n_step 3" in u for u in unmatched)   # an SB3 without n-step returns says so
