"""Scratch directories (output.scratch): the history writer's socket directory of an agent killed with
`kill -9` is removed by the next agent that starts, and never one of an agent that runs, in a PID namespace of
its own too (its lock says so where its pid cannot).

Real processes, each making the HistoryProcess an agent makes, in a temporary directory of the test's own
(TMPDIR for the children, `tempfile.tempdir` here), so tests running in parallel never see each other's.
"""

from __future__ import annotations

import fcntl
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from twin.output import scratch
from twin.output.history_feed import HistoryProcess

AGENTS = Path(__file__).resolve().parents[1] / "agents"
# A process that makes an agent's HistoryProcess (its socket's directory), says where, and waits.
HOLDER = (
    "import multiprocessing, sys\n"
    "from twin.output.history_feed import HistoryProcess\n"
    "history = HistoryProcess({}, multiprocessing.get_context('spawn'))\n"
    "print(history.link.address, flush=True)\n"
    "sys.stdin.read()\n"
)


@pytest.fixture
def tmp_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """The temporary directory of this test's processes, this one's included."""
    root = tmp_path / "tmp"
    root.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(root))
    yield root


def _holder(tmp_dir: Path) -> tuple[subprocess.Popen[str], Path]:
    env = {**os.environ, "TMPDIR": str(tmp_dir), "PYTHONPATH": str(AGENTS)}
    child = subprocess.Popen(
        [sys.executable, "-c", HOLDER], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
    )
    assert child.stdout is not None
    line = child.stdout.readline().strip()
    assert line, f"the holder exited with {child.wait(30)} before saying where its socket is"
    return child, Path(line).parent


def test_the_directory_of_a_killed_agent_goes_and_a_running_agent_s_stays(tmp_dir: Path) -> None:
    killed, killed_dir = _holder(tmp_dir)
    running, running_dir = _holder(tmp_dir)
    try:
        killed.send_signal(signal.SIGKILL)
        killed.wait(30)
        assert killed_dir.is_dir() and running_dir.is_dir()  # kill -9: nothing of it removed its directory

        ours = HistoryProcess({}, multiprocessing.get_context("spawn"))

        assert not killed_dir.exists()
        assert running_dir.is_dir()
        ours_dir = Path(ours.link.address).parent
        assert ours_dir.is_dir() and ours_dir.parent == tmp_dir
        assert ours_dir.name.startswith(f"twin-history-{os.getpid()}-")
        ours.stop(timeout=1.0)  # never launched: a clean stop removes its directory all the same
        assert not ours_dir.exists()
    finally:
        running.kill()
        running.wait(30)


def test_only_this_user_s_named_directories_of_gone_owners_are_removed(tmp_dir: Path) -> None:
    # A process that ran and ended: its pid and start time are known, and it is gone.
    ended = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    ended_start = scratch._start_time(ended.pid)
    ended.kill()
    ended.wait(30)
    me, my_start = os.getpid(), scratch._start_time(os.getpid())
    assert ended_start is not None and my_start is not None
    gone = tmp_dir / f"twin-history-{ended.pid}-{ended_start}-a1"
    reused = tmp_dir / f"twin-history-{me}-{my_start + 1}-b2"  # this pid, another process's start: reused
    mine = tmp_dir / f"twin-history-{me}-{my_start}-c3"
    unknown_start = tmp_dir / f"twin-history-{me}-0-d4"  # where no start time could be read: the pid runs
    older = tmp_dir / "twin-history-e5f6g7h8"  # an older agent's: no owner in its name
    other_prefix = tmp_dir / f"twin-other-{ended.pid}-{ended_start}-f6"
    for directory in (gone, reused, mine, unknown_start, older, other_prefix):
        directory.mkdir()
        (directory / "writer.sock").touch()
    a_file = tmp_dir / f"twin-history-{ended.pid}-{ended_start}-g7"
    a_file.touch()
    theirs = tmp_dir / f"twin-history-{ended.pid}-{ended_start}-h8"
    if os.getuid() == 0:
        theirs.mkdir()
        os.chown(theirs, 65534, 65534)

    removed = scratch.remove_orphans("twin-history-")

    assert sorted(removed) == sorted([gone, reused])
    assert not gone.exists() and not reused.exists()
    assert all(p.exists() for p in (mine, unknown_start, older, other_prefix, a_file))
    assert theirs.exists() or os.getuid() != 0


def test_a_running_agent_in_another_pid_namespace_keeps_its_directory(tmp_dir: Path) -> None:
    # An agent in a container of its own sharing this /tmp: its pid (1, in its namespace) names a process
    # here that is not it, so the pid cannot tell whether it runs; its lock on the directory can.
    env = {**os.environ, "TMPDIR": str(tmp_dir), "PYTHONPATH": str(AGENTS)}
    command = ["unshare", "--pid", "--mount-proc", "--kill-child=SIGKILL", sys.executable, "-c", HOLDER]
    contained = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert contained.stdout is not None
        line = contained.stdout.readline().strip()
        assert line, f"unshare exited with {contained.wait(30)}: a PID namespace needs root (CAP_SYS_ADMIN)"
        directory = Path(line).parent
        pid = int(directory.name.split("-")[2])
        assert pid != contained.pid  # named for its pid in its own namespace
        assert not scratch._runs(pid, int(directory.name.split("-")[3]))  # which says gone here

        assert scratch.remove_orphans("twin-history-") == []
        assert directory.is_dir()

        contained.kill()  # kill -9 of the container's agent (--kill-child: the kernel ends the holder too)
        contained.wait(30)
        removed: list[Path] = []
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:  # its lock goes once the kernel has ended it
            removed = scratch.remove_orphans("twin-history-")
            if removed:
                break
            time.sleep(0.05)
        assert removed == [directory] and not directory.exists()
    finally:
        contained.kill()
        contained.wait(30)


def test_a_directory_is_locked_before_it_has_its_name_and_released_when_removed(tmp_dir: Path) -> None:
    made = scratch.owned_tempdir("twin-test-")
    assert made.parent == tmp_dir and made.name.startswith(f"twin-test-{os.getpid()}-")
    assert scratch._locked(made)  # the lock file, held by this process
    assert not list(tmp_dir.glob(".twin-test-*"))  # the hidden name it was made under is gone
    scratch.remove(made)
    assert not made.exists() and made not in scratch._owned
    scratch.remove(made)  # twice: nothing more to do


def test_a_hidden_directory_a_kill_left_before_its_rename_goes_once_old_and_unlocked(tmp_dir: Path) -> None:
    # owned_tempdir makes a hidden directory, locks it and renames it; a kill in between leaves the hidden
    # one, which names no owner. Only an old one is a killed maker's (a young one is being made), and a
    # locked one is a maker's that is about to rename it.
    old = time.time() - scratch.HIDDEN_GRACE_S - 5
    left = tmp_dir / ".twin-history-k1ll3d00"
    young = tmp_dir / ".twin-history-m4k1ng00"
    held = tmp_dir / ".twin-history-l0ck3d00"
    other_prefix = tmp_dir / ".twin-other-k1ll3d00"
    for directory in (left, young, held, other_prefix):
        directory.mkdir()
        (directory / scratch.OWNER_FILE).touch()
    for directory in (left, held, other_prefix):
        os.utime(directory, (old, old))
    # Another open file description of the lock file: the same conflict as another process's flock.
    fd = os.open(held / scratch.OWNER_FILE, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        removed = scratch.remove_orphans("twin-history-")
    finally:
        os.close(fd)

    assert removed == [left]
    assert not left.exists()
    assert young.exists() and held.exists() and other_prefix.exists()
