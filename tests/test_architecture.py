"""The shape of the code: no import cycles, each algorithm's loop deterministic and resumable."""

import ast
import csv
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from drivelab.algos import ALGORITHMS
from drivelab.api import build_config, train
from drivelab.training.outputs.checkpoint import list_checkpoints, resolve_checkpoint

PACKAGE = Path(__file__).resolve().parent.parent / "drivelab"

# The layers, bottom first. A module may import its own layer and the layers below it, never one
# above; the faces (the package's lazy API, the CLI) sit on top.
LAYERS = (
    ("drivelab.errors", "drivelab.version"),
    ("drivelab.envs",),          # environments, wrappers, vectorisation, the env config
    ("drivelab.config",),        # the whole run's config
    # what every algorithm uses, in four rooms (drivelab/training/__init__.py)
    ("drivelab.training", "drivelab.training.learning"),  # returns, losses, optimisers, nets, storage
    ("drivelab.training.outputs",),     # episode statistics, checkpoints, metrics, plots, videos
    ("drivelab.training.collection",),  # collectors, exploration, worker rollouts, evaluation episodes
    ("drivelab.training.run",),         # Run and its services
    ("drivelab.algos",),         # one file per algorithm, and the registry
    ("drivelab.tools",),         # around runs: loading policies, baselines, export, report, sweep
    ("drivelab.api",),           # the Python face
    ("drivelab.cli", "drivelab.__main__", "drivelab"),
)


def _layer(module: str) -> int:
    """The layer of the longest prefix that names ``module`` or a package above it."""
    matches = [(len(p), level) for level, prefixes in enumerate(LAYERS) for p in prefixes
               if module == p or (p not in ("drivelab", "drivelab.training") and module.startswith(p + "."))]
    if not matches:
        raise AssertionError(f"{module} belongs to no layer: add its folder to LAYERS")
    return max(matches)[1]


def _module_name(path: Path, package: Path) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _under_type_checking(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return True
    return False


def _imports(path: Path, modules: set[str], package: Path = PACKAGE) -> set[str]:
    """Every drivelab module that ``path`` imports, at module level or inside a function (imports
    under ``if TYPE_CHECKING`` never run and are left out)."""
    tree = ast.parse(path.read_text())
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    name = _module_name(path, package)
    home = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against this module's package
                parts = home.split(".")
                base = ".".join([*parts[: len(parts) - node.level + 1], *([base] if base else [])])
            # `from drivelab.algos import ppo` imports the submodule drivelab.algos.ppo
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        else:
            continue
        if not _under_type_checking(node, parents):
            found.update(n for n in names if n in modules)
    return found


def _graph() -> dict[str, set[str]]:
    files = {_module_name(p, PACKAGE): p for p in PACKAGE.rglob("*.py")}
    return {name: _imports(path, set(files)) - {name} for name, path in files.items()}


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


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_among_drivelab_modules():
    graph = _graph()
    assert len(graph) > 30 and graph["drivelab.api"] >= {"drivelab.algos", "drivelab.training.run"}
    assert _cycles(graph) == []


def test_imports_run_only_down_the_layers():
    upward = sorted(f"{module} -> {dep}" for module, deps in _graph().items() for dep in deps
                    if _layer(dep) > _layer(module))
    assert upward == [], upward


def test_the_package_root_holds_only_the_faces_and_the_base():
    root = sorted(p.stem for p in PACKAGE.glob("*.py"))
    assert root == ["__init__", "__main__", "api", "cli", "config", "errors", "version"], root


def test_every_training_module_lives_in_a_room():
    loose = sorted(p.name for p in (PACKAGE / "training").glob("*.py") if p.name != "__init__.py")
    assert loose == [], loose


def test_the_layer_of_a_module_is_its_innermost_room():
    assert _layer("drivelab.training.run.timing") > _layer("drivelab.training.collection.rollout") > \
        _layer("drivelab.training.outputs.checkpoint") > _layer("drivelab.training.learning.losses") > _layer("drivelab.config")
    with pytest.raises(AssertionError, match="belongs to no layer"):
        _layer("drivelab.training.newroom.x")


MAX_CLASS_LINES, MAX_FUNCTION_LINES = 150, 60


def _oversized(source: str, where: str) -> list[str]:
    """Classes over MAX_CLASS_LINES and functions (methods included) over MAX_FUNCTION_LINES,
    counted from the ``def``/``class`` line to the last line of the body."""
    found = []
    for node in ast.walk(ast.parse(source)):
        limit = (MAX_CLASS_LINES if isinstance(node, ast.ClassDef) else
                 MAX_FUNCTION_LINES if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) else None)
        if limit is not None and node.end_lineno - node.lineno + 1 > limit:
            found.append(f"{where}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines > {limit})")
    return found


def test_no_class_over_150_lines_and_no_function_over_60():
    found = [line for path in sorted(PACKAGE.rglob("*.py"))
             for line in _oversized(path.read_text(), str(path.relative_to(PACKAGE.parent)))]
    assert found == [], found


def test_the_size_check_sees_methods_and_classes():
    def body(n, indent):
        return "".join(f"{indent}x{i} = {i}\n" for i in range(n))
    # A: 1 + 61 + 120 lines, its method f: 1 + 60; B: 1 + 60 lines, its method g: 1 + 59 (at the limit)
    source = "class A:\n    def f(self):\n" + body(60, " " * 8) + body(120, " " * 4) + \
             "class B:\n    def g(self):\n" + body(59, " " * 8)
    assert sorted(line.split()[1] for line in _oversized(source, "m.py")) == ["A", "f"]


def test_the_import_walker_sees_function_level_and_relative_imports(tmp_path):
    source = tmp_path / "drivelab" / "tools" / "x.py"
    source.parent.mkdir(parents=True)
    source.write_text("import os\n\ndef f():\n    from drivelab.api import train\n    from ..config import x\n"
                      "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from drivelab.cli import main\n")
    found = _imports(source, {"drivelab.api", "drivelab.config", "drivelab.cli"}, package=tmp_path / "drivelab")
    assert found == {"drivelab.api", "drivelab.config"}


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
    # the constrained algorithms need an env with a cost (tests/constrained_env.py)
    "ppo_lag": {"env": {"id": "constrained_env:ThreeLanes-v0", "num_envs": 4}, "steps": 2500, "ppo_lag": {"num_steps": 64}},
    "sac_lag": {"env": {"id": "constrained_env:ThreeLanes-v0", "num_envs": 1}, "steps": 1200,
                "sac_lag": {"learning_starts": 400, "hidden": [32, 32], "batch_size": 32, "lagrange_every": 200},
                "eval": {"every": 600, "episodes": 1, "video": False}},
    # multi-agent: four cars of MetaDrive's Intersection in two scene processes
    "ippo": {"env": {"id": "MultiAgentIntersection-v0", "num_envs": 2, "kwargs": {"num_agents": 4, "horizon": 60}},
             "steps": 192, "ippo": {"num_steps": 32, "hidden": [32, 32]}, "eval": {"every": 0}},
    "mappo": {"env": {"id": "MultiAgentIntersection-v0", "num_envs": 2, "kwargs": {"num_agents": 4, "horizon": 60}},
              "steps": 192, "mappo": {"num_steps": 32, "hidden": [32, 32]}, "eval": {"every": 0}},
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
    if CASES[algo].get("eval", {}).get("every"):
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
