import os
import subprocess
import sys

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


@pytest.fixture
def run_cli():
    """Run `python -m drivelab ARGS...` and return the CompletedProcess (text output)."""

    def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "drivelab", *map(str, args)], capture_output=True, text=True,
                              timeout=timeout)

    return _run
