"""Scratch directories of a running agent under the system's temporary directory, and the ones killed agents
left there.

The history writer's socket lives in such a directory (output.history_feed), and so do the console's
session files (service.session_files); a clean stop removes them, a `kill -9` of `twin run` cannot, and a
host that runs for weeks gathered them kill after kill. So a directory's name says
whose it is: the owner's pid and when that process started (the kernel's start time, so a pid used again by
another process is not taken for the owner), e.g. `twin-history-4242-987654-k3j2h1x0`. Making one first
removes those of the same prefix whose owner is gone, and never one whose owner runs: several agents may run
at once (the tests in parallel, two of a person's). Only directories in `tempfile.gettempdir()`, of this
user, whose names have the prefix and an owner are looked at; directories made by agents older than this
naming say no owner and are left alone.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import stat
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

_PROC = Path("/proc")


def owned_tempdir(prefix: str) -> Path:
    """A new directory in the system's temporary directory, named for this process (module doc); the ones of
    `prefix` left by processes that no longer run are removed first."""
    remove_orphans(prefix)
    pid = os.getpid()
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{pid}-{_start_time(pid) or 0}-"))


def remove_orphans(prefix: str) -> list[Path]:
    """Remove this user's directories of `prefix` whose owner no longer runs; returns them."""
    root = Path(tempfile.gettempdir())
    named = re.compile(re.escape(prefix) + r"(\d+)-(\d+)-[^/]+")
    removed: list[Path] = []
    try:
        entries = list(os.scandir(root))
    except OSError as exc:
        log.warning("the temporary directory %s cannot be listed: %s", root, exc)
        return removed
    for entry in entries:
        owner = named.fullmatch(entry.name)
        if owner is None or _runs(int(owner[1]), int(owner[2])):
            continue
        try:
            info = entry.stat(follow_symlinks=False)
        except OSError:
            continue  # gone meanwhile
        if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        removed.append(Path(entry.path))
    if removed:
        log.info(
            "removed %d scratch directories of agents no longer running",
            len(removed),
            extra={"directories": [str(p) for p in removed]},
        )
    return removed


def _runs(pid: int, started: int) -> bool:
    """Whether process `pid`, started at `started` (0: not known), still runs."""
    now = _start_time(pid)
    if now is not None:
        return started in (0, now)
    if _PROC.is_dir():
        return False  # /proc lists every process: this one is gone
    try:
        os.kill(pid, 0)  # where there is no /proc: is there a process of that pid at all
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's, running
    return True


def _start_time(pid: int) -> int | None:
    """When process `pid` started (clock ticks since boot, /proc/<pid>/stat field 22); None when /proc has
    no such process or no /proc at all."""
    try:
        text = (_PROC / str(pid) / "stat").read_text()
    except OSError:
        return None
    # Field 2, the command, is in parentheses and may hold spaces and parentheses itself.
    fields = text[text.rindex(")") + 2 :].split()
    return int(fields[19])
