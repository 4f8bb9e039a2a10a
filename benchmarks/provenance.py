"""What every benchmark's results JSON records of how it was made, so that a number can be traced
back to its command, code, packages, machine and time (imported by the scripts beside it as
``from provenance import provenance``)."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("torch", "numpy", "gymnasium", "metadrive-simulator")
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")


def package_version(name: str) -> str | None:
    """The installed version of a package, None when it is not installed (a benchmark must not fail on it)."""
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def git(*args: str) -> str:
    """A git command's output in the checkout this file lives in ("" when git or the checkout is missing)."""
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout.strip()
    except OSError:
        return ""


def utc_iso(seconds: float) -> str:
    """A time.time() value as ISO-8601 UTC, to the second."""
    return datetime.fromtimestamp(seconds, timezone.utc).isoformat(timespec="seconds")


def threads() -> dict:
    """torch's intra-op threads now (None without torch) and the thread variables as set (None when unset)."""
    try:
        import torch
        torch_threads = torch.get_num_threads()
    except ImportError:
        torch_threads = None
    return {"torch": torch_threads, **{name: os.environ.get(name) for name in THREAD_VARIABLES}}


def provenance(started: float | None = None) -> dict:
    """The command, the commit (and whether tracked files outside benchmarks/results had changes),
    the versions of what was measured, the machine, the threads, and when the measurement started
    (``started``, a time.time() value; now when None) and ended (now)."""
    # Imported here, not at the top: importing this module stays cheap (torch loads with drivelab's
    # timing), so a script may import it before it forks workers that set up torch themselves.
    from drivelab.training.run.timing import machine
    from drivelab.version import __version__

    ended = time.time()
    return {"command": shlex.join(["python", *sys.argv]), "commit": git("rev-parse", "HEAD"),
            # results files do not count: a benchmark rewrites its own table (and a sitting the one
            # the sitting before it wrote), which changes no code that measures
            "uncommitted_changes": bool(git("status", "--porcelain", "--untracked-files=no", "--", ".",
                                            ":(exclude)benchmarks/results")),
            "versions": {"python": sys.version.split()[0], "drivelab": __version__,
                         **{name: package_version(name) for name in PACKAGES}},
            "machine": machine(), "threads": threads(),
            "started": utc_iso(ended if started is None else started), "ended": utc_iso(ended)}
