"""A history writer process (or a check of its commit) that dies where a test says (tests/test_history.py).

A module of its own, light to import: the spawned writer process unpickles its target by importing the module
that holds it, and test_history's imports (polars, moto, the test helpers) cost each writer seconds.
"""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path
from typing import Any

from twin.output.history_feed import writer_main


def writer_killed_in_its_first_commit(*args: Any) -> None:
    """The history writer process, killed (SIGKILL) as $TWIN_TEST_DIE_MARKER's file says, one word per
    process started (a comma-separated list, each process taking the first; once it is empty, a writer runs
    normally): "after": in its first commit once Delta has accepted the append, before the writer counts it;
    "before": as that append begins, once the commit is recorded; "start": before it says it is ready."""
    from twin.output import history as module

    marker = Path(os.environ["TWIN_TEST_DIE_MARKER"])
    if marker.exists():
        when, *rest = marker.read_text().split(",")
        if rest:
            marker.write_text(",".join(rest))
        else:
            marker.unlink()
        if when == "start":
            os.kill(os.getpid(), signal.SIGKILL)
        append = module.HistoryWriter._append

        def dying_append(self: Any, *a: Any, **k: Any) -> int | None:
            if when == "after":
                append(self, *a, **k)
            os.kill(os.getpid(), signal.SIGKILL)
            return None

        module.HistoryWriter._append = dying_append  # type: ignore[method-assign]
    writer_main(*args)


def check_that_dies(*args: Any) -> None:
    """The agent's check of a commit in doubt at its stop (history_feed.check_main), killed before it
    answers."""
    os.kill(os.getpid(), signal.SIGKILL)


def check_that_hangs(*args: Any) -> None:
    """The agent's check of a commit in doubt at its stop, hung (a store that never answers) and deaf to
    SIGINT as check_main is (no SIGTERM comes while the agent runs): the agent's kill at its timeout ends
    it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    threading.Event().wait()
