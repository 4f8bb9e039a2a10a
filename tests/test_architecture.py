"""The shape of the code: no import cycles, each algorithm's loop deterministic and resumable."""

import ast
import csv
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from drivelab.algos import ALGORITHMS
from drivelab.api import build_config, train
from drivelab.checkpoint import list_checkpoints, resolve_checkpoint

PACKAGE = Path(__file__).resolve().parent.parent / "drivelab"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_level_imports(path: Path, modules: set[str]) -> set[str]:
    """drivelab modules that ``path`` imports at module level (not inside functions, nor under
    ``if TYPE_CHECKING``)."""
    found = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # `from drivelab.algos import ppo` imports the submodule drivelab.algos.ppo
            names = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in modules else node.module
                     for alias in node.names]
        else:
            continue
        found.update(name for name in names if name in modules)
    return found


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph[v]:
                out.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle_among_drivelab_modules():
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {name: _module_level_imports(path, set(files)) - {name} for name, path in files.items()}
    assert len(graph) > 30 and graph["drivelab.api"] >= {"drivelab.algos", "drivelab.run"}
    assert _cycles(graph) == []
    # the registry is handed down: nothing below the algorithms imports it
    importers = sorted(name for name, deps in graph.items() if "drivelab.algos" in deps)
    assert importers == ["drivelab.api", "drivelab.cli"], importers


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


# Small budgets on CartPole (on-policy) and Pendulum (off-policy); eval on for two of them, so
# periodic evaluation is shown not to disturb the training streams.
CASES = {
    "reinforce": {"env": {"id": "CartPole-v1", "num_envs": 4}, "steps": 2500, "reinforce": {"batch_steps": 1000}},
    "a2c": {"env": {"id": "CartPole-v1", "num_envs": 4}, "steps": 2500},
    "ppo": {"env": {"id": "CartPole-v1", "num_envs": 4}, "steps": 2500, "ppo": {"num_steps": 128},
            "eval": {"every": 1000, "episodes": 2}},
    "grpo": {"env": {"id": "CartPole-v1", "num_envs": 4}, "steps": 2500, "grpo": {"group_size": 2, "batch_steps": 1000}},
    "ddpg": {"env": {"id": "Pendulum-v1", "num_envs": 1}, "steps": 1200, "ddpg": {"learning_starts": 400, "hidden": [32, 32], "batch_size": 32}},
    "td3": {"env": {"id": "Pendulum-v1", "num_envs": 2}, "steps": 1200, "td3": {"learning_starts": 400, "hidden": [32, 32], "batch_size": 32}},
    "sac": {"env": {"id": "Pendulum-v1", "num_envs": 1}, "steps": 1200, "sac": {"learning_starts": 400, "hidden": [32, 32], "batch_size": 32},
            "eval": {"every": 600, "episodes": 1}},
}


def _metrics(run_dir: Path) -> list[tuple[str, str, str]]:
    with open(run_dir / "metrics.csv") as f:
        return [(r["step"], r["name"], r["value"]) for r in csv.DictReader(f) if not r["name"].startswith("perf/")]


def test_every_algorithm_is_listed():
    assert set(CASES) == set(ALGORITHMS)


@pytest.mark.parametrize("algo", sorted(CASES))
def test_same_seed_same_metrics(algo, tmp_path):
    for name in ("a", "b"):
        train(build_config({"algo": algo, "seed": 0, "run_dir": str(tmp_path / name), **CASES[algo]}), progress=False)
    first, second = _metrics(tmp_path / "a"), _metrics(tmp_path / "b")
    names = {name for _, name, _ in first}
    assert "episode/return" in names and any(n.startswith("loss/") for n in names), names
    assert first == second
    if "eval" in CASES[algo]:
        assert "eval/return_mean" in names and (tmp_path / "a" / "checkpoints" / "best" / "eval.json").is_file()


def _weights(run_dir):
    tensors = load_file(str(resolve_checkpoint(run_dir) / "tensors.safetensors"))
    return {k: v for k, v in tensors.items() if k.startswith(("module/", "replay/"))}


def test_an_off_policy_run_resumed_between_episodes_equals_the_uninterrupted_run(tmp_path):
    # Pendulum episodes last 200 steps: a checkpoint every 400 steps falls between episodes, where
    # the resumed envs restart from the seeds the uninterrupted run drew, so nothing differs.
    def config(run_dir, steps):
        return build_config({"algo": "sac", "seed": 1, "steps": steps, "run_dir": str(run_dir), "checkpoint_every": 400,
                             "env": {"id": "Pendulum-v1", "num_envs": 1},
                             "sac": {"learning_starts": 300, "hidden": [32, 32], "batch_size": 32}})

    train(config(tmp_path / "straight", 1200), progress=False)
    train(config(tmp_path / "split", 800), progress=False)       # "killed" at step 800
    train(config(tmp_path / "split", 1200), resume=True, progress=False)
    a, b = _weights(tmp_path / "straight"), _weights(tmp_path / "split")
    assert a.keys() == b.keys() and "replay/obs" in a
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert [p.name for p in list_checkpoints(tmp_path / "split")] == [p.name for p in list_checkpoints(tmp_path / "straight")]
    # the same episode history, but for the first process's last log at the interruption (step
    # 800); losses are means since the previous log, so that extra log changes the next one
    episodes = lambda run: [r for r in _metrics(tmp_path / run) if r[1].startswith("episode/") and r[0] != "800"]  # noqa: E731
    assert episodes("split") == episodes("straight") and len(episodes("straight")) >= 4
