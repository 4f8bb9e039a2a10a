import multiprocessing
import multiprocessing.forkserver
import os
import subprocess
from concurrent.futures import ProcessPoolExecutor

import pytest

# One OpenMP thread per process (torch, and the BLAS of every subprocess: notebook kernels, CLI
# runs, env workers): the xdist workers and the processes they start already share the cores,
# and a second thread per process spins waiting for a core instead of working. Set before torch
# is imported (by drivelab, below), which reads it once.
os.environ.setdefault("OMP_NUM_THREADS", "1")

from drivelab.algos import ALGORITHMS
from drivelab.envs import worker_start_method
from flaky_env import importable_env
from processes import METADRIVE_ID, run_drivelab

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


def pytest_collection_modifyitems(config, items):
    """The learning tests (marked slow: a minute or more each) first, in their files' order: with
    two xdist workers stealing work from each other, a long test started last leaves the other
    worker idle at the end of the suite (longest-first scheduling)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(scope="session", autouse=True)
def fork_server_with_metadrive():
    """Start this pytest process's fork server (Linux) as a MetaDrive run would, with MetaDrive
    imported: most of the suite's subprocess envs are MetaDrive's, so each forks in under a second
    instead of importing it again (6 s of CPU on a 2 GHz core). Left to itself, the server would
    take the preloads of whichever env the first test happens to build. It imports drivelab's CLI,
    its API and the algorithms (and so torch: the CLI itself imports them only when a command
    runs) too, for the CLI runs of :func:`run_drivelab`, and torch._dynamo, which torch imports
    when a run builds its first optimizer (2.7 s of CPU on a 2 GHz core)."""
    if worker_start_method(METADRIVE_ID) == "forkserver":
        env_modules = multiprocessing.forkserver._forkserver._preload_modules
        algorithms = [f"drivelab.algos.{name}" for name in ALGORITHMS]
        multiprocessing.set_forkserver_preload([*env_modules, "drivelab.cli", "drivelab.api", *algorithms,
                                                "torch._dynamo"])
        multiprocessing.forkserver.ensure_running()


@pytest.fixture
def run_cli():
    """Run ``drivelab ARGS...`` (:func:`run_drivelab`) with this directory importable (``--env
    flaky_env:Flaky-v0``) and return the CompletedProcess (text output)."""

    def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
        return run_drivelab(*args, env=importable_env(), timeout=timeout)

    return _run


@pytest.fixture
def fresh_process():
    """The function ``run_in_fresh_process`` (below), for tests that build MetaDrive's pygame views."""
    return run_in_fresh_process


def run_in_fresh_process(fn, *args, timeout: float = 300):
    """Call the module-level function ``fn(*args)`` in a new interpreter and return its result.

    MetaDrive's engine (Panda3D, Bullet, pygame) is one per process and leaves state behind when it
    closes: a pygame top-down canvas built after several engines in the pytest process segfaulted on
    CI and took the whole suite down. In a fresh process the same test is isolated, an assertion comes
    back as itself (with the child's traceback as its cause) and a crash fails only this test.
    """
    context = multiprocessing.get_context(worker_start_method(METADRIVE_ID))  # a fresh interpreter either way
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(fn, *args).result(timeout=timeout)
