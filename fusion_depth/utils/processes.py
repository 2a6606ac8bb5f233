"""Worker processes that end with their parent: a worker whose parent is killed (``kill -9``,
an out-of-memory kill, a closed terminal) must not go on using every core for hours, nor compete
with the next run for the same files.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time

_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_POLL_S = 0.5


def pid_alive(pid: object) -> bool:
    """Whether a process ``pid`` runs on this machine (another user's counts as alive)."""
    if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _set_parent_death_signal(signum: int) -> bool:
    """Linux's ``prctl(PR_SET_PDEATHSIG, signum)``: the kernel sends ``signum`` to this process
    when the thread that forked it ends. False where there is no such call."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, signum, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def die_with_parent(parent_pid: int) -> None:
    """Ends this (forked) process with SIGKILL as soon as ``parent_pid``, its parent, is gone.

    On Linux the kernel does it (``PR_SET_PDEATHSIG``), whatever the process is doing, even
    inside a long C call; elsewhere a daemon thread checks the parent every 0.5 s. A parent
    already gone before this call ends the process at once. SIGKILL leaves no chance to clean
    up: what the process was writing is a temporary file, which the next run removes
    (:func:`~fusion_depth.utils.atomic.remove_orphaned_temporaries`).
    """
    if not _set_parent_death_signal(signal.SIGKILL):

        def watch() -> None:
            while os.getppid() == parent_pid:
                time.sleep(_POLL_S)
            os.kill(os.getpid(), signal.SIGKILL)

        threading.Thread(target=watch, name="die-with-parent", daemon=True).start()
    if os.getppid() != parent_pid:  # the parent died before the death signal was set
        os.kill(os.getpid(), signal.SIGKILL)
