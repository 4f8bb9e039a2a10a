"""The trained driver that ships with drivelab (drivelab/drivers/drivelab-driver) and its model card."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import drivelab
from drivelab.api import evaluate_checkpoint
from drivelab.errors import DrivelabError
from drivelab.tools.drivers import CARD_METRICS, DRIVERS_DIR, read_card, shipped_drivers
from processes import run_drivelab

ROOT = Path(__file__).resolve().parent.parent
NAME = "drivelab-driver"


def _card() -> dict:
    return read_card(DRIVERS_DIR / NAME)


def test_the_driver_ships_with_a_complete_card():
    assert NAME in shipped_drivers()
    card = _card()
    assert set(card["files"]) == {"tensors.safetensors", "state.json"}
    assert sum((DRIVERS_DIR / NAME / f).stat().st_size for f in card["files"]) < 2_000_000  # a small MLP
    for key in ("algo", "config", "seed", "steps", "minutes", "drivelab_commit", "metadrive_version", "reproduce"):
        assert card["training"][key] not in (None, ""), key
    evaluation = card["evaluation"]
    assert evaluation["episodes"] == 200 and "start seeds 0-199" in evaluation["protocol"]
    for who in (NAME, "metadrive-expert"):
        assert set(evaluation["policies"][who]) == set(CARD_METRICS)
    per_episode = evaluation["per_episode"]["success_rate"]
    assert len(per_episode) == 200
    assert np.mean(per_episode) == pytest.approx(evaluation["policies"][NAME]["success_rate"]["mean"], abs=1e-4)


def test_the_driver_loads_by_name_and_acts():
    policy = drivelab.load(NAME)
    obs = np.zeros(policy.observation_space.shape, np.float32)
    action, state = policy.predict(obs)
    assert action.shape == (2,) and state is None and np.all(np.abs(action) <= 1.0)


def test_a_changed_file_is_refused(tmp_path):
    copy = shutil.copytree(DRIVERS_DIR / NAME, tmp_path / "driver")
    data = bytearray((copy / "tensors.safetensors").read_bytes())
    data[-1] ^= 0xFF
    (copy / "tensors.safetensors").write_bytes(bytes(data))
    with pytest.raises(DrivelabError, match="tensors.safetensors does not match the sha256"):
        drivelab.load(copy)


def test_another_observation_layout_is_refused():
    with pytest.raises(DrivelabError, match="trained on observations of shape"):
        evaluate_checkpoint(NAME, episodes=1, env_id="MetaDrive-validation-v0",
                            env_kwargs={"vehicle_config": {"lidar": {"num_lasers": 120}}})


def test_models_and_card_commands():
    listing = run_drivelab("models")
    assert listing.returncode == 0 and NAME in listing.stdout, listing.stderr
    card = run_drivelab("eval", NAME, "--card")
    assert card.returncode == 0 and "metadrive-expert" in card.stdout and "reproduce" in card.stdout


# The card's per-episode numbers are those of the shipped weights: the first scenarios of the
# protocol, replayed. The outcome is the same; route completion moves by a few tenths of a
# percent with the engine's history (the card's episodes shared 2 engines, here one plays them).
def test_the_card_matches_the_shipped_weights_on_its_first_scenarios():
    result, _, _ = evaluate_checkpoint(NAME, episodes=3, env_id="MetaDrive-validation-v0", num_envs=1)
    per_episode = _card()["evaluation"]["per_episode"]
    np.testing.assert_array_equal(result.metrics["success_rate"], per_episode["success_rate"][:3])
    np.testing.assert_allclose(result.metrics["route_completion"], per_episode["route_completion"][:3], atol=0.01)


def test_export_by_name_drives_without_drivelab(tmp_path):
    exported = run_drivelab("export", NAME, "--format", "onnx", "--out", tmp_path / "x")
    assert exported.returncode == 0, exported.stderr
    meta = json.loads((tmp_path / "x" / "policy.json").read_text())
    assert meta["file"] == "policy.onnx"
    out = subprocess.run([sys.executable, str(ROOT / "examples" / "onnx_drive.py"), str(tmp_path / "x"), "--episodes", "1"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
