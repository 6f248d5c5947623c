"""The telemetry history in a process of its own, fed by the mirrors' batches.

    mirror's worker thread --its sinks stage: a row per decoded or rejected message--> HistoryFeed
      --the feed's own thread: the rows as columns, pickled, over a Unix socket-->
    history writer process: Arrow tables (history.telemetry_table_of) -> HistoryWriter -> Delta Lake
    agent --control pipe: stats, stop--> history writer process (HistoryProcess starts, watches, restarts it)

Why a process: turning rows into Arrow, encoding Parquet and committing cost about 18 % of a core at 1,000
arms, and on the mirrors' threads (and GIL) that work showed as the mirrors' latency (the p99 with history
on was five times that without). Here a mirror only appends a row to a deque; its feed's thread hands the
rows over every HAND_OFF_S; the writer process converts and commits with nothing of the mirror's to wait
for. A mirror's process no longer loads pyarrow and deltalake either.

Counting. Every row a mirror hands the feed is delivered over the socket, or dropped and counted when the
feed's queue is full (the writer process has been gone longer than the queue lasts). The writer process counts
the rows it received, committed and dropped (its write buffer, as before) in shared memory, so when it dies (a
crash in a native library, say) the agent knows how many rows it held and counts them as lost (but for the
commit it was in, which may have landed: the next writer asks the table, `_InDoubt`, or, at a stop, a process
started to ask it, `check_main`), starts it again, and the feeds connect to the new one and carry on; rows a
feed wrote to the socket of a writer that died before reading them show as the difference between the feeds'
delivered rows (counted in memory shared with the agent, so a worker started again keeps its count) and the
rows the writers received. Nothing else is lost: at shutdown every feed delivers what it holds, and the writer
commits it before it exits.

Once each. A worker that dies is started again and sent every message its last checkpoint does not count
(service.shards); some of their rows the dead feed had delivered. The mirror marks, after each batch, its
stream position in its feed (`HistoryFeed.mark`: once a batch, nothing per message); the feed's thread
hands over the rows up to the latest mark only, so a hand-over ends where a batch of the mirror ended, and
after it went through records the position it reached, with the rows handed up to there, in the memory it
shares with the agent (`HistoryLink.reached`). A hand-over is one message on the socket: a worker killed
in the middle of it leaves the writer a cut-off message, which it drops (EOF), so a batch reaches the writer
whole or not at all. The agent gives the new worker that position (`resume_point`): the messages sent again
before it skip history's stage, the later ones (their rows were still in the dead feed's queue) are written.
Rows the dead feed held for messages the checkpoint already counts are sent again by nobody, and those it
dropped before the position are not written again: both are counted lost at the restart (the dead worker's
count of its drops went with it), so rows written + rows lost = messages handled. A kill between a
hand-over going through and its record (a few bytecodes) has that one batch written twice.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import multiprocessing
import os
import pickle
import secrets
import signal
import socket
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Client, Connection, Listener, wait
from multiprocessing.context import SpawnContext, SpawnProcess
from multiprocessing.sharedctypes import SynchronizedArray
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from twin.core import heap
from twin.output import scratch
from twin.output.sinks import SinkStats

if TYPE_CHECKING:
    from twin.output.history import RejectedRow, WriterStats

log = logging.getLogger(__name__)

# A feed hands its rows over this often (rows wait for a commit anyway: every 10 s by default).
HAND_OFF_S = 0.05
# A feed that cannot reach the writer tries again after this long.
RECONNECT_S = 0.5
# Made beside the writer's socket when the agent stops with no writer running (it died, and the stop starts
# none again), or when the writer dies once the stop has begun: a closing feed then stops waiting for one, and
# what it holds is counted as not written.
NO_WRITER = "no-writer"
# The writer process must be up within this (Python, pyarrow, deltalake; the table opened on first commit).
START_TIMEOUT_S = 60.0
# Why a start ends at the agent's stop (the stop kills a writer being started: HistoryProcess._abandon_start).
ABANDONED = "start abandoned: the agent is stopping"
# How long the writer may take to answer the agent's request for its figures.
ASK_TIMEOUT_S = 10.0
# A writer that dies within this long of starting is started again after a growing pause.
QUICK_DEATH_S = 30.0
MAX_RESTART_PAUSE_S = 60.0
# At a stop, a commit in doubt that no writer is started again to check is asked of the table by a process
# started for it (`check_main`): it has what is left of the stop's timeout, and at least this long (a spawned
# Python, deltalake and one read of the table's log took 0.4-0.5 s on a local disk).
CHECK_MIN_S = 10.0
# A check told to stop (SIGTERM: an operator's kill, or systemd's stop of the unit, which reaches every
# process of it) answers within this long or ends without answering; so does a writer in the same check at its
# start (it holds no row yet). It only reads the table, so ending it leaves the table as it was; its rows
# count as not checked. A check stuck on a store that never answers otherwise held on for object_store's
# timeouts and retries, or for ever on a hung file system. An agent that was killed ends both at once: they
# watch its end of their control pipe (`_ask_table`).
CHECK_TERM_GRACE_S = 2.0
# The writer process runs this much nicer than the mirrors (os.nice; its threads, deltalake's included, and
# its maintenance process inherit it). Its commits are bursts of Parquet encoding every commit_every_s; at the
# same priority they took the mirrors' cores and showed as their p99. At 5 its scheduler weight is a third of
# a mirror's: on a host with a core to spare (1,000 arms here) it still gets all it needs; on a saturated one
# it falls behind first, and its lag and the feeds' bounded queues take that (docs/history.md; measured in
# docs/cost-per-message.md, "History's writer at a lower priority"). The default of [history] writer_nice.
WRITER_NICE = 5

# A rejected message is kept up to this many bytes (its whole length is stored too): HistorySettings' default,
# here so a mirror cuts the payload before it crosses the socket without loading pyarrow.
REJECTED_PAYLOAD_MAX_BYTES = 4096
# The history tables' names (twin.output.history takes them from here: this module must not load pyarrow,
# and the agent counts each table's commits by name).
TELEMETRY_TABLE = "telemetry"
REJECTED_TABLE = "rejected"

# The writer process's counters in shared memory (int64 each), written by it alone.
_RECEIVED, _REJECTED_RECEIVED, _COMMITTED, _REJECTED_COMMITTED, _DROPPED, _BUFFERED, _COMMITS = range(7)
_COUNTED = 7
# ... and the commit it is in: its table (0: none; 1 + its index in _TABLES), sequence number, rows, and the
# table's rows committed before it. Set before each append, cleared once the commit is counted; a writer that
# dies with it set may or may not have committed those rows, and the next writer asks the table (_InDoubt).
_IN_TABLE, _IN_SEQ, _IN_ROWS, _IN_BASE = range(_COUNTED, _COUNTED + 4)
_COUNTERS = _COUNTED + 4
# The tables, with the counter of each's commits.
_TABLES = (TELEMETRY_TABLE, REJECTED_TABLE)
_COMMITTED_OF = (_COMMITTED, _REJECTED_COMMITTED)


class _Counters(Protocol):
    """A writer's counters: the shared array, or the sums of the writers that ended."""

    def __getitem__(self, index: int, /) -> int: ...


def _read(counters: _Counters) -> int:
    """The rows a writer read from the feeds, by its counters."""
    return counters[_RECEIVED] + counters[_REJECTED_RECEIVED]


def _held(counters: _Counters) -> int:
    """The rows a writer read and had neither committed nor counted as dropped, by its counters."""
    kept = counters[_COMMITTED] + counters[_REJECTED_COMMITTED] + counters[_DROPPED]
    return max(0, _read(counters) - kept)


# One decoded message as the telemetry table keeps it: device, receive wall time, edge time (ms), units,
# the six decoded angles (JOINTS order), payload.
TelemetryRow = tuple[str, float, int, str, Sequence[float], bytes]


# What the writer says on a feed's connection once the connection is in its list (the feed waits for it).
_REGISTERED = b"listed"
REGISTER_TIMEOUT_S = 5.0

# Slots of the feeds' delivered counts: one per mirror (its shard's index), at most twin.workers' maximum.
FEED_SLOTS = 64
# Per slot, in `HistoryLink.progress`: where the slot's feeds have reached (the mirror's stream position
# every message before which has its row delivered or dropped, and the rows handed up to there, over every
# process of the slot) as two pairs and which of them holds it (a process killed while writing one pair
# leaves the other whole); the rows the agent counted lost when it started the slot's worker again; and of
# the rows handed up to where a restarted worker took up, those not delivered that it has counted so far.
_WHICH, _PAIRS, _LOST_AT_RESTART, _UNDELIVERED = 0, 1, 5, 6
_PROGRESS = 7


@dataclass(frozen=True)
class HistoryLink:
    """Where the mirrors find the history writer process: its socket and the key that admits them; and,
    in shared memory, the rows each mirror's feed has written to a writer's socket, by the mirror's slot.
    A worker started again takes up its slot's count where the dead one left it, so the agent's stop knows
    every row delivered, whichever process delivered it (`HistoryProcess.count_unread`)."""

    address: str
    authkey: bytes
    delivered: SynchronizedArray[int] | None = field(default=None, compare=False)
    # Where each slot's feeds have reached in their mirror's stream (`reached`), for a worker started again
    # to hand history only the rows not yet delivered (`HistoryFeed.mark`).
    progress: SynchronizedArray[int] | None = field(default=None, compare=False)

    @classmethod
    def new(cls, address: str, authkey: bytes, context: SpawnContext) -> HistoryLink:
        """A link with its shared counts, in memory the agent's processes share (made by `context`)."""
        return cls(
            address,
            authkey,
            context.Array("q", FEED_SLOTS, lock=False),
            context.Array("q", FEED_SLOTS * _PROGRESS, lock=False),
        )

    def reached(self, slot: int) -> tuple[int, int]:
        """(position, rows): every message of slot `slot`'s stream before `position` has had its row
        delivered to a writer (or dropped, counted); `rows` is how many rows its feeds were handed up to
        there, over every process of the slot. (0, 0) before any delivery."""
        progress = self.progress
        if progress is None:
            return 0, 0
        base = slot * _PROGRESS + _PAIRS + 2 * progress[slot * _PROGRESS + _WHICH]
        return progress[base], progress[base + 1]

    def record_reached(self, slot: int, position: int, rows: int) -> None:
        """The feed's thread of slot `slot`, after a delivery: the pair not in use, then the switch to it."""
        progress = self.progress
        if progress is None:
            return
        which = slot * _PROGRESS + _WHICH
        other = 1 - progress[which]
        base = slot * _PROGRESS + _PAIRS + 2 * other
        progress[base], progress[base + 1] = position, rows
        progress[which] = other

    def count_lost_at_restart(self, slot: int, rows: int) -> int:
        """The agent, starting slot `slot`'s worker again where the slot's feeds were handed `rows` rows in
        all: those not delivered (dropped by a full queue, or held by the dead feed for messages no one sends
        again) and not counted at an earlier restart are counted as lost, and returned."""
        progress, delivered = self.progress, self.delivered
        if progress is None or delivered is None:
            return 0
        undelivered = rows - delivered[slot]
        counted = slot * _PROGRESS + _UNDELIVERED
        lost = max(0, undelivered - progress[counted])
        progress[counted] = max(progress[counted], undelivered)
        progress[slot * _PROGRESS + _LOST_AT_RESTART] += lost
        return lost

    def lost_at_restarts(self) -> int:
        progress = self.progress
        if progress is None:
            return 0
        return sum(progress[_LOST_AT_RESTART::_PROGRESS])


@dataclass(frozen=True, slots=True)
class Resume:
    """Where a worker started again takes up history: the messages it is sent again before stream position
    `skip_to` had their rows delivered by the dead one (they are not handed to history again), and `rows`
    is how many rows the slot's feeds were handed up to where this one starts (`HistoryFeed.resume`)."""

    skip_to: int
    rows: int


def resume_point(link: HistoryLink, slot: int, *, taken: int, taken_rows: int, replay_from: int) -> Resume:
    """The agent, starting slot `slot`'s worker again from a checkpoint that counts `taken` messages (and
    `taken_rows` rows handed to history for them), then sending it its messages again from the one the dead
    worker knew as `replay_from` (later than `taken` when the agent no longer kept them all): where its
    history takes up. The rows handed for the messages before it that no feed delivered are counted as lost
    here, once: those the dead feed dropped (its queue was full; the count went with its process) and, when
    the checkpoint counts messages past where the dead feed reached, those it still held for them, which
    nobody sends again (the slot is then recorded as reached at the checkpoint)."""
    position, rows = link.reached(slot)
    if position >= taken:
        # Replayed messages are renumbered from `taken` on; the dead feed delivered up to `position`.
        resume = Resume(taken + max(0, position - replay_from), rows)
    else:
        resume = Resume(taken, max(rows, taken_rows))
    # Recorded in the new numbering at once (nothing of the slot runs yet): a worker that dies again before
    # its feed records a delivery of its own (in the skipped part of the replay, say) is then started from
    # this point, not from the dead one's position in numbers that no longer hold.
    link.record_reached(slot, resume.skip_to, resume.rows)
    lost = link.count_lost_at_restart(slot, resume.rows)
    if lost:
        log.error(
            "history: %d rows of messages worker %d had handled were dropped or still queued when it died, "
            "and are not sent again: lost",
            lost,
            slot,
            extra={"worker": slot, "history_rows_lost": lost},
        )
    return resume


@dataclass(frozen=True)
class _Batch:
    """What crosses the socket: a feed's telemetry rows as columns, and its rejected rows."""

    device_ids: tuple[str, ...]
    received_wall_s: tuple[float, ...]
    edge_ms: tuple[int, ...]
    units: tuple[str, ...]
    angles: tuple[float, ...]
    payloads: tuple[bytes, ...]
    rejected: tuple[RejectedRow, ...]

    @property
    def rows(self) -> int:
        return len(self.device_ids) + len(self.rejected)


def _batch_of(telemetry: list[TelemetryRow], rejected: list[RejectedRow]) -> _Batch:
    if telemetry:
        devices, walls, stamps, units, angles, payloads = zip(*telemetry, strict=True)
        flat = tuple(itertools.chain.from_iterable(angles))
    else:
        devices = walls = stamps = units = payloads = flat = ()
    return _Batch(devices, walls, stamps, units, flat, payloads, tuple(rejected))


# -------------------------------------------------------------------------------------------- the feed


class HistoryFeed:
    """A mirror's way to the history writer process (module doc). `telemetry()` and `rejected()` run on the
    mirror's worker thread and only append; the feed's thread connects, hands the rows over and reconnects
    after the writer was started again. `close()` delivers what is left, then disconnects."""

    name = "history"

    def __init__(self, link: HistoryLink, *, max_pending: int, payload_max_bytes: int, slot: int = 0) -> None:
        if link.delivered is not None and not 0 <= slot < len(link.delivered):
            raise ValueError(f"a history feed's slot is 0..{len(link.delivered) - 1}, not {slot}")
        self._link = link
        self._slot = slot
        self._max = max_pending
        self.payload_max_bytes = payload_max_bytes
        self._telemetry: deque[TelemetryRow] = deque()
        self._rejected: deque[RejectedRow] = deque()
        self._conn: Connection | None = None
        self._closing = threading.Event()
        # Held by whoever takes rows from the left of the queues: the feed's thread, and the mirror's when
        # it drops. Each queue's rows are numbered in the order they came (`_in`: written by the mirror's
        # thread only) and `_out` counts those that left (taken or dropped), so the feed's thread knows which
        # rows a mark covers.
        self._drop_lock = threading.Lock()
        self._telemetry_in = self._rejected_in = 0
        self._telemetry_out = self._rejected_out = 0
        # The mirror's last mark: the rows of each queue handed before it, and its stream position then.
        self._mark: tuple[int, int, int] | None = None
        # The rows this slot's feeds were handed before this one took over (a worker started again: resume).
        self._base = 0
        self._in_hand = 0  # the rows of the batch the feed's thread took and has not delivered yet
        self._delivered = 0
        self._dropped = 0
        self._errors = 0
        self._last_error = ""
        self._thread = threading.Thread(target=self._run, name="history-feed", daemon=True)
        self._thread.start()

    # -- the mirror's side ----------------------------------------------------------------------------

    def telemetry(self, row: TelemetryRow) -> None:
        self._telemetry_in += 1
        rows = self._telemetry
        rows.append(row)
        if len(rows) > self._max:
            self._drop(rows)

    def rejected(self, row: RejectedRow) -> None:
        self._rejected_in += 1
        rows = self._rejected
        rows.append(row)
        if len(rows) > self._max:
            self._drop(rows)

    def _drop(self, rows: deque[Any]) -> None:
        # The writer has been out of reach for longer than the queue lasts: the oldest rows go, counted.
        with self._drop_lock:
            gone = max(0, len(rows) - self._max)
            for _ in range(gone):
                rows.popleft()  # only holders of the lock take from the left
            self._dropped += gone
            if rows is self._telemetry:
                self._telemetry_out += gone
            else:
                self._rejected_out += gone

    def mark(self, position: int) -> None:
        """The mirror's thread, after a batch: every row of the messages before stream position `position`
        has been handed over. From the first mark on, the feed's thread delivers whole batches only (the rows
        up to the latest mark) and records, once they are delivered, the position they reach
        (`HistoryLink.reached`): a worker started again hands history no row a dead one delivered. A feed
        never marked delivers every row it holds."""
        self._mark = (self._telemetry_in, self._rejected_in, position)

    def resume(self, rows: int) -> None:
        """Before the first row: this slot's feeds were handed `rows` rows before this one takes over."""
        self._base = rows

    def stats(self) -> SinkStats:
        """As a sink's: rows delivered to the writer process, dropped, waiting (`skipped`: none; `pending`
        includes the batch the feed's thread holds). Read under the lock the feed's thread moves rows with,
        so a row is counted once: waiting, in hand or delivered."""
        with self._drop_lock:
            delivered, pending = self._delivered, len(self._telemetry) + len(self._rejected) + self._in_hand
        return SinkStats(
            name=self.name,
            delivered=delivered,
            dropped=self._dropped,
            errors=self._errors,
            pending=pending,
            last_error=self._last_error,
        )

    @property
    def handed(self) -> int:
        return self._telemetry_in + self._rejected_in

    @property
    def handed_in_all(self) -> int:
        """The rows this slot's feeds were handed, this one's and its predecessors' (`resume`)."""
        return self._base + self._telemetry_in + self._rejected_in

    def close(self, timeout: float = 30.0) -> None:
        """Deliver what is queued (until `timeout`), then disconnect. Idempotent."""
        self._closing.set()
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.error("history feed: %d rows not delivered within %.0f s", self.stats().pending, timeout)

    # -- the feed's thread ----------------------------------------------------------------------------

    def _run(self) -> None:
        batch: _Batch | None = None
        reached: tuple[int, int] | None = None
        while True:
            closing = self._closing.wait(HAND_OFF_S)
            if batch is None:
                batch, reached = self._take(everything=closing)
            if batch is not None and self._send(batch):
                if reached is not None:
                    self._link.record_reached(self._slot, *reached)
                batch = None
                continue
            if closing and batch is None and not self._telemetry and not self._rejected:
                break
            if batch is not None:
                if closing and Path(self._link.address).with_name(NO_WRITER).exists():
                    break  # none will come (HistoryProcess.stopping): its rows stay pending, counted
                # Not delivered (the writer is being started again): it waits, and the queue fills behind it.
                time.sleep(RECONNECT_S)
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def _take(self, *, everything: bool) -> tuple[_Batch | None, tuple[int, int] | None]:
        """The rows up to the mirror's latest mark (`everything`, or never marked: all there are), and the
        (position, rows handed in all) they reach once delivered (None: unknown, not recorded)."""
        mark = self._mark
        with self._drop_lock:
            if mark is None or everything:
                telemetry_count, rejected_count = len(self._telemetry), len(self._rejected)
            else:
                telemetry_count = mark[0] - self._telemetry_out
                rejected_count = mark[1] - self._rejected_out
            telemetry = _popped(self._telemetry, telemetry_count)
            rejected = _popped(self._rejected, rejected_count)
            self._telemetry_out += len(telemetry)
            self._rejected_out += len(rejected)
            # In hand as they leave the queues, under the lock `stats` reads them with: set after the batch
            # was built, a report in between saw the rows nowhere (a stress run's test caught it).
            self._in_hand = len(telemetry) + len(rejected)
        if not telemetry and not rejected:
            return None, None
        reached = None
        if mark is not None and self._telemetry_out >= mark[0] and self._rejected_out >= mark[1]:
            reached = (mark[2], self._base + mark[0] + mark[1])
        return _batch_of(telemetry, rejected), reached

    def _send(self, batch: _Batch) -> bool:
        """Hand `batch` over; False when the writer cannot be reached (the batch is kept and sent later: it
        never reached a writer, so it is not written twice)."""
        conn = self._conn
        try:
            if conn is None:
                conn = self._conn = Client(self._link.address, family="AF_UNIX", authkey=self._link.authkey)
                # Rows go only to a writer that has taken the connection into its list: the handshake ends
                # inside its accept(), before it lists the connection, and a stop in between read nothing of
                # it. A writer that does not say so in time (stopped, say) is out of reach for now.
                if not conn.poll(REGISTER_TIMEOUT_S) or conn.recv_bytes() != _REGISTERED:
                    raise OSError(
                        f"the history writer did not take the connection within {REGISTER_TIMEOUT_S} s"
                    )
            conn.send_bytes(pickle.dumps(batch, protocol=pickle.HIGHEST_PROTOCOL))
        except (OSError, EOFError, multiprocessing.AuthenticationError) as exc:
            if conn is not None:
                with contextlib.suppress(OSError):
                    conn.close()
            self._conn = None
            self._errors += 1
            self._last_error = f"history writer out of reach: {exc}"
            return False
        with self._drop_lock:  # delivered and no longer in hand at once, for `stats`
            self._delivered += batch.rows
            self._in_hand = 0
        shared = self._link.delivered
        if shared is not None:
            # This feed's thread is the slot's only writer while its process lives.
            shared[self._slot] += batch.rows
        return True


def _popped(rows: deque[Any], count: int) -> list[Any]:
    """The first `count` rows of `rows` (fewer when it holds fewer), taken off it."""
    popleft = rows.popleft
    return [popleft() for _ in range(min(count, len(rows)))]


# -------------------------------------------------------------------------------- the writer process


@dataclass(frozen=True, slots=True)
class _StatsRequest:
    pass


@dataclass(frozen=True, slots=True)
class _Stop:
    # What the agent's shutdown budget leaves the writer: the feeds' last rows and its last commit.
    timeout_s: float = 30.0


@dataclass(frozen=True, slots=True)
class _InDoubt:
    """A commit a writer that died was in, not counted: did writer `writer_id`'s `seq` land in `table`?"""

    writer_id: str
    table: str
    seq: int
    rows: int


@dataclass(frozen=True, slots=True)
class _Launch:
    """Who a new writer process commits as, and the commit in doubt it is to check first, if any."""

    writer_id: str
    in_doubt: _InDoubt | None = None
    # The agent's logging, as (its setup function, level): a spawned process starts with none, so its INFO
    # lines (maintenance) were lost and its warnings came as plain text, not the agent's JSON lines.
    log: tuple[Callable[[str], None], str] | None = None


@dataclass(frozen=True, slots=True)
class _Ready:
    pid: int
    # The answer about the _InDoubt commit the writer was given: None when there was none or the table could
    # not be read.
    landed: bool | None = None


@dataclass(frozen=True, slots=True)
class _Failed:
    message: str
    setting: bool  # a setting the writer cannot work with (the agent exits as for any configuration error)


class HistoryStartError(OSError):
    """The history writer process could not start; `setting`: because of a setting (`message` names it)."""

    def __init__(self, message: str, *, setting: bool = False) -> None:
        super().__init__(message)
        self.setting = setting


def writer_main(
    settings: dict[str, Any],
    link: HistoryLink,
    control: Connection,
    counters: SynchronizedArray[int],
    launch: _Launch | None = None,
) -> None:
    """The history writer process: a HistoryWriter (made from `settings`, HistorySettings' fields, and
    committing as `launch.writer_id`) fed by every mirror's HistoryFeed (module doc). It first checks
    `launch.in_doubt`. `settings["writer_nice"]`, if given, is how much nicer than the agent it runs
    (WRITER_NICE by default)."""
    # The agent stops it in order (the feeds first, then a _Stop), so a Ctrl-C or systemd's SIGTERM to the
    # process group must not cut its last commit short. But for its check of a commit in doubt, first: it
    # holds no row yet, and a check stuck on its store ends on SIGTERM (`_ask_table`), from now on.
    in_doubt = launch.in_doubt if launch is not None else None
    terminated = threading.Event()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN if in_doubt is None else _setting(terminated))
    if launch is not None and launch.log is not None:
        setup, level = launch.log
        setup(level)
    # Before deltalake loads (it reads them once): its allocator's settings for a process that commits every
    # few seconds for weeks (twin.core.heap says why); the maintenance process inherits them.
    heap.tune_deltalake_allocator()
    # Before any thread starts: Linux keeps a nice value per thread, and a new thread takes its creator's.
    settings = dict(settings)
    os.nice(settings.pop("writer_nice", WRITER_NICE))
    # pyarrow and deltalake load here only: neither the receiving process nor a mirror carries them.
    from twin.output.history import HistorySettings, HistoryWriter  # noqa: PLC0415

    try:
        writer = HistoryWriter(HistorySettings(**settings), writer_id=launch.writer_id if launch else None)
    except ValueError as exc:  # HistoryError: a setting
        control.send(_Failed(f"[history]: {exc}", setting=True))
        return
    landed = None
    if in_doubt is not None:
        answer = _ask_table(control, lambda: _landed(writer, in_doubt), terminated, what="history writer")
        if answer is None:
            os._exit(1)  # it holds no row yet; its reader may be stuck in native code for good
        landed = answer[0]
    writer.start()
    try:
        with contextlib.suppress(FileNotFoundError):
            Path(link.address).unlink()  # left by a writer that died
        listener = Listener(link.address, family="AF_UNIX", authkey=link.authkey)
    except Exception as exc:
        log.exception("history writer could not start")
        control.send(_Failed(f"history writer: {type(exc).__name__}: {exc}", setting=False))
        return
    control.send(_Ready(os.getpid(), landed))
    _Receiver(writer, listener, control, counters).run()


def _landed(writer: Any, in_doubt: _InDoubt | None) -> bool | None:
    """Whether the commit a dead writer was in landed; None when there was none or the table says nothing."""
    if in_doubt is None:
        return None
    try:
        return bool(writer.landed(in_doubt.table, in_doubt.writer_id, in_doubt.seq))
    except Exception:
        log.exception("history: could not read whether the last writer's last commit landed")
        return None


def check_main(
    settings: dict[str, Any],
    in_doubt: _InDoubt,
    control: Connection,
    log_setup: tuple[Callable[[str], None], str] | None = None,
) -> None:
    """The agent's check of a commit in doubt at its stop, in a process of its own (the agent's does not load
    deltalake): sends `_landed`'s answer for `in_doubt` (None: the table could not be read). On SIGTERM it
    ends within CHECK_TERM_GRACE_S, answered or not; when the agent is gone (killed), at once."""
    # A Ctrl-C to the process group must not cut it short (the agent kills it at its timeout).
    terminated = threading.Event()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _setting(terminated))
    if log_setup is not None:
        setup, level = log_setup
        setup(level)
    answer = _ask_table(control, lambda: _checked(settings, in_doubt), terminated, what="check")
    if answer is None:
        os._exit(1)  # the reader may be stuck in native code for good: nothing of the exit may wait for it
    with contextlib.suppress(OSError, ValueError):
        control.send(answer[0])


def _setting(event: threading.Event) -> Callable[[int, Any], None]:
    """A signal handler that sets `event` (SIGTERM's, for `_ask_table`)."""

    def handler(*_: object) -> None:
        event.set()

    return handler


def _ask_table(
    control: Connection, read: Callable[[], bool | None], terminated: threading.Event, *, what: str
) -> tuple[bool | None] | None:
    """`read()`'s answer (whether a commit in doubt landed), read on a thread of its own while this, the
    main thread, watches `terminated` (set by SIGTERM's handler, `_setting`) and the agent's end of `control`;
    None when the process is to end without an answer: a SIGTERM came and the read did not answer within
    CHECK_TERM_GRACE_S, or the agent hung up (killed: no one is left to answer, and no pipe or socket of a
    dead agent ever says more). The read only reads the table, so ending it leaves the table as it was.
    Python runs signal handlers on the main thread only, between bytecodes: with the read on a thread of its
    own, one stuck in deltalake's native code (a store that never answers) no longer holds them. SIGTERM is
    ignored from the return on."""
    wake, woken = os.pipe()
    os.set_blocking(woken, False)
    answer: list[bool | None] = []
    done = threading.Event()

    def run() -> None:
        try:
            answer.append(read())
        finally:
            done.set()  # before the wake-up: the main thread that reads that byte finds it set
            with contextlib.suppress(OSError):
                os.write(woken, b"r")

    # The wakeup fd: whichever thread the kernel gives the signal to, the main thread's wait returns.
    previous = signal.set_wakeup_fd(woken, warn_on_full_buffer=False)
    reader = threading.Thread(target=run, name="history-check-read", daemon=True)
    reader.start()
    try:
        gone = _wait_answer(done, control, wake, terminated)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.set_wakeup_fd(previous)
        os.close(wake)
        os.close(woken)
    if answer:
        return (answer[0],)
    log.error(
        "history: the %s's read of whether the last writer's last commit landed was stopped (%s) before the "
        "table answered; the table is as it was, and its rows count as not checked",
        what,
        "the agent is gone" if gone else "SIGTERM" if terminated.is_set() else "it failed",
    )
    return None


def _wait_answer(done: threading.Event, control: Connection, wake: int, terminated: threading.Event) -> bool:
    """Until the read is `done`, CHECK_TERM_GRACE_S after a SIGTERM, or the agent hangs up `control`: True
    for the last. (The agent sends nothing while a process reads: it asks a starting writer nothing
    (`HistoryProcess._ask`), a check has no request; so a message there is left for later, and only the
    hang-up counts.)"""
    watched: list[Any] = [wake, control]
    deadline: float | None = None
    while not done.is_set():
        if terminated.is_set() and deadline is None:
            deadline = time.monotonic() + CHECK_TERM_GRACE_S
        timeout = None if deadline is None else deadline - time.monotonic()
        if timeout is not None and timeout <= 0:
            break
        ready = wait(watched, timeout)
        if wake in ready:
            os.read(wake, 512)
        if control in ready:
            if _hung_up(control):
                return True
            watched.remove(control)
    return False


def _hung_up(conn: Connection) -> bool:
    """Whether the other end of `conn`, found readable, has closed (EOF), peeked so that a message waiting
    stays for its reader. False when that cannot be told (no socket; the agent's pipes are socket pairs)."""
    try:
        with socket.fromfd(conn.fileno(), socket.AF_UNIX, socket.SOCK_STREAM) as peer:
            return peer.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False  # a message, not EOF
    except ConnectionResetError:
        return True
    except OSError:
        return False


def _checked(settings: dict[str, Any], in_doubt: _InDoubt) -> bool | None:
    """`_landed` of a writer made from `settings` (None: the table could not be read)."""
    settings = dict(settings)
    settings.pop("writer_nice", None)
    from twin.output.history import HistorySettings, HistoryWriter  # noqa: PLC0415

    try:
        return _landed(HistoryWriter(HistorySettings(**settings)), in_doubt)
    except Exception:  # a setting the writer could not work with either: it never started to commit
        log.exception("history: could not check the last writer's last commit")
        return None


class _Receiver:
    """The writer process's loop: accept feeds, turn their batches into Arrow rows, answer the agent."""

    def __init__(
        self, writer: Any, listener: Listener, control: Connection, counters: SynchronizedArray[int]
    ) -> None:
        self.writer = writer
        self.listener = listener
        self.control = control
        self.counters = counters
        self.feeds: list[Connection] = []
        self._lock = threading.Lock()
        # The run loop and the committer thread (after each commit) both write the counters: one at a time,
        # each from the writer's figures read under this lock, so a later write never holds older figures.
        self._count_lock = threading.Lock()
        writer.before_append = self._appending
        writer.on_commit = self._committed
        self._closed = False
        self._stop_timeout_s = 30.0
        threading.Thread(target=self._accept, name="history-accept", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn = self.listener.accept()
            except Exception:  # closed at the end, or a caller without the key (AuthenticationError)
                if self._closed:
                    return
                continue
            with self._lock:
                self.feeds.append(conn)
            # The feed sends nothing before this (HistoryFeed._send): what it sends, a stop's `_finish` reads.
            with contextlib.suppress(OSError):
                conn.send_bytes(_REGISTERED)

    def run(self) -> None:
        while True:
            with self._lock:
                feeds = list(self.feeds)
            for ready in wait([self.control, *feeds], timeout=0.2):
                if ready is self.control:
                    if not self._answer():
                        self._finish()
                        return
                    continue
                assert isinstance(ready, Connection)
                try:
                    batch = pickle.loads(ready.recv_bytes())
                except (EOFError, OSError):
                    self._forget(ready)
                    continue
                self._write(batch, TELEMETRY_TABLE, REJECTED_TABLE)
            self._count()

    def _write(self, batch: _Batch, telemetry_table: str, rejected_table: str) -> None:
        from twin.output.history import rejected_table_of, telemetry_table_of  # noqa: PLC0415

        if batch.device_ids:
            self.counters[_RECEIVED] += len(batch.device_ids)
            try:
                rows, slow = telemetry_table_of(
                    device_ids=batch.device_ids,
                    received_wall_s=batch.received_wall_s,
                    edge_ms=batch.edge_ms,
                    units=batch.units,
                    angles=batch.angles,
                    payloads=batch.payloads,
                )
            except Exception as exc:
                log.exception("history: %d rows could not be converted", len(batch.device_ids))
                self.writer.count_conversion(
                    lost_rows=len(batch.device_ids), error=f"{type(exc).__name__}: {exc}"
                )
            else:
                if slow:
                    self.writer.count_conversion(slow=True)
                self.writer.add(telemetry_table, rows)
        if batch.rejected:
            self.counters[_REJECTED_RECEIVED] += len(batch.rejected)
            self.writer.add(rejected_table, rejected_table_of(batch.rejected))

    def _count(self) -> WriterFigures:
        """The writer's figures now, written to the shared counters (what the agent reads if this process
        dies) before anyone is told them: an answer never runs ahead of the counters. (Two reads of the
        writer's stats, one for each, could straddle a commit on its thread: the agent was then told 10 rows
        committed while the counters, read after a crash, still said 5.)"""
        with self._count_lock:
            figures = _figures_of(self.writer.stats(), self.writer.buffered_rows())
            counters = self.counters
            counters[_COMMITTED] = figures.rows_committed
            counters[_REJECTED_COMMITTED] = figures.rejected_rows_committed
            counters[_DROPPED] = figures.rows_dropped
            counters[_BUFFERED] = figures.rows_buffered
            counters[_COMMITS] = figures.commits
        return figures

    def _appending(self, table: str, seq: int, rows: int, committed: int) -> None:
        """The commit the writer is about to make, recorded for the agent in case this process dies in it
        (the table last: a reader that finds it set finds the rest written)."""
        counters = self.counters
        counters[_IN_SEQ], counters[_IN_ROWS], counters[_IN_BASE] = seq, rows, committed
        counters[_IN_TABLE] = 1 + _TABLES.index(table)

    def _committed(self) -> None:
        """After a commit: counted, then no longer in doubt (dying between the two leaves it counted and
        still recorded; the agent sees the count has it: `_in_doubt`)."""
        self._count()
        self.counters[_IN_TABLE] = 0

    def _answer(self) -> bool:
        """One request of the agent; False to stop."""
        try:
            request = self.control.recv()
        except (EOFError, OSError):
            return False  # the agent is gone
        if isinstance(request, _Stop):
            self._stop_timeout_s = request.timeout_s
            return False
        figures = self._count()
        with contextlib.suppress(OSError, ValueError):
            self.control.send(figures)
        return True

    def _forget(self, conn: Connection) -> None:
        with self._lock:
            if conn in self.feeds:
                self.feeds.remove(conn)
        conn.close()

    def _finish(self) -> None:
        """Read what the feeds still send until every one has hung up (they close after delivering), then
        commit."""
        started = time.monotonic()
        budget = self._stop_timeout_s
        # The agent stops the writer after every mirror has closed its feed, so what the sockets hold is all
        # there is: read it to the end, for up to half the budget (the rest is the last commit's). A fixed 5 s
        # could end first on a saturated host, where this writer runs nicer than everything else, and what it
        # left in the sockets reached no table (now the agent counts such rows at its stop: count_unread).
        deadline = started + budget / 2.0
        while time.monotonic() < deadline:
            with self._lock:
                feeds = list(self.feeds)
            if not feeds:
                break
            for ready in wait(feeds, timeout=0.2):
                assert isinstance(ready, Connection)
                try:
                    self._write(pickle.loads(ready.recv_bytes()), TELEMETRY_TABLE, REJECTED_TABLE)
                except (EOFError, OSError):
                    self._forget(ready)
        with self._lock:
            if self.feeds:
                log.error(
                    "history writer: %d feed(s) still sending after %.0f s of the stop; what they had not "
                    "sent is not written",
                    len(self.feeds),
                    budget / 2.0,
                )
        self._closed = True
        self.listener.close()
        # Retrying the last commit for what is left of the budget, less a moment for the answer: the agent
        # kills a writer that has not answered by then.
        self.writer.close(timeout=max(1.0, budget - (time.monotonic() - started) - 2.0))
        figures = self._count()
        with contextlib.suppress(OSError, ValueError):
            self.control.send(figures)


# ------------------------------------------------------------------------------------- the agent's side


@dataclass(frozen=True)
class WriterFigures:
    """What the writer process tells the agent of its HistoryWriter (plain values: the agent's process must
    not load pyarrow to read them)."""

    rows_committed: int = 0
    rejected_rows_committed: int = 0
    commits: int = 0
    commit_failures: int = 0
    rows_dropped: int = 0  # its write buffer was full, or a chunk could not be converted
    rows_buffered: int = 0
    maintenance_runs: int = 0
    maintenance_failures: int = 0
    rows_expired: int = 0  # deleted by maintenance for being older than keep_days
    log_entries_set_aside: int = 0  # newest log entries found empty and moved aside (TableStats)
    storage_ok: bool | None = None  # None: no commit attempted yet (WriterStats)
    last_error: str = ""
    # How long the oldest row not yet written has waited (0: none waits); it grows while commits fail.
    lag_s: float = 0.0


def _figures_of(stats: WriterStats, buffered: int) -> WriterFigures:
    tables = stats.tables
    return WriterFigures(
        rows_committed=tables[TELEMETRY_TABLE].rows_committed,
        rejected_rows_committed=tables[REJECTED_TABLE].rows_committed,
        commits=tables[TELEMETRY_TABLE].commits,
        commit_failures=sum(t.commit_failures for t in tables.values()),
        rows_dropped=sum(t.rows_dropped for t in tables.values()) + stats.rows_lost_in_conversion,
        rows_buffered=buffered,
        maintenance_runs=stats.maintenance_runs,
        maintenance_failures=stats.maintenance_failures,
        rows_expired=stats.rows_expired,
        log_entries_set_aside=sum(t.log_entries_set_aside for t in tables.values()),
        storage_ok=stats.storage_ok,
        last_error=stats.last_error,
        lag_s=stats.lag_s,
    )


@dataclass(frozen=True)
class HistoryFigures:
    """The writer process's figures for /state, over every process the agent started."""

    stats: WriterFigures | None
    pid: int | None
    restarts: int
    rows_received: int
    rows_lost: int

    @property
    def rows_not_written(self) -> int:
        """As `HistoryState.rows_not_written`: the writer's drops plus the rows lost."""
        return (self.stats.rows_dropped if self.stats is not None else 0) + self.rows_lost


class HistoryProcess:
    """The agent's handle on the history writer process: starts it (and its socket), answers for it in
    /state, starts it again when it died (counting the rows it held), stops it last."""

    def __init__(
        self,
        settings: dict[str, Any],
        context: SpawnContext,
        log: tuple[Callable[[str], None], str] | None = None,
    ) -> None:
        self.settings = settings
        self._ctx = context
        # The agent's logging for the writer process (_Launch.log): a module-level function, so it pickles.
        self._log = log
        # What the writer process runs (tests swap in one that dies at a chosen point), and what the check of
        # a commit in doubt at the stop runs.
        self.target: Callable[..., None] = writer_main
        self.check_target: Callable[..., None] = check_main
        # Named for this process, so an agent started after a kill of this one removes it (output.scratch).
        self._dir = scratch.owned_tempdir("twin-history-")
        self.link = HistoryLink.new(str(self._dir / "writer.sock"), secrets.token_bytes(32), context)
        self._counters: SynchronizedArray[int] = context.Array("q", _COUNTERS, lock=False)
        self._process: SpawnProcess | None = None
        self._control: Connection | None = None
        # The control pipe's users, one at a time, and the start's state below. A launch holds it only to
        # start the process and to take its answer, never while it waits for that (up to START_TIMEOUT_S):
        # the agent's stop, which needs it, would have waited as long on top of its budget.
        self._lock = threading.Lock()
        # A launch waits for the writer's first word (its control pipe is the launch's until then); and the
        # stop killed that writer, abandoning its start (`_abandon_start`).
        self._starting = False
        self._abandoned = False
        self.pid: int | None = None
        self.started_at = 0.0
        self.restarts = 0
        # The writer processes that died once running, and the last one's exit code and the rows it lost: the
        # agent makes an event of each (the Events page explains a hole in a session's history, as for a
        # worker). Not a start that failed before it was ready: retried up to once a minute while a store is
        # out of reach, each would be an event, and a weekend of them pushed every other lifecycle event out.
        self.exits = 0
        self.last_exit: tuple[int | None, int] = (None, 0)
        self._ran = False  # the current process said it was ready
        self._restart_at: float | None = None
        # Over the processes that ended: what they received, committed and dropped, and the rows they held
        # when they died (the figures of /state run on across restarts).
        self._before = dict.fromkeys(range(_COUNTED), 0)
        self._rows_lost = 0
        # The id the current writer commits as (new for each process), and the commit a dead one was in that
        # the next one is to check (counted as neither written nor lost until then).
        self.writer_id = ""
        self._in_doubt: _InDoubt | None = None
        # The rows of the commit the writer was in when it ended during the stop without answering it, which
        # the table says landed: among its counters' held rows, but written (`unwritten_rows`).
        self._written_at_stop = 0
        self._stopped = False
        # From the stop's start: waits for the writer to exit, then tells the feeds none will come (stopping).
        self._watch: threading.Thread | None = None
        self._last: WriterFigures | None = None
        self._last_at = 0.0  # when _last was answered (time.monotonic)
        self._last_own = False  # _last is the current writer's answer (not an earlier writer's)
        self._stop_answered = False

    def launch(self) -> None:
        """Start the writer process and wait until it listens; HistoryStartError when it cannot (`setting`:
        because of a setting), did not say so within START_TIMEOUT_S (it is killed), or the agent's stop
        began (none is started, and one being started is killed: `_abandon_start`)."""
        with self._lock:
            if self._stopped:
                raise HistoryStartError(ABANDONED)
            if self._control is not None:
                self._control.close()  # a dead writer's
            for i in range(_COUNTERS):
                self._counters[i] = 0
            self.writer_id = f"so101-twin-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
            control, child = self._ctx.Pipe()
            process = self._ctx.Process(
                target=self.target,
                args=(
                    self.settings,
                    self.link,
                    child,
                    self._counters,
                    _Launch(self.writer_id, self._in_doubt, self._log),
                ),
                name="twin-history-writer",
            )
            process.start()
            child.close()
            self._process, self._control = process, control
            self.started_at = time.monotonic()
            self._starting, self._last_own = True, False
        hello = self._hello(process, control)
        with self._lock:
            self._starting = False
            if not self._abandoned and isinstance(hello, _Ready):
                self.pid = hello.pid
                self._ran = True
                self._settle(hello.landed)
                return
        if self._abandoned:  # killed by the stop, which counts what it held: nothing of it is left to do here
            control.close()  # the stop left it to this launch, which was reading it
            raise HistoryStartError(ABANDONED)
        process.join(5.0)
        if isinstance(hello, _Failed):
            raise HistoryStartError(hello.message, setting=hello.setting)
        raise HistoryStartError(
            f"the history writer exited while starting (exit code {process.exitcode}); its log lines above "
            "say why"
        )

    @staticmethod
    def _hello(process: SpawnProcess, control: Connection) -> _Ready | _Failed | None:
        """The starting writer's first word on `control`; None when it exited first (or was killed by the
        stop). One that says nothing within START_TIMEOUT_S is killed (a _Failed that says so): left running,
        it looked alive to the supervisor, which then never started another."""
        try:
            if control.poll(START_TIMEOUT_S):
                hello: _Ready | _Failed = control.recv()
                return hello
        except (EOFError, OSError):
            return None
        process.kill()
        process.join(5.0)
        message = f"the history writer did not start within {START_TIMEOUT_S:.0f} s; killed"
        return _Failed(message, setting=False)

    def _doubt(self) -> _InDoubt | None:
        """The commit a writer that died was in and had not counted, by its counters."""
        counters = self._counters
        code = counters[_IN_TABLE]
        if not 1 <= code <= len(_TABLES):
            return None
        if counters[_COMMITTED_OF[code - 1]] >= counters[_IN_BASE] + counters[_IN_ROWS]:
            return None  # it died after counting the commit, before clearing the record
        return _InDoubt(self.writer_id, _TABLES[code - 1], counters[_IN_SEQ], counters[_IN_ROWS])

    def _settle(self, landed: bool | None) -> None:
        """The dead writer's commit in doubt, as the new writer found it: written, or lost."""
        doubt, self._in_doubt = self._in_doubt, None
        if doubt is None:
            return
        if landed:
            self._count_landed(doubt, "died", "written, not lost")
            return
        self._rows_lost += doubt.rows
        log.error(
            "the last commit of the history writer that died (%d rows to %s) %s: counted as lost",
            doubt.rows,
            doubt.table,
            "did not land" if landed is False else "could not be checked",
            extra={"history_rows_lost": doubt.rows},
        )

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.is_alive()

    def figures(self) -> HistoryFigures:
        """The writer's figures since the agent started, over every writer process: the current one's asked
        of it (its last known while it is being started again), plus those of the ones that ended."""
        stats = self._ask()
        if stats is None and self._last is not None:
            # The writer is not answering (being started again): its rows wait in the feeds, so history's
            # lag keeps growing from what it last said.
            stats = dataclasses.replace(self._last, lag_s=self._last.lag_s + time.monotonic() - self._last_at)
        before = self._before
        dead = self._restart_at is not None
        if stats is not None and (self.restarts or dead or self._written_at_stop):
            # While a dead writer waits to be started again, or the next one starts (not answered yet), the
            # dead one's counts are in `before` already: its last answer (`stats`) gives the rest, not these.
            own = stats if self._last_own and not dead else WriterFigures()
            stats = dataclasses.replace(
                stats,
                rows_committed=own.rows_committed + before[_COMMITTED],
                rejected_rows_committed=own.rejected_rows_committed + before[_REJECTED_COMMITTED],
                commits=own.commits + before[_COMMITS],
                rows_dropped=own.rows_dropped + before[_DROPPED],
            )
        return HistoryFigures(
            stats=stats,
            pid=self.pid if self.alive else None,
            restarts=self.restarts,
            rows_received=self._received(),
            rows_lost=self._rows_lost + self.link.lost_at_restarts(),
        )

    def _received(self) -> int:
        """The rows every writer process read from the feeds, all told."""
        received = _read(self._before)
        if self._restart_at is None:  # else the dead writer's counters are in `before` already
            received += _read(self._counters)
        return received

    def delivered(self) -> int:
        """The rows every feed wrote to a writer's socket, all told (the link's shared counts: those of
        worker processes that ended, or were started again, included)."""
        shared = self.link.delivered
        return sum(shared[:]) if shared is not None else 0

    def count_unread(self) -> int:
        """After `stop`, once every feed has closed: the rows delivered that no writer read, left in the
        socket of one that died or of the last one after it stopped reading. They are counted as lost
        (`rows_lost`) and returned. Called once, by the agent's stop. (A worker killed between writing a
        batch and counting it leaves those rows uncounted: fewer unread, never more.)"""
        unread = max(0, self.delivered() - self._received())
        self._rows_lost += unread
        return unread

    def _ask(self) -> WriterFigures | None:
        with self._lock:
            conn = self._control
            if conn is None or self._starting or not self.alive:
                return None
            try:
                conn.send(_StatsRequest())
                if not conn.poll(ASK_TIMEOUT_S):
                    log.warning("the history writer did not answer within %.0f s", ASK_TIMEOUT_S)
                    return None
                stats: WriterFigures = conn.recv()
            except (EOFError, OSError, ValueError):
                return None
            self._last, self._last_at, self._last_own = stats, time.monotonic(), True
            return stats

    def supervise(self) -> None:
        """Called every half second while the agent runs: start a dead writer again, counting what it held."""
        process = self._process
        if process is None or process.is_alive() or self._stopped:
            return
        now = time.monotonic()
        if self._restart_at is None:
            self._restart_at = self._count_dead(process.exitcode, now)
        if now < self._restart_at:
            return
        self._restart_at = None
        self.restarts += 1
        try:
            self.launch()  # holds the lock only while it starts the process, not while it waits for it
        except HistoryStartError as exc:
            log.log(
                logging.WARNING if self._stopped else logging.ERROR,
                "the history writer could not be started again: %s",
                exc,
            )
            return
        log.info("history writer running again", extra={"pid": self.pid})

    def _count_dead(self, exitcode: int | None, now: float) -> float:
        """A writer that died: what it held is lost, but a commit it was in, which the next writer checks.
        Returns when to start it again."""
        counters = self._counters
        held = _held(counters)
        doubt = self._doubt()
        doubtful = min(doubt.rows, held) if doubt is not None else 0
        for i in range(_COUNTED):
            self._before[i] += counters[i]
        self._rows_lost += held - doubtful
        if self._ran:
            self.exits += 1
            self.last_exit = (exitcode, held - doubtful)
        self._ran = False
        # A writer that never got as far as committing leaves an earlier writer's commit in doubt as it was.
        if doubt is not None and doubtful:
            self._settle(None)  # (an older one would have been checked by the writer that made this commit)
            self._in_doubt = dataclasses.replace(doubt, rows=doubtful)
        quick = now - self.started_at < QUICK_DEATH_S
        pause = min(MAX_RESTART_PAUSE_S, 2.0 ** min(self.restarts, 6)) if quick else 0.0
        log.error(
            "history writer exited (code %s) holding %d rows not yet written, lost%s; starting it again%s",
            exitcode,
            held - doubtful,
            f" (and {doubtful} in a commit the next writer checks)" if doubtful else "",
            f" in {pause:.0f} s" if pause else "",
            extra={"exit_code": exitcode, "history_rows_lost": held - doubtful},
        )
        return now + pause

    def unwritten_rows(self) -> int:
        """After `stop`: the rows the writer could not commit (its figures at the end), or, when it did not
        answer in time, every row it received and had neither committed nor counted as dropped."""
        if self._stop_answered and self._last is not None:
            return self._last.rows_buffered
        if self._restart_at is not None:
            return 0  # it died before the stop: what it held is counted in rows_lost already
        return _held(self._counters) - self._written_at_stop

    def stopping(self) -> None:
        """The agent's stop begins, before it closes the mirrors' feeds: no writer is started again from now
        on. With none running (one died, and waits out its restart pause, say), the feeds are told so
        (NO_WRITER), so their close does not wait the whole shutdown budget for a writer that will not come;
        what they hold is counted as not written, as at the end of that budget. With one running, they are
        told the moment it exits: it may die while they close, and the supervisor that would notice is gone.
        (A writer that exits at the end of a stop that went well is told of too, but by then every feed has
        closed or been given up at the budget, its rows counted: the counts stay as they were.)"""
        self._abandon_start()
        process = self._process
        if process is None or not process.is_alive():
            self._no_writer()
        elif self._watch is None:
            # Watched here, not guessed at in the feeds: one that cannot connect cannot tell a writer dead for
            # good from one being started again, and only this process holds the writer's exit.
            self._watch = threading.Thread(
                target=self._watch_writer, args=(process,), name="history-writer-watch", daemon=True
            )
            self._watch.start()

    def _abandon_start(self) -> bool:
        """The stop begins: no writer is started from now on, and one being started (a restart) is killed, its
        start abandoned: waiting for it (up to START_TIMEOUT_S) would have gone past the stop's budget and the
        unit's stop timeout. It has read no row unless it said it was ready just now; what it read is counted
        by its counters as a writer's that ended in the stop, and the commit in doubt it was to check is asked
        of the table by the stop (`_settle_at_stop`). True when a start was abandoned (now or before)."""
        with self._lock:
            self._stopped = True
            if self._starting and not self._abandoned and self._process is not None:
                self._abandoned = True
                log.warning("history writer (pid %s): %s; killed", self._process.pid, ABANDONED)
                self._process.kill()
            return self._abandoned

    def _watch_writer(self, process: SpawnProcess) -> None:
        """The stop's watch on the writer: it ends with the writer process (stop() sees to that)."""
        wait([process.sentinel])
        self._no_writer()

    def _no_writer(self) -> None:
        # Suppressed: after stop() removed the directory there is no feed left to tell.
        with contextlib.suppress(OSError):
            (self._dir / NO_WRITER).touch()

    def stop(self, timeout: float = 30.0) -> None:
        """After the mirrors have closed their feeds: the writer commits what it holds (retrying for at most
        `timeout` seconds), then exits; one that has not answered by then is killed. A commit in doubt that no
        writer will check is asked of the table last (`_settle_at_stop`)."""
        deadline = time.monotonic() + timeout
        abandoned = self._abandon_start()
        process, conn = self._process, self._control
        if not abandoned and process is not None and conn is not None and process.is_alive():
            with self._lock:
                try:
                    conn.send(_Stop(timeout_s=timeout))
                    if conn.poll(timeout):
                        self._last, self._last_at = conn.recv(), time.monotonic()
                        self._stop_answered = self._last_own = True
                except (EOFError, OSError, ValueError):
                    pass
        if process is not None:
            process.join(5.0 if self._stop_answered else 1.0)
            if process.is_alive():
                log.error("the history writer did not stop in time; killing it")
                process.kill()
                process.join(5.0)
        if self._watch is not None and process is not None and not process.is_alive():
            self._watch.join(5.0)  # it has seen the exit: NO_WRITER is made before the directory goes
        if conn is not None and not abandoned:  # else the launch's until it returns (it is woken by the kill)
            conn.close()
        self._settle_at_stop(process, deadline)
        scratch.remove(self._dir)

    def _settle_at_stop(self, process: SpawnProcess | None, deadline: float) -> None:
        """The commits in doubt no writer is started again to check, asked of the table here: a dead writer's
        (the agent stopped before the next one started), and the one the writer was in when it ended during
        the stop without answering (killed in its last commit, say). Counted as written if it landed; as lost
        (not written, for the last one) if it did not or could not be checked."""
        own = None
        if process is not None and not self._stop_answered and self._restart_at is None:
            own = self._doubt()
            rows = min(own.rows, _held(self._counters)) if own is not None else 0
            own = dataclasses.replace(own, rows=rows) if own is not None and rows else None
        if self._in_doubt is not None:
            self._settle(self._check(self._in_doubt, deadline))
        if own is None:
            return
        landed = self._check(own, deadline)
        if landed:
            self._count_landed(own, "ended in the stop", "written")
            self._written_at_stop += own.rows
            return
        log.error(
            "the last commit of the history writer that ended in the stop (%d rows to %s) %s: counted as not "
            "written",
            own.rows,
            own.table,
            "did not land" if landed is False else "could not be checked",
        )

    def _count_landed(self, doubt: _InDoubt, how: str, counted: str) -> None:
        """A dead writer's commit in doubt that the table says landed: its rows and commit count as written
        (`how` it ended, and what its rows are `counted` as, for the log)."""
        index = _TABLES.index(doubt.table)
        self._before[_COMMITTED_OF[index]] += doubt.rows
        self._before[_COMMITS] += index == 0
        log.info(
            "the history writer that %s had committed its last %d rows to %s: %s",
            how,
            doubt.rows,
            doubt.table,
            counted,
            extra={"history_rows_committed_before_death": doubt.rows},
        )

    def _check(self, doubt: _InDoubt, deadline: float) -> bool | None:
        """Whether the commit in doubt landed, asked of a process started for it (`check_target`), which has
        until `deadline` and at least CHECK_MIN_S; None when it could not say."""
        timeout = max(CHECK_MIN_S, deadline - time.monotonic())
        control, child = self._ctx.Pipe()
        process = self._ctx.Process(
            target=self.check_target, args=(self.settings, doubt, child, self._log), name="twin-history-check"
        )
        try:
            process.start()
        except Exception:
            log.exception("history: the check of the last writer's last commit could not be started")
            control.close()
            child.close()
            return None
        child.close()
        answer = None
        try:
            if control.poll(timeout):
                answer = control.recv()
            else:
                log.error("history: the check of the last writer's last commit took over %.0f s", timeout)
        except (EOFError, OSError):
            pass  # it died first: nothing said
        finally:
            control.close()
            process.join(1.0)
            if process.is_alive():
                process.kill()
                process.join(5.0)
        return answer if isinstance(answer, bool) else None


__all__ = [
    "REJECTED_PAYLOAD_MAX_BYTES",
    "REJECTED_TABLE",
    "TELEMETRY_TABLE",
    "WRITER_NICE",
    "HistoryFeed",
    "HistoryFigures",
    "HistoryLink",
    "HistoryProcess",
    "HistoryStartError",
    "Resume",
    "TelemetryRow",
    "WriterFigures",
    "resume_point",
    "writer_main",
]
