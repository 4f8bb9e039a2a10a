"""Checkpoints written by drivelab 0.3 (before the package was laid out in layers) still load,
evaluate to the same numbers, and export. The two checkpoints under tests/data/checkpoints_v0.3
were written by commit 8b1a122 (the small PPO/CartPole and SAC/Pendulum cases of
test_architecture.py); the expected numbers are what that commit's `drivelab eval` printed."""

import json
from pathlib import Path

import pytest

from drivelab.cli import main

DATA = Path(__file__).parent / "data" / "checkpoints_v0.3"

# `drivelab eval CKPT --episodes 3 --num-envs 1 --json` at commit 8b1a122
EXPECTED = {
    "ppo_cartpole": {"episodes": 3, "return_mean": 58.0, "return_std": 9.797958971132712, "length_mean": 58.0},
    "sac_pendulum": {"episodes": 3, "return_mean": -1598.0369838832091, "return_std": 62.322124923377565,
                     "length_mean": 200.0},
}


def _cli_json(capsys, *argv: str) -> dict:
    with pytest.raises(SystemExit) as exit_:
        main(list(argv))
    assert exit_.value.code == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_a_v0_3_checkpoint_evaluates_as_it_did(name, capsys):
    row = _cli_json(capsys, "eval", str(DATA / name), "--episodes", "3", "--num-envs", "1", "--json")
    # rel 1e-6, not exact: the same weights give the same actions up to the float32 rounding of the
    # CPU's matmul kernels, which differs between CPUs (by ~1e-9 relative in the mean return); a
    # checkpoint read wrongly is off by far more
    assert {key: row[key] for key in EXPECTED[name]} == pytest.approx(EXPECTED[name], rel=1e-6)


def test_a_v0_3_checkpoint_exports(tmp_path):
    with pytest.raises(SystemExit) as exit_:
        main(["export", str(DATA / "ppo_cartpole"), "--format", "torchscript", "--out", str(tmp_path)])
    assert exit_.value.code == 0 and (tmp_path / "policy.pt").is_file() and (tmp_path / "policy.json").is_file()


def test_a_removed_option_left_on_is_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--algo", "ppo", "--env", "CartPole-v1", "--ppo.overlap_update", "true", "--run-dir", str(tmp_path / "r")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "'ppo.overlap_update' was removed" in err
    assert not (tmp_path / "r").exists()
