"""The console's session files on disk (CSV, Parquet, plots, `.rrd`, USD): made on demand, kept for the
next request, within a bound.

A completed session's file is made once and served from disk after that (an `.rrd` or a USD session of a long
session takes seconds to rebuild). Kept until the agent stopped, every file anyone ever asked for stayed: on a
host that runs for weeks, with people downloading sessions, that is disk (or, where /tmp is a tmpfs, memory)
without end. So the files together stay under `[http] session_files_mb`: once a new file takes them over, the
ones used longest ago go first. A file used within the last KEEP_S is never removed, because its download may
still be running (the response opens the file after the handler returned); the bound can be passed for that
long, never for good. A removed file is made again when asked for.

The directory is named for the agent's process (output.scratch), so one that a `kill -9` left behind is
removed when the next agent starts (`remove_orphans`), not left in /tmp for good.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from pathlib import Path

from twin.output import scratch

log = logging.getLogger(__name__)

# A file used this recently is kept whatever the bound: its download may still be reading it.
KEEP_S = 300.0
# Files being written have this suffix (ops.sessions): not the cache's yet.
PART_SUFFIX = ".part"
PREFIX = "twin-console-"


def remove_orphans() -> None:
    """Remove the session-file directories of agents that no longer run (killed before their stop)."""
    scratch.remove_orphans(PREFIX)


class SessionFiles:
    """A directory of session files made on demand (its own, made when first needed and removed by
    `close`), with at most `max_bytes` in it beyond the files used within KEEP_S."""

    def __init__(self, max_bytes: int, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_bytes = max_bytes
        self._clock = clock
        self._dir: Path | None = None
        self._used: dict[str, float] = {}  # file name -> when it was last made or served (clock)
        self.removed = 0  # files removed to keep the bound, over the agent's run

    @property
    def directory(self) -> Path:
        if self._dir is None:
            self._dir = scratch.owned_tempdir(PREFIX)
        return self._dir

    def used(self, path: Path) -> None:
        """`path` (in `directory`) was just made or served: the last to go, and kept for KEEP_S."""
        self._used[path.name] = self._clock()

    def trim(self) -> list[str]:
        """Remove the files used longest ago until the rest fit `max_bytes` (never one used within KEEP_S);
        the names removed."""
        if self._dir is None:
            return []
        sizes: dict[str, int] = {}
        young: set[str] = set()  # not served yet and written within KEEP_S: being made, most likely
        wall = time.time()
        for path in self._dir.iterdir():
            if path.name.endswith(PART_SUFFIX) or path.name == scratch.OWNER_FILE:
                continue  # a file being made, or the directory's lock (output.scratch)
            with contextlib.suppress(OSError):
                info = path.stat()
                sizes[path.name] = info.st_size
                if path.name not in self._used and wall - info.st_mtime < KEEP_S:
                    young.add(path.name)
        total = sum(sizes.values())
        now = self._clock()
        removed: list[str] = []
        # A file not served yet goes first, unless it is young: a plot or a USD session is written under a
        # name of its own while it is made (ops.sessions), and a file being made is not the cache's to remove.
        for name in sorted(sizes, key=lambda n: self._used.get(n, -1.0)):
            if total <= self.max_bytes:
                break
            if name in young or now - self._used.get(name, -KEEP_S * 2) < KEEP_S:
                continue
            with contextlib.suppress(OSError):
                (self._dir / name).unlink()
                total -= sizes[name]
                removed.append(name)
        for name in removed:
            self._used.pop(name, None)
        if removed:
            self.removed += len(removed)
            log.info(
                "session files: removed %d used longest ago to stay within %d MB (made again if asked for)",
                len(removed),
                self.max_bytes // 2**20,
                extra={"removed": len(removed), "kept_bytes": total},
            )
        return removed

    def close(self) -> None:
        if self._dir is not None:
            scratch.remove(self._dir)
            self._dir = None
        self._used.clear()
