"""The events page over a restart: the agent's events, appended to a file and read back at its next start.

The agent's `EventStore` is memory only. Without this, a restart (a deploy, a reboot, a crash and systemd
starting it again) leaves an operator who opens the Events page the next morning a list that begins at the
restart, and each session's count of the alarms raised in it at 0. With `[twin] events_file` set, every
event the store numbers is appended to that file as one JSON line, and the next start puts the newest
`capacity` of them back in its store with their ids, so the page, its exports and the sessions read the
same before and after.

- **When it is written.** The store calls `add` on whatever thread makes the event, which must only hand it
  on; the agent's supervisor calls `flush` every round (half a second) and the stop calls it last. So a
  process killed outright loses at most its last round of events, and the run after it says so
  (`AgentService` reads the journal's last event: a run that stopped wrote `agent stopped` last).
- **How big it gets.** The file is renamed `<name>.1` once it passes `max_bytes` (replacing the one before)
  and a new one begun, so the disk holds at most about twice `max_bytes`. The default holds more than a
  store keeps (about 300 bytes an event), so the newest `capacity` are always in the two files.
- **What goes wrong.** A line cut short by a kill, or one that is not an event, is skipped when read back and
  counted (`unreadable`, one warning); the next write starts on a line of its own. A write that fails (disk
  full, permissions) is logged with what to do and its events counted (`not_written`); they stay in the
  store, and the next flush tries again with the events made since. What waits for a flush is bounded
  (`MAX_PENDING`; the oldest go, counted), so a disk that stays broken cannot grow the agent's memory. The
  counts are an output's in /state (`agent.sinks`, `events_journal`), so they reach CloudWatch's SinkDrops.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import BinaryIO

import msgspec

from twin.core.throttle import Throttle
from twin.output.sinks import SinkStats
from twin.service.events import DEFAULT_CAPACITY, Event

log = logging.getLogger(__name__)

__all__ = ["MAX_BYTES", "MAX_PENDING", "SINK_NAME", "EventJournal"]

# Its name among the outputs of /state's `agent.sinks` and /metrics' `sink` label.
SINK_NAME = "events_journal"

# Each of the two files is renamed away once past this: at about 300 bytes an event, each holds more than a
# store's DEFAULT_CAPACITY, so reading the two back always finds the newest `capacity`.
MAX_BYTES = 8 * 1024 * 1024
# Events waiting for a flush: a store's worth. More only while writes fail; then the oldest go, counted.
MAX_PENDING = DEFAULT_CAPACITY
# A write that keeps failing is logged again at most this often (each flush would otherwise log).
WARN_EVERY_S = 60.0

_DECODER = msgspec.json.Decoder(Event)
_ENCODER = msgspec.json.Encoder()


class EventJournal:
    """Appends events to `path` and reads them back (module doc). Thread-safe: `add` from any thread,
    `flush` from the agent's supervisor and its stop, one at a time."""

    def __init__(
        self, path: str | Path, *, max_bytes: int = MAX_BYTES, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if max_bytes < 1:
            raise ValueError(f"an event journal's files hold at least one byte, got max_bytes = {max_bytes}")
        self.path = Path(path)
        self.previous = self.path.with_name(self.path.name + ".1")
        self.max_bytes = max_bytes
        self._pending: deque[Event] = deque()
        self._lock = threading.Lock()  # the queue
        # One flush at a time: a supervisor round still flushing as the stop closes must not interleave.
        self._write_lock = threading.RLock()
        self._file: BinaryIO | None = None
        self._error_lines = Throttle(WARN_EVERY_S, clock=clock)
        self.written = 0
        self.write_failures = 0
        self.last_error = ""
        self.not_written = 0  # failed writes, and events pushed out of the waiting queue by newer ones
        self.unreadable = 0  # lines of the files read back that were not events

    # -- reading -------------------------------------------------------------------------------------------

    def load(self, limit: int | None = DEFAULT_CAPACITY) -> list[Event]:
        """The newest `limit` events the files hold (None: all of them), oldest first, as they were
        numbered; [] for none. A file that cannot be read is reported and left as it is (the next write
        appends to it)."""
        try:
            fresh = not self.path.exists() and not self.previous.exists()
        except OSError:
            fresh = False  # its directory cannot be searched: reading says why
        if fresh:
            # Absolute: a relative path started from another directory is a new, empty journal there.
            log.info(
                "event journal %s does not exist yet: the Events page starts empty",
                self.path.absolute(),
                extra={"path": str(self.path.absolute())},
            )
            return []
        events, bad = self._read(self.path)
        if limit is None or len(events) < limit:
            # The older file only when the current one holds too few: it is most of a start's reading.
            older, bad_older = self._read(self.previous)
            wanted = len(older) if limit is None else limit - len(events)
            events, bad = older[max(0, len(older) - wanted) :] + events, bad + bad_older
        if bad:
            self.unreadable += bad
            log.warning(
                "the event journal %s has %d line(s) that are not events (a write cut short by a kill or a "
                "full disk, or the file edited by hand); they are skipped, the rest is read",
                self.path,
                bad,
                extra={"path": str(self.path), "unreadable": bad},
            )
        return events if limit is None else events[max(0, len(events) - limit) :]

    @staticmethod
    def _read(path: Path) -> tuple[list[Event], int]:
        """The events of one file, and how many of its lines were not events."""
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return [], 0
        except OSError as exc:
            log.error("the event journal %s cannot be read (%s); its events are not shown", path, exc)
            return [], 0
        events, bad = [], 0
        for line in data.splitlines():
            if not line.strip():
                continue
            try:
                events.append(_DECODER.decode(line))
            except msgspec.DecodeError:
                bad += 1
        return events, bad

    # -- writing -------------------------------------------------------------------------------------------

    def add(self, event: Event) -> None:
        """Queue `event` (numbered by its store) for the next flush. Any thread; never blocks on the disk."""
        with self._lock:
            if len(self._pending) >= MAX_PENDING:
                self._pending.popleft()
                self.not_written += 1
            self._pending.append(event)

    def flush(self) -> bool:
        """Append what is queued; False when the write failed (logged, counted; the next flush tries again
        with what is queued then)."""
        with self._write_lock:
            with self._lock:
                batch = list(self._pending)
                self._pending.clear()
            if not batch:
                return True
            try:
                self._write(batch)
            except OSError as exc:
                self.not_written += len(batch)
                self.write_failures += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
                # Closing flushes what the failed write left in the file's buffer, which fails the same way:
                # that is this failure again, told (once a minute) by _warn, not a line per flush.
                self._close_file(after_failure=True)
                self._warn(exc, len(batch))
                return False
            self.written += len(batch)
            if self._error_lines.streak:
                log.warning(
                    "the event journal %s is written again, after %d failed write(s); %d event(s) in all "
                    "were not written",
                    self.path,
                    self._error_lines.streak,
                    self.not_written,
                )
                self._error_lines.clear()
            return True

    def close(self) -> None:
        """Flush what is queued and close the file (a later flush opens it again)."""
        with self._write_lock:
            self.flush()
            self._close_file()

    @property
    def pending(self) -> int:
        return len(self._pending)

    def stats(self) -> SinkStats:
        """The journal as an output in /state's `agent.sinks`: what it could not write reaches the SinkDrops
        metric and its alarm like any output's drops."""
        return SinkStats(
            name=SINK_NAME,
            delivered=self.written,
            dropped=self.not_written,
            errors=self.write_failures,
            pending=self.pending,
            last_error=self.last_error,
        )

    def _write(self, batch: Sequence[Event]) -> None:
        f = self._file
        if f is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            f = self._file = open(self.path, "ab")  # noqa: SIM115 - kept open between flushes
            if _ends_cut_short(self.path):
                # A kill cut the last line short: without a line end the first event written now would
                # join it and be skipped with it when read back.
                f.write(b"\n")
        # One write a flush: a kill leaves at most its last line cut short, which `load` skips.
        f.write(b"".join(_ENCODER.encode(e) + b"\n" for e in batch))
        f.flush()
        if f.tell() >= self.max_bytes:
            self._close_file()
            os.replace(self.path, self.previous)

    def _close_file(self, *, after_failure: bool = False) -> None:
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()  # the descriptor is released even when the flush inside it fails
            except OSError as exc:
                if not after_failure:
                    log.warning("the event journal %s could not be closed: %s", self.path, exc)

    def _warn(self, exc: OSError, count: int) -> None:
        if self._error_lines.due() is None:
            return
        log.error(
            "%d event(s) could not be written to the event journal %s (%s): they are shown until the agent "
            "stops, and missing from the Events page after its next start. Make room on its disk, or let "
            "the agent's user write there (%d not written so far)",
            count,
            self.path,
            exc,
            self.not_written,
            extra={"path": str(self.path), "not_written": self.not_written},
        )


def _ends_cut_short(path: Path) -> bool:
    """Whether the file's last byte is something other than a line end (it is not empty)."""
    with path.open("rb") as f:
        if f.seek(0, os.SEEK_END) == 0:
            return False
        f.seek(-1, os.SEEK_END)
        return f.read(1) != b"\n"
