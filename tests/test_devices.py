"""Device discipline without a GPU: every algorithm's update runs with its networks and batch on
PyTorch's ``meta`` device, where any tensor created on the CPU beside them (a stats vector, an
action scale, a constant) fails with "tensors on different devices", as it would on CUDA."""

import platform
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn

from drivelab.algos import a2c, ddpg, grpo, ppo, sac, td3
from drivelab.algos.grpo import GroupBatch
from drivelab.training.learning.replay_buffer import ReplayBatch
from drivelab.training.learning.policy_nets import ActorCritic
from drivelab.training.learning.offpolicy_nets import OffPolicyAgent, make_target
from drivelab.training.learning.optim import make_optimizers
from drivelab.training.learning.rollout_buffers import RolloutBatch
from drivelab.training.run.timing import machine
from drivelab.training.learning.precision import native_bf16

META = torch.device("meta")
OBS, ACT, B = gym.spaces.Box(-1, 1, (6,)), gym.spaces.Box(-2, 2, (2,)), 16


def _on_meta(*shapes) -> list[torch.Tensor]:
    return [torch.zeros(shape, device=META) for shape in shapes]


# REINFORCE is left out: its advantage weights are computed in numpy on purpose (the returns go
# to the host once per batch and back), which a meta tensor cannot do.
@pytest.mark.parametrize("algo", ["ppo", "a2c", "grpo"])
def test_on_policy_updates_keep_to_the_networks_device(algo):
    agent = ActorCritic(OBS, ACT, [8]).to(META)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3)
    obs, actions, b = _on_meta((B, 6), (B, 2), (B,))
    if algo in ("ppo", "a2c"):
        module = ppo if algo == "ppo" else a2c
        hp = module.Params(num_minibatches=2, update_epochs=1, target_kl=None) if algo == "ppo" else module.Params()
        logged = module.update(agent, optimizer, RolloutBatch(obs, actions, b, b.clone(), b.clone(), b.clone()), hp)
    else:
        logged = grpo.update(agent, optimizer, GroupBatch(obs, actions, b, b.clone()), grpo.Params(num_minibatches=2))
    for name, value in logged.items():
        assert not isinstance(value, torch.Tensor) or value.device == META, name


@pytest.mark.parametrize("algo", ["ddpg", "td3", "sac"])
def test_off_policy_updates_and_actions_keep_to_the_networks_device(algo):
    agent = OffPolicyAgent(OBS, ACT, [8], "relu", stochastic=algo == "sac", critics=1 if algo == "ddpg" else 2).to(META)
    target = make_target(agent)
    obs, actions, rewards, next_obs, terminated, discount = _on_meta((B, 6), (B, 2), (B,), (B, 6), (B,), (B,))
    batch = ReplayBatch(obs, actions, rewards, next_obs, terminated, discount)
    if algo == "sac":
        hp = sac.Params()
        log_alpha = nn.Parameter(torch.zeros((), device=META))
        opt = sac.Optimizers(**make_optimizers(agent, hp)._asdict(), alpha=torch.optim.Adam([log_alpha]))
        logged = sac.update(agent, target, log_alpha, opt, batch, hp, -2.0, update_actor=True)
    elif algo == "td3":
        hp = td3.Params()
        logged = td3.update(agent, target, make_optimizers(agent, hp), batch, hp, update_actor=True)
    else:
        hp = ddpg.Params()
        logged = ddpg.update(agent, target, make_optimizers(agent, hp), batch, hp)
    for name, value in logged.items():
        assert not isinstance(value, torch.Tensor) or value.device == META, name
    # an action computed as numpy in the trainer, mapped to the env's bounds by the agent
    with pytest.raises(NotImplementedError):  # meta tensors have no data: it got that far on the agent's device
        agent.to_env(torch.zeros(3, 2))


def test_a_checkpoint_from_a_gpu_run_loads_evaluates_exports_and_resumes_on_the_cpu(tmp_path, capsys):
    """A GPU run's files differ from a CPU run's only in the device its config names (safetensors
    store no device): such a run, made here by rewriting a CPU run's device, must evaluate, export
    and load on a CPU-only machine, and resume there when asked to with --device cpu."""
    import json

    import yaml

    import drivelab
    from drivelab.cli import main
    from drivelab.training.outputs.checkpoint import checkpoint_step, resolve_checkpoint

    run = tmp_path / "gpu_run"
    drivelab.train("ppo", "CartPole-v1", steps=256, seed=0, run_dir=run, progress=False, ppo={"num_steps": 128})
    config = yaml.safe_load((run / "config.yaml").read_text())
    (run / "config.yaml").write_text(yaml.safe_dump({**config, "device": "cuda:0"}, sort_keys=False))
    for state_file in run.glob("checkpoints/*/state.json"):
        state = json.loads(state_file.read_text())
        state["config"]["device"] = "cuda:0"
        state_file.write_text(json.dumps(state))

    def cli(*argv: str) -> int:
        with pytest.raises(SystemExit) as exit_:
            main(list(argv))
        return exit_.value.code or 0

    assert drivelab.load(run).predict(np.zeros(4, np.float32))[0].shape == ()
    assert cli("eval", str(run), "--episodes", "2", "--json") == 0
    assert cli("export", str(run), "--format", "torchscript", "--out", str(tmp_path / "x")) == 0
    capsys.readouterr()
    if not torch.cuda.is_available():
        assert cli("train", "--resume", str(run), "--steps", "2048", "--no-progress") == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--device cpu" in err
    assert cli("train", "--resume", str(run), "--steps", "2048", "--device", "cpu", "--no-progress") == 0
    assert checkpoint_step(resolve_checkpoint(run)) == 2048


def test_native_bf16_follows_the_cpu_flags_and_is_unknown_elsewhere():
    # bf16_updates warns where native_bf16 is False (Run): on x86 it must mean what Linux's CPU
    # flags say, AVX512-BF16 or AMX tiles; torch has no answer for the meta device.
    assert native_bf16(META) is None
    cpuinfo = Path("/proc/cpuinfo")
    if platform.machine() not in ("x86_64", "AMD64") or not cpuinfo.is_file():
        pytest.skip("CPU flags are read from Linux's /proc/cpuinfo on x86")
    flags = set(cpuinfo.read_text().split())
    assert native_bf16(torch.device("cpu")) == bool(flags & {"avx512_bf16", "amx_tile"})
    assert machine()["bf16_in_hardware"] == native_bf16(torch.device("cpu")) and machine()["cpu"]
