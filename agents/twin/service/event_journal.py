"""The events page over a restart: the agent's events, appended to a file and read back at its next start.

The agent's `EventStore` is memory only. Without this, a restart (a deploy, a reboot, a crash and systemd
starting it again) leaves an operator who opens the Events page the next morning a list that begins at the
restart, and each session's count of the alarms raised in it at 0. With `[twin] events_file` set, every
event the store numbers is appended to that file as one JSON line, and the next start puts the newest
of them back in its store with their ids, so the page, its exports and the sessions read the
same before and after.

- **When it is written.** The store calls `add` on whatever thread makes the event, which must only hand it
  on; the agent's supervisor calls `flush` every round (half a second) and the stop calls it last. So a
  process killed outright loses at most its last round of events, and the run after it says so
  (`AgentService` reads the journal's last event: a run that stopped wrote `agent stopped` last).
- **Three pairs of files, one per part of the store.** The kinds that come in floods (`events.BULK_KINDS`:
  status, rejected, twin) go to `<stem>.bulk<suffix>` beside it (`events.bulk.jsonl`), the rare lifecycle
  kinds (`events.LIFECYCLE_KINDS`: calibration, agent, worker, broker) to `<stem>.lifecycle<suffix>`, the
  alarms to the file named: a flood of status events rotates only its own file, never the alarms before it
  out, and an alarm flood only the alarms' file, never the restarts and calibrations before it (the store
  keeps those in a reserve of their own). A file from before a split holds several parts, and is read as it
  is (each event goes where its kind does).
- **How big it gets.** Each file is renamed `<name>.1` once it passes its pair's size (replacing the one
  before) and a new one begun. Any part of a store may fill nearly all of it (an alarm flood with no status
  events leaves `capacity` alarms in it), so a pair's size is `[twin] events_capacity` of its longest lines
  (KEPT_LINE_BYTES, BULK_LINE_BYTES): just after a rename its `.1` alone holds that many, so each pair holds
  every event the store keeps of its kinds. The disk holds at most twice the three sizes and a flush more
  each: `capacity` x 5,000 bytes, 100 MB at the default 20,000 (500 MB at the largest, 100,000); the
  lifecycle pair, its kinds rare, is far from its size in practice.
- **How a start reads it.** Line by line, keeping the newest `limit` events of each of the store's parts
  (bulk, alarm, lifecycle: `events.EventStore`), so a start holds at most three times `limit` events
  however big the files are, and hands them over in id order.
- **What goes wrong.** A line cut short by a kill, or one that is not an event, is skipped when read back and
  counted (`unreadable`, one warning); the next write starts on a line of its own. A write that fails (disk
  full, permissions) is logged with what to do and its events counted (`not_written`); they stay in the
  store, and the next flush tries again with the events made since. What waits for a flush is bounded, in
  a queue per pair (a store's capacity each; the oldest of that pair go, counted), so a disk that stays
  broken or slow cannot grow the agent's memory, and a flood of status events waiting behind it pushes out
  only older bulk events, never the alarms waiting with them. Each pair's counts are an output's in /state
  (`agent.sinks`: `events_journal` for the file named, `events_journal_bulk` and
  `events_journal_lifecycle` for the others), so they reach CloudWatch's SinkDrops; its log lines name the
  file that failed.
- **A line longer than its pair's longest** (KEPT_LINE_BYTES, BULK_LINE_BYTES: a rejection's detail, a long
  arm id) would leave its pair's files fewer events than the store keeps, and a restart fewer back. Its
  message is cut to fit, ending in CUT_MARK, with `data.cut_from_bytes` the line's whole size: the event comes
  back, saying it was cut. If no start of the message fits, its data values are cut to CUT_DATA_CHARS first
  and the message only as much as it then must (not at all if it fits). The store keeps it whole until the
  agent stops.
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from operator import attrgetter
from pathlib import Path
from typing import BinaryIO

import msgspec

from twin.core.throttle import Throttle
from twin.output.sinks import SinkStats
from twin.service.events import (
    ALARM_PART,
    BULK_PART,
    DEFAULT_CAPACITY,
    LIFECYCLE_PART,
    Event,
    part_index,
)

log = logging.getLogger(__name__)

__all__ = [
    "BULK_LINE_BYTES",
    "BULK_SINK_NAME",
    "KEPT_LINE_BYTES",
    "LIFECYCLE_SINK_NAME",
    "SINK_NAME",
    "EventJournal",
]

# The pairs' names among the outputs of /state's `agent.sinks` and /metrics' `sink` label.
SINK_NAME = "events_journal"  # the file named: alarm
BULK_SINK_NAME = "events_journal_bulk"  # status, rejected, twin
LIFECYCLE_SINK_NAME = "events_journal_lifecycle"  # calibration, agent, worker, broker

# Each pair's files are renamed away once past its store's capacity times these: the most a line of its kinds
# takes. An alarm's line is about 530 to 760 bytes for a 7-character arm id (the id is in it three times, its
# text twice), up to about 940 for a 64-character one (IoT Core's longest); a status event's about 200 to
# 300, a twin event's up to about 500. Any part may fill nearly a whole store, so each pair needs `capacity`.
KEPT_LINE_BYTES = 1_000  # alarm; and calibration, agent, worker, broker: 20 MB a file at the default capacity
BULK_LINE_BYTES = 500  # status, rejected, twin: 10 MB a file at the default capacity
# A write that keeps failing is logged again at most this often (each flush would otherwise log).
WARN_EVERY_S = 60.0
# The end of a message cut to fit its pair's line (module doc), and the key of the line's whole size.
CUT_MARK = "… [cut]"
CUT_KEY = "cut_from_bytes"
# A data value of a line still too long once its message is cut keeps this many characters.
CUT_DATA_CHARS = 40

_DECODER = msgspec.json.Decoder(Event)
_ENCODER = msgspec.json.Encoder()
_ID = attrgetter("id")


def bulk_path(path: Path) -> Path:
    """Where a journal at `path` keeps the bulk kinds' events: `events.jsonl` -> `events.bulk.jsonl`."""
    return path.with_name(f"{path.stem}.bulk{path.suffix}")


def lifecycle_path(path: Path) -> Path:
    """Where a journal at `path` keeps the lifecycle kinds' events: `events.lifecycle.jsonl`."""
    return path.with_name(f"{path.stem}.lifecycle{path.suffix}")


class _Files:
    """One pair of the journal's files: `path`, appended to, renamed `<name>.1` once past `max_bytes`; the
    events waiting for it (`pending`, guarded by the journal's queue lock) and what became of them, as the
    output `name` reports them. The other fields are its journal's writing thread's."""

    def __init__(
        self, path: Path, max_bytes: int, *, name: str, line_bytes: int, clock: Callable[[], float]
    ) -> None:
        self.path = path
        self.line_bytes = line_bytes
        self.previous = path.with_name(path.name + ".1")
        self.max_bytes = max_bytes
        self.name = name
        self._file: BinaryIO | None = None
        self.pending: deque[Event] = deque()
        self.error_lines = Throttle(WARN_EVERY_S, clock=clock)
        self.written = 0
        self.write_failures = 0
        self.last_error = ""
        self.not_written = 0  # failed writes, and events pushed out of the waiting queue by newer ones

    def stats(self) -> SinkStats:
        return SinkStats(
            name=self.name,
            delivered=self.written,
            dropped=self.not_written,
            errors=self.write_failures,
            pending=len(self.pending),
            last_error=self.last_error,
        )

    def exist(self) -> bool:
        return self.path.exists() or self.previous.exists()

    def write(self, batch: Sequence[Event]) -> None:
        f = self._file
        if f is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            f = self._file = open(self.path, "ab")  # noqa: SIM115 - kept open between flushes
            if _ends_cut_short(self.path):
                # A kill cut the last line short: without a line end the first event written now would
                # join it and be skipped with it when read back.
                f.write(b"\n")
        # One write a flush: a kill leaves at most its last line cut short, which `load` skips.
        f.write(b"".join(_line(e, self.line_bytes) for e in batch))
        f.flush()
        if f.tell() >= self.max_bytes:
            self.close()
            os.replace(self.path, self.previous)

    def close(self, *, after_failure: bool = False) -> None:
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()  # the descriptor is released even when the flush inside it fails
            except OSError as exc:
                if not after_failure:
                    log.warning("the event journal %s could not be closed: %s", self.path, exc)


class EventJournal:
    """Appends events to `path` and reads them back (module doc). Thread-safe: `add` from any thread,
    `flush` from the agent's supervisor and its stop, one at a time."""

    def __init__(
        self,
        path: str | Path,
        *,
        capacity: int = DEFAULT_CAPACITY,
        max_bytes: int | None = None,
        max_pending: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """`capacity`: the store's (`[twin] events_capacity`), which sizes each pair's files (module doc)
        and its queue; `max_bytes`, when given, sizes every pair's files instead, `max_pending` their
        queues."""
        if capacity < 1:
            raise ValueError(f"an event journal's store holds at least one event, got capacity = {capacity}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"an event journal's files hold at least one byte, got max_bytes = {max_bytes}")
        self.path = Path(path)
        kept_bytes = capacity * KEPT_LINE_BYTES if max_bytes is None else max_bytes
        bulk_bytes = capacity * BULK_LINE_BYTES if max_bytes is None else max_bytes
        kept, bulk = KEPT_LINE_BYTES, BULK_LINE_BYTES
        self._kept = _Files(self.path, kept_bytes, name=SINK_NAME, line_bytes=kept, clock=clock)
        self._bulk = _Files(
            bulk_path(self.path), bulk_bytes, name=BULK_SINK_NAME, line_bytes=bulk, clock=clock
        )
        self._lifecycle = _Files(
            lifecycle_path(self.path), kept_bytes, name=LIFECYCLE_SINK_NAME, line_bytes=kept, clock=clock
        )
        # Every pair, indexed by the store's parts (events.part_index): where each event's kind goes.
        by_part = {BULK_PART: self._bulk, ALARM_PART: self._kept, LIFECYCLE_PART: self._lifecycle}
        self._pairs = tuple(by_part[part] for part in sorted(by_part))
        self._lock = threading.Lock()  # the pairs' queues
        # Events waiting for a flush, in each pair's queue: a store's worth. More only while writes fail or
        # are slow; then the oldest of that pair go, counted, so the memory held is at most twice the store's.
        self._max_pending = capacity if max_pending is None else max_pending
        # One flush at a time: a supervisor round still flushing as the stop closes must not interleave.
        self._write_lock = threading.RLock()
        self.unreadable = 0  # lines of the files read back that were not events

    # -- reading -------------------------------------------------------------------------------------------

    def load(self, limit: int | None = DEFAULT_CAPACITY) -> list[Event]:
        """The newest `limit` events of each part of a store (bulk, alarm, lifecycle; None: all of them) the
        files hold, in id order, as they were numbered; [] for none. A file that cannot be read is reported
        and left as it is (the next write appends to it)."""
        try:
            fresh = not any(files.exist() for files in self._pairs)
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
        parts: list[list[Event]] = [[], [], []]
        for path in itertools.chain.from_iterable((files.previous, files.path) for files in self._pairs):
            # A file from before a part had files of its own holds several kinds: each to its part.
            read, bad = self._read(path, limit)
            parts = [_newest((*held, *new), limit) for held, new in zip(parts, read, strict=True)]
            if bad:  # named by its own file: there are six
                self.unreadable += bad
                log.warning(
                    "the event journal %s has %d line(s) that are not events (a write cut short by a kill "
                    "or a full disk, or the file edited by hand); they are skipped, the rest is read",
                    path,
                    bad,
                    extra={"path": str(path), "unreadable": bad},
                )
        return _newest(itertools.chain.from_iterable(parts), None)

    @staticmethod
    def _read(path: Path, limit: int | None) -> tuple[list[deque[Event]], int]:
        """The newest `limit` events of each part of one file, read a line at a time, and how many of its
        lines were not events."""
        parts: list[deque[Event]] = [deque(maxlen=limit) for _ in range(3)]
        bad = 0
        try:
            with path.open("rb") as f:
                for line in f:
                    if not line.strip():
                        continue
                    try:
                        event = _DECODER.decode(line)
                    except msgspec.DecodeError:
                        bad += 1
                        continue
                    parts[part_index(event.kind)].append(event)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.error("the event journal %s cannot be read (%s); its events are not shown", path, exc)
        return parts, bad

    # -- writing -------------------------------------------------------------------------------------------

    def add(self, event: Event) -> None:
        """Queue `event` (numbered by its store) for the next flush. Any thread; never blocks on the disk."""
        files = self._pairs[part_index(event.kind)]
        with self._lock:
            # Each pair's own bound: a flood of status events behind a slow disk never pushes out an alarm.
            if len(files.pending) >= self._max_pending:
                files.pending.popleft()
                files.not_written += 1
            files.pending.append(event)

    def flush(self) -> bool:
        """Append what is queued; False when a write failed (logged, counted; the next flush tries again
        with what is queued then)."""
        with self._write_lock:
            ok = True
            for files in self._pairs:
                with self._lock:
                    batch = list(files.pending)
                    files.pending.clear()
                if batch:
                    ok = self._write(files, batch) and ok
            return ok

    def _write(self, files: _Files, batch: Sequence[Event]) -> bool:
        """Append `batch` to `files`; a failure logged (naming that file) and counted as that pair's."""
        try:
            files.write(batch)
        except OSError as exc:
            # Closing flushes what the failed write left in the file's buffer, which fails the same way:
            # that is this failure again, told (once a minute) by _warn, not a line per flush.
            files.close(after_failure=True)
            files.not_written += len(batch)
            files.write_failures += 1
            files.last_error = f"{type(exc).__name__}: {exc}"
            _warn(files, exc, len(batch))
            return False
        files.written += len(batch)
        if files.error_lines.streak:
            log.warning(
                "the event journal %s is written again, after %d failed write(s); %d event(s) in all "
                "were not written",
                files.path,
                files.error_lines.streak,
                files.not_written,
            )
            files.error_lines.clear()
        return True

    def close(self) -> None:
        """Flush what is queued and close every pair's files (a later flush opens them again)."""
        with self._write_lock:
            self.flush()
            for files in self._pairs:
                files.close()

    @property
    def pending(self) -> int:
        return sum(len(files.pending) for files in self._pairs)

    @property
    def written(self) -> int:
        return sum(files.written for files in self._pairs)

    @property
    def not_written(self) -> int:
        return sum(files.not_written for files in self._pairs)

    def sinks(self) -> tuple[SinkStats, SinkStats, SinkStats]:
        """The journal as three outputs in /state's `agent.sinks`, a pair each (`events_journal`, the file
        named; `events_journal_bulk`; `events_journal_lifecycle`): what any could not write reaches the
        SinkDrops metric and its alarm like any output's drops."""
        return self._kept.stats(), self._bulk.stats(), self._lifecycle.stats()


def _warn(files: _Files, exc: OSError, count: int) -> None:
    """A failed write of `files`, told at once and then once a minute, naming the file that failed."""
    if files.error_lines.due() is None:
        return
    log.error(
        "%d event(s) could not be written to the event journal %s (%s): they are shown until the agent "
        "stops, and missing from the Events page after its next start. Make room on its disk, or let "
        "the agent's user write there (%d not written to it so far)",
        count,
        files.path,
        exc,
        files.not_written,
        extra={"path": str(files.path), "not_written": files.not_written},
    )


def _newest(events: Iterable[Event], limit: int | None) -> list[Event]:
    """The newest `limit` of `events` (None: all), in id order, each id once."""
    by_id = sorted({e.id: e for e in events}.values(), key=_ID)
    return by_id if limit is None else by_id[max(0, len(by_id) - limit) :]


def _line(event: Event, limit: int) -> bytes:
    """`event` as one line of at most `limit` bytes (its end included): a longer one's message cut (module
    doc), and its data values too if that is not enough; longer still only for an arm id of such a size."""
    line = _ENCODER.encode(event) + b"\n"
    if len(line) <= limit:
        return line
    data = {**event.data, CUT_KEY: str(len(line))}
    cut = _cut_message(msgspec.structs.replace(event, data=data), event.message, limit)
    if cut is None:
        short = {k: v if k == CUT_KEY else v[:CUT_DATA_CHARS] for k, v in data.items()}
        cut = _cut_message(msgspec.structs.replace(event, data=short), event.message, limit)
    return cut if cut is not None else _ENCODER.encode(event) + b"\n"


def _cut_message(event: Event, message: str, limit: int) -> bytes | None:
    """The line of `event` with `message` whole if it fits in `limit`, else its longest start that does (None:
    none does). Once the data values are cut, a short message can fit whole and keeps its last characters."""
    whole = _ENCODER.encode(msgspec.structs.replace(event, message=message)) + b"\n"
    if len(whole) <= limit:
        return whole

    def encoded(keep: int) -> bytes:
        return _ENCODER.encode(msgspec.structs.replace(event, message=message[:keep] + CUT_MARK)) + b"\n"

    if len(encoded(0)) > limit:
        return None
    fits, over = 0, len(message)  # the longest start known to fit, the shortest known not to (whole does not)
    while over - fits > 1:
        mid = (fits + over) // 2
        fits, over = (mid, over) if len(encoded(mid)) <= limit else (fits, mid)
    return encoded(fits)


def _ends_cut_short(path: Path) -> bool:
    """Whether the file's last byte is something other than a line end (it is not empty)."""
    with path.open("rb") as f:
        if f.seek(0, os.SEEK_END) == 0:
            return False
        f.seek(-1, os.SEEK_END)
        return f.read(1) != b"\n"
