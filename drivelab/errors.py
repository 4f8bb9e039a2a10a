"""What goes wrong, on purpose or not: the one exception type that the CLI turns into a one-line
message instead of a traceback, SIGTERM as an exception (:class:`Terminated`), and the hook that
lets tests kill a run at a named phase."""

from __future__ import annotations

import os
import signal
from collections import Counter
from pathlib import Path


class DrivelabError(Exception):
    """Bad input from the user: a config field, an env id, a missing file.

    The message must fit on one line and name the offending field or file.
    """


class TrainingCrashed(DrivelabError):
    """An unexpected exception escaped training. Its message is one line naming the error, the
    run's ``error.log`` (which holds the traceback) and the command that continues the run; the
    original exception is its ``__cause__``. The CLI exits with 1 for it (2 is for bad input)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (what a cluster scheduler or ``kill`` sends), raised where Ctrl-C raises
    ``KeyboardInterrupt``, so that a run stops the same way, with a checkpoint. It is a
    ``KeyboardInterrupt``, so every handler of Ctrl-C handles it too; the CLI tells the two apart
    only for its exit code: 128 + 15 = 143 for SIGTERM, 128 + 2 = 130 for Ctrl-C, as a shell does."""


def raise_interrupt(signum, frame) -> None:
    """The SIGTERM handler of a run (:func:`drivelab.api.stop_signals`, the CLI): stop like Ctrl-C."""
    raise Terminated


# Where a run can be killed on purpose (``DRIVELAB_KILL_AT=PHASE`` or ``PHASE:N``, the N-th time
# the process reaches it), so that the kill tests choose moments by what the run is doing rather
# than by the clock. ``DRIVELAB_KILL_MARKER=FILE`` kills only while FILE does not exist (and
# creates it first), so a restarted env worker or a resumed run is not killed again.
KILL_PHASES = ("before-config", "after-first-checkpoint", "mid-checkpoint", "mid-evaluation", "mid-video",
               "best-copy", "env-worker")
_reached: Counter[str] = Counter()


def kill_point(phase: str) -> None:
    """SIGKILL this process if ``DRIVELAB_KILL_AT`` names ``phase`` (a no-op otherwise)."""
    wanted = os.environ.get("DRIVELAB_KILL_AT")
    if not wanted or wanted.split(":")[0] != phase:
        return
    _reached[phase] += 1
    if _reached[phase] != int(wanted.partition(":")[2] or 1):
        return
    marker = os.environ.get("DRIVELAB_KILL_MARKER")
    if marker:
        if Path(marker).exists():
            return
        Path(marker).write_text(f"{phase} {os.getpid()}\n")
    os.kill(os.getpid(), signal.SIGKILL)
