import json

import pytest
import torch

from drivelab.training.outputs.checkpoint import (list_checkpoints, load_checkpoint, resolve_checkpoint, restore,
                                                  save_checkpoint)
from drivelab.errors import DrivelabError


def _model_and_optimizer(seed):
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 2))
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    loss = model(torch.randn(5, 3)).pow(2).sum()
    loss.backward()
    optimizer.step()
    return model, optimizer


def test_round_trip_weights_optimizer_and_rng(tmp_path):
    model, optimizer = _model_and_optimizer(0)
    torch.manual_seed(123)
    path = save_checkpoint(tmp_path, 10, modules={"policy": model}, optimizers={"policy": optimizer},
                           state={"custom": [1, 2]})
    expected_draw = torch.rand(3)
    other, other_opt = _model_and_optimizer(1)
    ckpt = load_checkpoint(tmp_path)
    assert ckpt.path == path and ckpt.step == 10 and ckpt.state["custom"] == [1, 2]
    restore(ckpt, {"policy": other}, {"policy": other_opt})
    for a, b in zip(model.state_dict().values(), other.state_dict().values()):
        assert torch.equal(a, b)
    saved, loaded = optimizer.state_dict(), other_opt.state_dict()
    assert saved["param_groups"] == loaded["param_groups"]
    for i in saved["state"]:
        for key in saved["state"][i]:
            assert torch.equal(torch.as_tensor(saved["state"][i][key]), torch.as_tensor(loaded["state"][i][key]))
    assert torch.equal(torch.rand(3), expected_draw)  # the torch RNG stream continues
    assert json.loads((path / "state.json").read_text())["step"] == 10
    assert not any(p.name.startswith(".tmp") for p in (tmp_path / "checkpoints").iterdir())


def test_pruning_keeps_initial_and_latest(tmp_path):
    model, _ = _model_and_optimizer(0)
    for step in (0, 1, 2, 3, 4):
        save_checkpoint(tmp_path, step, modules={"m": model}, keep=2)
    assert [p.name[-2:] for p in list_checkpoints(tmp_path)] == ["00", "03", "04"]
    assert resolve_checkpoint(tmp_path).name.endswith("04")


def test_missing_or_mismatched_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(DrivelabError, match="not found"):
        resolve_checkpoint(tmp_path / "missing")
    with pytest.raises(DrivelabError, match="no checkpoint"):
        resolve_checkpoint(tmp_path)
    model, _ = _model_and_optimizer(0)
    save_checkpoint(tmp_path, 0, modules={"policy": model})
    with pytest.raises(DrivelabError, match="does not fit"):
        restore(load_checkpoint(tmp_path), {"policy": torch.nn.Linear(7, 7)})
