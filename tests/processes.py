"""Processes of the test session: the CLI in a process of its own (:func:`run_drivelab`)."""

import atexit
import multiprocessing
import os
import runpy
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path

from drivelab.envs import worker_start_method

METADRIVE_ID = "MetaDrive-10env-v0"   # whose modules the test processes' fork server imports (conftest.py)


def run_drivelab(*args: str, env: dict[str, str] | None = None, cwd: Path | None = None,
                 timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m drivelab ARGS`` in a process of its own: its exit status (negative: the signal
    that killed it), stdout and stderr as text, like ``subprocess.run(..., capture_output=True)``.

    On Linux the process is forked from the test session's fork server, a fresh interpreter that
    has imported drivelab's CLI once, instead of starting a new interpreter: that import (torch
    first) is ~3.5 s of CPU per run on a 2 GHz core, and the suite runs the CLI dozens of times. The run
    itself is the CLI's: its own env workers, signal handlers and fork server, its atexit handlers
    at the end. Tests of what a terminal sees (signals to a process group, the installed entry
    point) start a real ``python -m drivelab`` instead."""
    args = [str(a) for a in args]
    env = dict(os.environ if env is None else env)
    if worker_start_method(METADRIVE_ID) != "forkserver":
        return subprocess.run([sys.executable, "-m", "drivelab", *args], capture_output=True, text=True,
                              timeout=timeout, env=env, cwd=cwd)
    with tempfile.TemporaryDirectory(prefix="drivelab-cli-") as tmp:
        out, err = Path(tmp, "stdout"), Path(tmp, "stderr")
        context = multiprocessing.get_context("forkserver")
        process = context.Process(target=_drivelab_main, args=(args, env, cwd, out, err))
        process.start()
        process.join(timeout)
        if process.exitcode is None:
            process.kill()
            process.join()
            raise subprocess.TimeoutExpired(["drivelab", *args], timeout)
        return subprocess.CompletedProcess(["drivelab", *args], process.exitcode, out.read_text(), err.read_text())


def _drivelab_main(args: list[str], env: dict[str, str], cwd: Path | None, out: Path, err: Path) -> None:
    """The body of :func:`run_drivelab`'s process: what ``python -m drivelab ARGS`` would do."""
    os.environ.clear()
    os.environ.update(env)
    if cwd is not None:
        os.chdir(cwd)
    for entry in reversed([p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]):
        if entry not in sys.path:  # PYTHONPATH is read when an interpreter starts: this one has started
            sys.path.insert(0, entry)
    for fd, path in ((1, out), (2, err)):  # file descriptors, so that the run's own subprocesses write there too
        opened = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(opened, fd)
        os.close(opened)
    sys.stdout, sys.stderr = open(1, "w", closefd=False), open(2, "w", closefd=False, buffering=1)
    sys.argv = ["drivelab", *args]
    try:
        runpy.run_module("drivelab", run_name="__main__", alter_sys=True)
    except (SystemExit, KeyboardInterrupt):
        raise   # multiprocessing turns SystemExit into the exit status, as the interpreter does
    except BaseException:
        traceback.print_exc()   # as the interpreter would, before its exit status 1
        raise SystemExit(1) from None
    finally:
        atexit._run_exitfuncs()   # a multiprocessing child ends without them; an interpreter runs them
        sys.stdout.flush()
        sys.stderr.flush()
