"""Files and paths (issue 79): config files that say nothing or say a key twice, checkpoints that
do not belong to their run, runs that lost their checkpoints, output paths that cannot be
written, and model cards that vouch for their driver. Each is bad input: one line on stderr,
naming the file or field, and exit code 2."""

import json
import os
import shutil
from pathlib import Path

import pytest
import yaml

import drivelab
from drivelab.api import build_config, train
from drivelab.cli import main
from drivelab.config import SHIPPED_CONFIGS, read_yaml, save_config
from drivelab.errors import DrivelabError
from drivelab.tools import drivers
from drivelab.tools.drivers import CARD, DRIVERS_DIR, SUMS, read_card, resolve_policy_path, write_driver
from drivelab.training.outputs.checkpoint import list_checkpoints

DRIVER = "drivelab-driver"


def _refused(args: list[str], capsys) -> str:
    """Run the CLI in this process; it must exit with code 2 and one line: that line."""
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert exit_info.value.code == 2 and len(lines) == 1, (args, err)
    assert lines[0].startswith("drivelab: error:") and "Traceback" not in err, err
    return lines[0]


def _train(run_dir: Path, algo: str, steps: int = 256, **fields) -> Path:
    """A tiny CartPole run with a checkpoint at its end."""
    params = {"ppo": {"num_steps": 128}, "a2c": {"num_steps": 8}}.get(algo, {})
    train(build_config({"algo": algo, "steps": steps, "seed": 0, "run_dir": str(run_dir),
                        "env": {"id": "CartPole-v1", "num_envs": 2}, algo: params, **fields}), progress=False)
    return run_dir


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A PPO run and an A2C run, trained once for the tests that need a checkpoint."""
    root = tmp_path_factory.mktemp("runs")
    return {"ppo": _train(root / "ppo", "ppo"), "a2c": _train(root / "a2c", "a2c", steps=64)}


# ---- 1. config files ------------------------------------------------------------------------

@pytest.mark.parametrize("text", ["", "\n", "# a comment, no fields\n", "---\n"])
def test_an_empty_config_file_is_refused_naming_it(text, tmp_path, capsys):
    config = tmp_path / "empty.yaml"
    config.write_text(text)
    line = _refused(["train", "--config", config, "--steps", "1", "--run-dir", tmp_path / "run", "--no-progress"], capsys)
    assert str(config) in line and "is empty" in line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("text, key, line_no", [
    ("algo: ppo\nsteps: 1000\nalgo: a2c\n", "algo", 3),
    ("algo: ppo\nppo:\n  lr: 0.1\n  gamma: 0.9\n  lr: 0.001\n", "lr", 5),
    ("algo: ppo\nenv: {id: CartPole-v1, num_envs: 2, id: Pendulum-v1}\n", "id", 2),
])
def test_a_key_written_twice_is_refused_naming_key_and_file(text, key, line_no, tmp_path, capsys):
    config = tmp_path / "twice.yaml"
    config.write_text(text)
    line = _refused(["train", "--config", config, "--steps", "1", "--run-dir", tmp_path / "run", "--no-progress"], capsys)
    assert str(config) in line and f"key '{key}' appears twice" in line and f"line {line_no}" in line
    assert not (tmp_path / "run").exists()


def test_shipped_and_saved_configs_still_load(tmp_path):
    files = sorted(SHIPPED_CONFIGS.glob("*.yaml")) + sorted((SHIPPED_CONFIGS / "rewards").glob("*.yaml"))
    assert len(files) > 20
    for path in files:
        assert isinstance(read_yaml(path), dict), path
    cfg = build_config({"algo": "sac", "env": {"id": "Pendulum-v1"}})
    save_config(cfg, tmp_path / "config.yaml")  # what every run directory holds
    assert build_config(read_yaml(tmp_path / "config.yaml")) == cfg
    # a YAML merge key overrides the keys it merges: that is no duplicate
    (tmp_path / "merge.yaml").write_text("base: &base {lr: 0.1, gamma: 0.9}\nppo:\n  <<: *base\n  lr: 0.01\n")
    assert read_yaml(tmp_path / "merge.yaml")["ppo"] == {"lr": 0.01, "gamma": 0.9}


# ---- 2. a checkpoint that does not belong to its run --------------------------------------------

def test_a_checkpoint_of_another_run_is_refused_on_eval_export_and_resume(runs, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(runs["ppo"], run)
    foreign = list_checkpoints(runs["a2c"])[-1]
    copied = run / "checkpoints" / "step_000000999999"   # the newest: what eval, export and resume take
    shutil.copytree(foreign, copied)
    for target in (run, copied):
        line = _refused(["eval", target, "--episodes", "1"], capsys)
        assert str(copied) in line and "does not match" in line and "algo" in line, line
        line = _refused(["export", target, "--format", "torchscript", "--out", tmp_path / "x"], capsys)
        assert str(copied) in line and "does not match" in line
    assert not (tmp_path / "x").exists()
    line = _refused(["train", "--resume", run, "--steps", "2000000", "--no-progress"], capsys)
    assert "does not match" in line and str(copied) in line
    # the run's own checkpoints, and the copy on its own, still load
    shutil.rmtree(copied)
    assert drivelab.load(run).config.algo == "ppo"
    assert drivelab.load(list_checkpoints(run)[0]).config.algo == "ppo"
    assert drivelab.load(foreign).config.algo == "a2c"


# ---- 3. a run whose checkpoints were deleted ---------------------------------------------------

def test_resume_of_a_run_without_its_checkpoints_is_refused(runs, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(runs["ppo"], run)
    for checkpoint in list_checkpoints(run):
        shutil.rmtree(checkpoint)
    line = _refused(["train", "--resume", run, "--steps", "1024", "--no-progress"], capsys)
    assert "has no checkpoint in checkpoints/" in line and str(run) in line
    shutil.rmtree(run / "checkpoints")
    line = _refused(["train", "--resume", run, "--steps", "1024", "--no-progress"], capsys)
    assert "has no checkpoints/" in line and "deleted" in line
    assert not (run / "checkpoints").exists()  # nothing was started


@pytest.mark.parametrize("left_behind", [None, "", "step,ti", "step,time,name,value\n0,17.5,charts/l"])
def test_a_run_that_logged_nothing_after_step_0_still_starts_afresh(left_behind, tmp_path):
    """Killed before its first checkpoint: no checkpoints/ and no logged step after 0 (the case of
    test_robustness.py::test_a_run_killed_before_its_first_checkpoint_starts_afresh): nothing to
    resume, no error."""
    from drivelab.api import _checkpoint_to_resume

    run = tmp_path / "run"
    run.mkdir()
    if left_behind is not None:
        (run / "metrics.csv").write_text(left_behind)
    cfg = build_config({"algo": "ppo", "steps": 256, "seed": 0, "run_dir": str(run), "env": {"id": "CartPole-v1"}})
    assert _checkpoint_to_resume(cfg) is None


# ---- 4. output paths ----------------------------------------------------------------------------

@pytest.fixture
def afile(tmp_path) -> Path:
    path = tmp_path / "afile"
    path.write_text("a file, not a directory")
    return path


def test_video_paths_that_cannot_be_written_are_one_line(afile, tmp_path, capsys, monkeypatch):
    base = ["eval", "--policy", "random", "--env", "CartPole-v1", "--episodes", "1"]
    assert "is a file" in _refused([*base, "--video", afile / "x.mp4"], capsys)
    assert "is not a directory" in _refused([*base, "--video-dir", afile], capsys)
    assert "is a file" in _refused([*base, "--video-dir", afile / "videos"], capsys)
    assert "is a directory" in _refused([*base, "--video", tmp_path], capsys)
    for name in ("x.avi", "x.mp4.txt", "x"):
        line = _refused([*base, "--video", tmp_path / name], capsys)
        assert str(tmp_path / name) in line and ".mp4 or .gif" in line
    _unwritable(tmp_path / "locked", monkeypatch)
    assert "not writable" in _refused([*base, "--video", tmp_path / "locked" / "x.gif"], capsys)
    assert not list(tmp_path.rglob("x*"))


def test_export_paths_that_cannot_be_written_are_one_line(runs, afile, tmp_path, capsys, monkeypatch):
    base = ["export", runs["ppo"], "--format", "torchscript", "--out"]
    line = _refused([*base, afile / "x.onnx"], capsys)
    assert "export --out" in line and f"{afile} is a file" in line
    assert "exists and is not a directory" in _refused([*base, afile], capsys)
    _unwritable(tmp_path / "locked", monkeypatch)
    assert "not writable" in _refused([*base, tmp_path / "locked" / "out"], capsys)
    with pytest.raises(SystemExit) as exit_info:   # and a good path still exports
        main([str(a) for a in [*base, tmp_path / "fine" / "out"]])
    assert exit_info.value.code == 0
    assert (tmp_path / "fine" / "out" / "policy.pt").is_file()


def _unwritable(directory: Path, monkeypatch) -> None:
    """``directory`` exists and refuses writes (tests may run as root, whom chmod does not stop:
    os.access is told so instead)."""
    directory.mkdir()
    directory.chmod(0o555)
    real = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if Path(path) == directory else real(path, mode, **kw))


# ---- 5. the model card ----------------------------------------------------------------------------

@pytest.fixture
def copy(tmp_path) -> Path:
    """A copy of the shipped driver, to damage."""
    return shutil.copytree(DRIVERS_DIR / DRIVER, tmp_path / DRIVER)


def test_the_shipped_driver_is_whole():
    sums = drivers.read_sums(DRIVERS_DIR / DRIVER)
    assert set(sums) == {"tensors.safetensors", "state.json", CARD}
    assert resolve_policy_path(DRIVER) == DRIVERS_DIR / DRIVER


def test_a_forged_card_is_refused(copy, capsys):
    card = json.loads((copy / CARD).read_text())
    card["evaluation"]["policies"][DRIVER]["success_rate"]["mean"] = 0.99
    (copy / CARD).write_text(json.dumps(card, indent=1) + "\n")
    line = _refused(["eval", copy, "--card"], capsys)
    assert "card.json does not match the sha256" in line and "0.990" not in line
    with pytest.raises(DrivelabError, match="card.json does not match the sha256"):
        drivelab.load(copy)


def test_a_driver_without_its_card_or_sums_is_refused(copy, capsys, monkeypatch):
    (copy / CARD).unlink()
    line = _refused(["eval", copy, "--episodes", "1"], capsys)
    assert "card.json" in line and "missing" in line
    (copy / SUMS).unlink()   # neither: a shipped driver is refused, a plain saved policy loads as before
    monkeypatch.setattr(drivers, "DRIVERS_DIR", copy.parent.resolve())
    with pytest.raises(DrivelabError, match=f"shipped driver {DRIVER} has no model card"):
        resolve_policy_path(DRIVER)
    monkeypatch.undo()
    assert drivelab.load(copy).config.algo == "td3"


def test_a_card_without_sums_is_refused(copy):
    (copy / SUMS).unlink()
    with pytest.raises(DrivelabError, match=f"no {SUMS}"):
        drivelab.load(copy)


def test_write_driver_writes_the_sums_of_every_file(copy, tmp_path):
    card = {k: v for k, v in read_card(copy).items() if k != "files"}
    out = write_driver(tmp_path / "new", copy, card)
    assert (out / SUMS).read_text() == (DRIVERS_DIR / DRIVER / SUMS).read_text()  # the shipped format, unchanged
    assert resolve_policy_path(out) == out
    assert yaml.safe_load((out / "state.json").read_text())["config"]["algo"] == "td3"
