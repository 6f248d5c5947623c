"""Child processes that end with the process that started them.

A broker, an agent or a publisher started by the local rig, a benchmark or the agent itself outlives a
parent killed outright (SIGKILL, the OOM killer, a CI job's timeout): it keeps its port, its files and its
share of the cores, and the next run finds the port taken or measures beside it. Linux can tie a child's
life to its parent's (prctl PR_SET_PDEATHSIG); `die_with_parent` gives the `preexec_fn` that does it.

The kernel sends the signal when the *thread* that forked the child ends, not the process. A child started
from a thread that then returns (a supervisor's restart, a test's helper thread) would be stopped with that
thread, so the tie is made only from the main thread, which lives as long as the process.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import threading
from collections.abc import Callable

_PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int = signal.SIGTERM) -> Callable[[], None] | None:
    """A `preexec_fn` for subprocess.Popen that has the kernel send `sig` to the child when this process
    dies; None (no preexec_fn) when called off the main thread or where prctl is not to be had."""
    if threading.current_thread() is not threading.main_thread():
        return None
    try:
        # Looked up here, in the parent: loading a library between fork and exec can deadlock on a lock
        # another thread of the parent held at the fork.
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    parent = os.getpid()

    def tie() -> None:  # pragma: no cover - runs in the child between fork and exec
        with contextlib.suppress(Exception):
            prctl(_PR_SET_PDEATHSIG, sig)
            # The parent may have died between the fork and the prctl: then no signal would come.
            if os.getppid() != parent:
                os.kill(os.getpid(), sig)

    return tie
