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

A pid means something only in its own PID namespace: an agent in a container that shares the host's /tmp
has pids the host does not know, or knows as other processes. So the owner also holds an exclusive `flock`
on a file in its directory (OWNER_FILE) for as long as it lives, and the kernel drops it when the process
ends, however it ends; a lock is the same lock in every namespace on the host. A directory whose pid says
its owner is gone is removed only when its lock can be taken. The lock is taken before the directory gets
its name (it is made under a hidden one, locked, then renamed), so no other agent ever sees it named and
unlocked. A process killed in that instant leaves the hidden one, which names no owner: it is removed once
it is older than HIDDEN_GRACE_S and unlocked, since the steps from its making to its rename take
microseconds.
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import shutil
import stat
import tempfile
import time
from pathlib import Path

log = logging.getLogger(__name__)

_PROC = Path("/proc")
OWNER_FILE = ".owner"
# A hidden directory (still to be locked and named) this old is a killed maker's, not one being made.
HIDDEN_GRACE_S = 60.0
# The directories this process made, and the open file of each one's lock (the lock lasts while it is open).
_owned: dict[Path, int] = {}


def owned_tempdir(prefix: str) -> Path:
    """A new directory in the system's temporary directory, named for this process and locked by it (module
    doc); the ones of `prefix` left by processes that no longer run are removed first. `remove` it."""
    remove_orphans(prefix)
    pid = os.getpid()
    hidden = Path(tempfile.mkdtemp(prefix=f".{prefix}"))
    fd = -1
    try:
        fd = os.open(hidden / OWNER_FILE, os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(fd, fcntl.LOCK_EX)
        named = hidden.with_name(f"{prefix}{pid}-{_start_time(pid) or 0}-{hidden.name[len(prefix) + 1 :]}")
        os.rename(hidden, named)
    except OSError:
        if fd >= 0:
            os.close(fd)
        shutil.rmtree(hidden, ignore_errors=True)
        raise
    _owned[named] = fd
    return named


def remove(directory: Path) -> None:
    """Remove a directory `owned_tempdir` made, then let go of its lock. Idempotent."""
    shutil.rmtree(directory, ignore_errors=True)
    fd = _owned.pop(directory, None)
    if fd is not None:
        os.close(fd)


def remove_orphans(prefix: str) -> list[Path]:
    """Remove this user's directories of `prefix` whose owner no longer runs; returns them."""
    root = Path(tempfile.gettempdir())
    named = re.compile(re.escape(prefix) + r"(\d+)-(\d+)-[^/]+")
    hidden = re.compile(r"\." + re.escape(prefix) + r"[^/]+")
    now = time.time()
    removed: list[Path] = []
    try:
        entries = list(os.scandir(root))
    except OSError as exc:
        log.warning("the temporary directory %s cannot be listed: %s", root, exc)
        return removed
    for entry in entries:
        owner = named.fullmatch(entry.name)
        if owner is None:
            if hidden.fullmatch(entry.name) is None:
                continue
        elif _runs(int(owner[1]), int(owner[2])):
            continue
        try:
            info = entry.stat(follow_symlinks=False)
        except OSError:
            continue  # gone meanwhile
        if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
            continue
        if owner is None and now - info.st_mtime < HIDDEN_GRACE_S:
            continue  # being made, most likely: locked and named in a moment
        if _locked(Path(entry.path)):
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


def _locked(directory: Path) -> bool:
    """Whether a live process may hold `directory`'s lock (its owner, in a PID namespace of its own maybe).
    Without the lock file (an agent older than the lock made it), the pid alone decides, as it did then. A
    lock that cannot be tried (a filesystem without flock, say) counts as held: a directory left behind
    costs little, one removed under a running agent costs its socket."""
    try:
        # Opened for writing: where flock is emulated with byte-range locks (NFS), an exclusive one needs it.
        fd = os.open(directory / OWNER_FILE, os.O_RDWR)
    except FileNotFoundError:
        return False
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True  # held (BlockingIOError), or not to be tried
    finally:
        os.close(fd)  # (which lets go of the lock, if it was taken)
    return False


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
