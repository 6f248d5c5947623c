"""The twin's events: what an operator wants to see happen, kept in a bounded store with ids and times.

An event is one line of the console's Events page: a device changing status (ONLINE, STALE, OFFLINE), a servo
alarm changing state, telemetry rejected (with its reason), the broker connection going down or up, a worker
process exiting or coming back. Logs have all of these too, but a log is not something an operator can filter
by device, tail live in a browser and export.

`Event` is a small frozen msgspec Struct: cheap to make on the worker thread, picklable, so a worker process
of a sharded agent hands its events to the receiving process over the control pipe (`EventStore.after`, then
`EventStore.ingest` there, which numbers them anew), and JSON-encodable as it is for the HTTP API.

`EventStore` keeps at most `capacity` events, each with an id that only grows, so a reader that remembers
the last id it saw asks for what came after it (`after`), and a reader that fell further behind than the store
simply gets what is left. The kinds that come in floods (`BULK_KINDS`: status transitions, rejections, the
watches' twin events), the alarms, and the rare lifecycle kinds (`LIFECYCLE_KINDS`: calibration, agent,
worker, broker) each hold a part of it: when it is full, the oldest event of a part over its share goes, so
a fleet going STALE and ONLINE cannot push an alarm raise out (the Sessions page counts the raises it holds),
and a flood of alarms cannot push out the agent's starts and stops, its workers' exits and the broker's
losses. `query` filters by device, level,
kind, text and time range; `subscribe` calls back on every new event (from the emitting thread: the callback
must only hand it on).

The emitters that need memory live here too, so the runtime calls each with one line: `StatusWatch` turns the
fleet's statuses (which change by the passing of time, not by a message) into transitions (an arm that
flaps between ONLINE and STALE, or OFFLINE, into one warning and a summary an interval), `BrokerWatch` the
connection pool's counters into disconnects and reconnects, `RejectionThrottle` a flood of rejected messages
into at most one event per device and reason per interval, with the count it stands for.
"""

from __future__ import annotations

import csv
import io
import itertools
import logging
import math
import threading
import time
from bisect import bisect_right
from collections import deque
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum, StrEnum
from operator import attrgetter
from typing import Protocol

import msgspec

from twin.core.alarms import UNITS as ALARM_UNITS
from twin.core.alarms import WAITING_STATES, AlarmEvent
from twin.core.health import HealthThresholds
from twin.transport.plan import ConnectionLimit

log = logging.getLogger(__name__)

__all__ = [
    "LIFECYCLE_KINDS",
    "BrokerWatch",
    "Event",
    "EventKind",
    "EventLevel",
    "EventQuery",
    "EventStore",
    "FlapRow",
    "FleetWatch",
    "RateWatch",
    "RejectionThrottle",
    "StatusWatch",
    "events_csv",
    "events_json",
    "neutralise_cell",
]

# How many events a store keeps by default: at a 2,000-arm fleet's start every arm comes ONLINE once, so the
# buffer must hold a few fleets' worth of transitions and still be small (an event is ~300 bytes).
# `[twin] events_capacity` sets it for a host.
DEFAULT_CAPACITY = 20_000
# A device's rejections of one reason make at most one event per this many seconds (the count in between is
# carried by the next one): a flooding edge must not push every other event out of the buffer.
REJECTION_INTERVAL_S = 10.0


class EventLevel(IntEnum):
    """Ordered, so a filter can ask for "warning and worse"."""

    INFO = 20
    WARNING = 30
    ERROR = 40

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def parse(cls, text: str) -> EventLevel:
        try:
            return cls[text.strip().upper()]
        except KeyError:
            raise ValueError(
                f"level {text!r} is not one of {', '.join(level.label for level in cls)}"
            ) from None


class EventKind(StrEnum):
    STATUS = "status"  # a device went ONLINE, STALE or OFFLINE
    ALARM = "alarm"  # a servo alarm was raised, cleared, acknowledged or reset
    REJECTED = "rejected"  # telemetry the decoder refused, by reason
    BROKER = "broker"  # a broker connection went down or came (back) up
    WORKER = "worker"  # a worker process of a sharded agent, or the history writer, exited or runs again
    # a device's twin was rebuilt (its edge clock jumped back), its rate is far from the expected, or it was
    # forgotten
    TWIN = "twin"
    CALIBRATION = "calibration"  # an arm's calibration was picked up, refused or removed
    AGENT = "agent"  # the agent started (saying whether the run before it stopped) or stopped


# The kinds whose number grows with the fleet and its troubles, not with what an operator must act on: every
# arm's status transitions (a loaded host sweeps 300 arms STALE and ONLINE again and again), rejections (up to
# MAX_REJECTED_EVENTS_PER_INTERVAL every 10 s, for hours) and the rate, loss and clock watches' and forgets'
# `twin` events (one per arm each). They share one part of the store; the others (alarm, calibration, agent,
# worker, broker) the rest, which a flood of these cannot take.
BULK_KINDS: frozenset[str] = frozenset(
    {EventKind.STATUS.value, EventKind.REJECTED.value, EventKind.TWIN.value}
)
# Of the others, the kinds that come a few an hour, not with the fleet's troubles: an alarm storm (every arm
# of a hot cell raising and clearing) must not push out the agent's start, a worker's exit or the broker's
# loss that explain it. They keep a reserve of their own within the non-bulk share (LIFECYCLE_RESERVE_ONE_IN).
LIFECYCLE_KINDS: frozenset[str] = frozenset(
    {EventKind.CALIBRATION.value, EventKind.AGENT.value, EventKind.WORKER.value, EventKind.BROKER.value}
)
# The lifecycle kinds' reserve: one event in this many of a store's capacity (1,000 of the default 20,000),
# at least one, at most the non-bulk share.
LIFECYCLE_RESERVE_ONE_IN = 20
# The parts a store keeps (EventStore), in this order: the numbers `part_index` gives.
BULK_PART, ALARM_PART, LIFECYCLE_PART = 0, 1, 2


def part_index(kind: str) -> int:
    """Which part of a store holds events of `kind` (BULK_PART, ALARM_PART, LIFECYCLE_PART): the store and
    the journal (which keeps the newest of each part at a start) by one rule."""
    if kind in BULK_KINDS:
        return BULK_PART
    return LIFECYCLE_PART if kind in LIFECYCLE_KINDS else ALARM_PART


class Event(msgspec.Struct, frozen=True, gc=False):
    """One event. `time` is wall-clock epoch seconds; `id` grows by one per event within one store (0 until a
    store numbers it); `data` holds the machine-readable details (alarm id, reason, statuses, counts)."""

    kind: str
    level: str
    message: str
    time: float
    device: str = ""
    data: dict[str, str] = msgspec.field(default_factory=dict)
    id: int = 0


@dataclass(frozen=True)
class EventQuery:
    """What `EventStore.query` returns: events matching every filter given, oldest first, at most `limit`
    (the newest ones when more match). Times are epoch seconds, `since` inclusive, `until` exclusive."""

    device: str = ""
    # Part of an id, in any case (the console's device box, as the Fleet and Sessions pages match): `device`
    # is one arm's whole id (its page's link to its events, where arm-1 must not bring arm-10's).
    device_part: str = ""
    min_level: EventLevel = EventLevel.INFO
    kinds: frozenset[str] = frozenset()
    text: str = ""
    since: float | None = None
    until: float | None = None
    after_id: int = 0
    limit: int = 1000

    def __post_init__(self) -> None:
        if self.limit < 1:
            raise ValueError(f"limit = {self.limit} must be at least 1")
        unknown = sorted(set(self.kinds) - {k.value for k in EventKind})
        if unknown:
            raise ValueError(
                f"kind {', '.join(unknown)} is not one of {', '.join(k.value for k in EventKind)}"
            )

    def matches(self, event: Event) -> bool:
        if event.id <= self.after_id:
            return False
        if self.device and event.device != self.device:
            return False
        if self.device_part and self.device_part.casefold() not in event.device.casefold():
            return False
        if self.kinds and event.kind not in self.kinds:
            return False
        if self.min_level > EventLevel.INFO and _level_of(event) < self.min_level:
            return False
        if self.since is not None and event.time < self.since:
            return False
        if self.until is not None and event.time >= self.until:
            return False
        if self.text:
            needle = self.text.casefold()
            return needle in event.message.casefold() or needle in event.device.casefold()
        return True


def _level_of(event: Event) -> EventLevel:
    try:
        return EventLevel[event.level.upper()]
    except KeyError:
        return EventLevel.INFO


Subscriber = Callable[[Event], None]
_ID = attrgetter("id")


class _Part:
    """One part of an `EventStore`: its events in id order, the oldest going first. A list and the index
    of its oldest, not a deque: `after` bisects it, and a deque's indexing walks its blocks. An event that
    goes is let go at once; the list's head is cut off once it is the larger half (amortised: pointers).
    """

    __slots__ = ("_head", "_items")

    def __init__(self) -> None:
        self._items: list[Event | None] = []
        self._head = 0

    def __len__(self) -> int:
        return len(self._items) - self._head

    def append(self, event: Event) -> None:
        self._items.append(event)

    def drop_oldest(self) -> None:
        self._items[self._head] = None
        self._head += 1
        if self._head * 2 > len(self._items):
            del self._items[: self._head]
            self._head = 0

    @property
    def oldest(self) -> Event:
        """Its oldest event (it holds one)."""
        return self._items[self._head]  # type: ignore[return-value]  # none from the head on is None

    def after(self, after_id: int, limit: int | None) -> list[Event]:
        """Its events newer than `after_id`, oldest first: the first `limit` of them."""
        items = self._items
        start = bisect_right(items, after_id, lo=self._head, key=_ID)  # none from the head on is None
        end = len(items) if limit is None else start + limit
        return items[start:end]  # type: ignore[return-value]


class EventStore:
    """At most `capacity` events, numbered, in three parts (module doc); thread-safe.

    `BULK_KINDS` fill one part, the alarms another, `LIFECYCLE_KINDS` the third. The alarms and the lifecycle
    kinds together keep `capacity // 2` for themselves: a full store lets go of one of those only while they
    hold more than that, else of the oldest bulk one. Within that share the lifecycle kinds keep a reserve
    (`capacity // LIFECYCLE_RESERVE_ONE_IN`): while they hold no more than it, the oldest alarm goes, else
    the older of the oldest alarm and the oldest lifecycle event. Any part may take what the others leave,
    so a store with no flood keeps the newest `capacity` events as one ring would, but for the lifecycle
    events in their reserve."""

    def __init__(
        self, capacity: int = DEFAULT_CAPACITY, *, wall_clock: Callable[[], float] = time.time
    ) -> None:
        if capacity < 1:
            raise ValueError(f"an event store holds at least one event, got capacity = {capacity}")
        self._capacity = capacity
        self._kept_share = capacity // 2
        self._lifecycle_share = min(self._kept_share, max(1, capacity // LIFECYCLE_RESERVE_ONE_IN))
        self._bulk = _Part()
        self._alarms = _Part()
        self._lifecycle = _Part()
        self._by_index = (self._bulk, self._alarms, self._lifecycle)  # part_index's order
        self._ids = itertools.count(1)
        self._last_id = 0
        self._lock = threading.Lock()
        self._subscribers: list[Subscriber] = []
        self._wall_clock = wall_clock
        self.dropped = 0  # let go of for newer ones
        # The time of the newest alarm event let go of (None: none was), this run's or a restored one's: the
        # alarms held are all there are from then on (alarms_complete_from).
        self._alarms_let_go_until: float | None = None
        self._alarm_let_go_id = 0  # and its id (0: none), which tells whether a reader had it first

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def last_id(self) -> int:
        return self._last_id

    @property
    def alarms_let_go_until(self) -> float | None:
        """The time of the newest alarm event this store let go of; None when it let go of none."""
        return self._alarms_let_go_until

    def alarms_let_go_after(self, after_id: int) -> float | None:
        """The time of the newest alarm event let go of when one numbered after `after_id` was: a reader that
        had read up to `after_id` never had it. None when every alarm let go of was numbered before."""
        with self._lock:
            return self._alarms_let_go_until if self._alarm_let_go_id > after_id else None

    def alarms_lost_until(self, at: float) -> None:
        """Alarm events up to `at` that this store never took were let go of elsewhere (a worker's store
        before the agent collected them): its alarms are complete only after `at` (alarms_complete_from)."""
        with self._lock:
            self._note_let_go(at)

    def _note_let_go(self, at: float) -> None:
        before = self._alarms_let_go_until
        self._alarms_let_go_until = at if before is None else max(before, at)

    def alarms_complete_from(self) -> float | None:
        """The time from which the alarm events held are all there were (the Sessions page counts raises from
        it); None when the store holds no event. The time of the oldest alarm or lifecycle event held (the
        journal keeps those in one file pair, service.event_journal): the bulk part, let go of on its own,
        may hold older events, of a time whose alarms are gone. Of the oldest event when it holds neither.
        Never before the newest alarm let go of: the lifecycle reserve may keep older events."""
        with self._lock:
            kept = [part.oldest for part in (self._alarms, self._lifecycle) if part]
            if not kept and not self._bulk:
                return None
            oldest = min(kept, key=_ID).time if kept else self._bulk.oldest.time
            let_go = self._alarms_let_go_until
            return oldest if let_go is None else max(oldest, let_go)

    def __len__(self) -> int:
        return len(self._bulk) + len(self._alarms) + len(self._lifecycle)

    def emit(
        self,
        kind: EventKind,
        level: EventLevel,
        message: str,
        *,
        device: str = "",
        data: Mapping[str, object] | None = None,
        at: float | None = None,
    ) -> Event:
        """Record a new event now (or at wall time `at`); returns it with its id."""
        event = Event(
            kind=str(kind),
            level=level.label,
            message=message,
            time=self._wall_clock() if at is None else at,
            device=device,
            data={k: "" if v is None else str(v) for k, v in (data or {}).items()},
        )
        return self._add((event,))[0]

    def ingest(self, events: Iterable[Event]) -> list[Event]:
        """Take events recorded elsewhere (a worker process's store), numbered anew in this store's order."""
        return self._add(tuple(events))

    def _add(self, events: Sequence[Event]) -> list[Event]:
        if not events:
            return []
        with self._lock:
            numbered = [msgspec.structs.replace(e, id=next(self._ids)) for e in events]
            for event in numbered:
                self._place(event)
            self._last_id = numbered[-1].id
            subscribers = tuple(self._subscribers)
        for callback in subscribers:
            for event in numbered:
                callback(event)
        return numbered

    def _part_of(self, kind: str) -> _Part:
        return self._by_index[part_index(kind)]

    def _parts(self, kinds: Collection[str]) -> tuple[_Part, ...]:
        """The parts that hold a kind of `kinds` (every part for none)."""
        if not kinds:
            return self._by_index
        return tuple(dict.fromkeys(self._part_of(kind) for kind in kinds))

    def _place(self, event: Event) -> None:
        """Into its part, letting go of the oldest of a part over its share if the store is full (the lock
        held)."""
        self._part_of(event.kind).append(event)
        if len(self) > self._capacity:
            self._let_go()

    def _let_go(self) -> None:
        """The oldest event of the part over its share goes (class doc). The alarm and lifecycle parts
        together over theirs, the lifecycle part within its reserve: the alarm part holds more than the rest
        of the share, so it is not empty. Else the bulk part is over the rest of the store: not empty."""
        alarms, lifecycle = self._alarms, self._lifecycle
        if len(alarms) + len(lifecycle) <= self._kept_share:
            self._bulk.drop_oldest()
        elif len(lifecycle) <= self._lifecycle_share or (alarms and alarms.oldest.id < lifecycle.oldest.id):
            let_go = alarms.oldest
            alarms.drop_oldest()
            self._note_let_go(let_go.time)
            self._alarm_let_go_id = max(self._alarm_let_go_id, let_go.id)
        else:
            lifecycle.drop_oldest()
        self.dropped += 1

    def restore(self, events: Sequence[Event]) -> int:
        """Put the events a run before this one numbered (service.event_journal) into this store, which
        has numbered none yet, with their ids; its own are numbered on from the highest, so a page that saw
        an id before the restart asks for what came after it. No subscriber hears of them: their alerts
        went out then. Returns how many were kept (the newest of each part, within `capacity`)."""
        ordered = sorted((e for e in events if e.id > 0), key=_ID)
        with self._lock:
            if self._last_id:
                raise ValueError("events are restored into a store before it numbers any of its own")
            for event in ordered:
                self._place(event)
            self.dropped = 0  # those of the run before, not this store's
            if ordered:
                self._last_id = ordered[-1].id
                self._ids = itertools.count(self._last_id + 1)
            return len(self)

    def after(self, after_id: int, limit: int | None = None) -> list[Event]:
        """Events newer than `after_id`, oldest first (at most the first `limit` of them)."""
        with self._lock:
            if after_id >= self._last_id:
                return []
            runs = [run for part in self._parts(()) if (run := part.after(after_id, limit))]
        return _merged(runs)[:limit]

    def query(self, query: EventQuery) -> list[Event]:
        with self._lock:
            # Only the parts that hold a kind asked for (the Sessions page's alarms skip a flood of statuses),
            # from `after_id` on (a page that follows the events asks for the last few, not the whole store).
            start = query.after_id
            runs = [run for part in self._parts(query.kinds) if (run := part.after(start, None))]
        matched = [e for e in _merged(runs) if query.matches(e)]
        return matched[-query.limit :]

    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        """Call `callback(event)` for every new event, on the thread that adds it; returns the unsubscribe."""
        with self._lock:
            self._subscribers.append(callback)

        def unsubscribe() -> None:
            with self._lock:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return unsubscribe


def _merged(runs: list[list[Event]]) -> list[Event]:
    """Runs each in id order as one list in id order: the sort merges them (timsort finds the runs)."""
    if len(runs) <= 1:
        return runs[0] if runs else []
    return sorted(itertools.chain.from_iterable(runs), key=_ID)


# ------------------------------------------------------------------------------------------------- emitters

_STATUS_LEVEL = {"ONLINE": EventLevel.INFO, "STALE": EventLevel.WARNING, "OFFLINE": EventLevel.WARNING}


# What StatusWatch holds for a device taken back from a checkpoint until a sweep reads its status.
_RESTORED = "restored"

# An arm back ONLINE (from STALE or OFFLINE) for the FLAP_ROUND_TRIPS-th time within FLAP_WINDOW_S is
# flapping: one warning says so (with the count), and its status changes make no event of their own
# after it, only a summary at most every FLAP_SUMMARY_S (the round trips since the last one, and where it
# stands), until it has kept one status for FLAP_SETTLE_S (one info event). An edge publishing slower than
# the stale line (stale_periods / expected_rate_hz) crosses it at nearly every sweep: 300 such arms made two
# events each a second, and pushed everything else out of the store in minutes. Three round trips a minute is
# not what an arm that pauses now and then does: a pause is one STALE and one ONLINE, as before.
# OFFLINE is told as always, and ends the episode, unless the arm's round trips went through OFFLINE (an edge
# publishing less often than offline_after_s: OFFLINE, then ONLINE with each message, three events a cycle):
# then its OFFLINE changes are held as well, and one that lasts FLAP_OFFLINE_HOLD_S is told (a warning) and
# ends the episode. That hold is the longest a round trip can take at the rule's pace, so an arm that stops
# is told OFFLINE that much later than one that was not flapping; the first OFFLINE after an episode ended
# is told at once.
FLAP_ROUND_TRIPS = 3
FLAP_WINDOW_S = 60.0
FLAP_SUMMARY_S = 300.0
FLAP_SETTLE_S = 60.0
FLAP_OFFLINE_HOLD_S = FLAP_WINDOW_S / FLAP_ROUND_TRIPS


# A flapping episode as a worker's checkpoint carries it (service.shards, MirrorCheckpoint.flapping): the
# device, then `_Flapping`'s fields in order. Its times are the host's monotonic clock, which a worker
# started again on the same host shares. A row without the last field (`offline`, added later) reads False:
# the episodes before it were all between ONLINE and STALE.
FlapRow = tuple[str, float, float, int, int, float, bool]
_FlapRowBefore = tuple[str, float, float, int, int, float]


@dataclass(slots=True)
class _Flapping:
    """A device reported flapping: when it began and its last status change (monotonic), the round trips in
    all and since the last summary, when the next summary may come, and whether its round trips went
    through OFFLINE (then its OFFLINE changes are held too)."""

    since: float
    changed: float
    trips: int
    pending: int
    next_summary: float
    offline: bool = False

    @property
    def between(self) -> str:
        return "ONLINE and OFFLINE" if self.offline else "ONLINE and STALE"


class StatusWatch:
    """Device status transitions from successive readings of the fleet's statuses, and each device's arrival.
    The arrival is told by the device's first valid message (`arrived`), not read by a later sweep: a sweep
    that comes over the STALE time after that message (a busy host) would say the arm arrived STALE. A device
    going STALE or OFFLINE and back over and over is told as flapping instead (FLAP_ROUND_TRIPS).
    `offline_after_s` (the health setting) is only named in the warning of an arm flapping through OFFLINE."""

    def __init__(self, store: EventStore, offline_after_s: float = HealthThresholds.offline_after_s) -> None:
        self._store = store
        self._offline_after_s = offline_after_s
        self._last: dict[str, str] = {}
        # Each device's recent returns to ONLINE: when, and whether from OFFLINE.
        self._returns: dict[str, deque[tuple[float, bool]]] = {}
        self._flapping: dict[str, _Flapping] = {}

    @property
    def flapping(self) -> tuple[str, ...]:
        return tuple(sorted(self._flapping))

    def flapping_rows(self) -> tuple[FlapRow, ...]:
        """The episodes as plain values, for a worker's checkpoint (`restore_flapping` takes them back)."""
        episodes = sorted(self._flapping.items())
        return tuple(
            (d, f.since, f.changed, f.trips, f.pending, f.next_summary, f.offline) for d, f in episodes
        )

    def restore_flapping(self, rows: Iterable[FlapRow | _FlapRowBefore]) -> None:
        """Episodes a checkpoint carried (the devices `restored` too): a worker started again neither warns
        of them a second time nor loses when they began, their round trips and their settle and summary
        times. The device's first reading after it, one of the statuses it flaps between, is held in the
        episode."""
        for row in rows:
            device, since, changed, trips, pending, next_summary = row[:6]
            self._flapping[device] = _Flapping(since, changed, trips, pending, next_summary, any(row[6:]))

    def arrived(self, device: str) -> None:
        """`device` sent its first valid message since this watch began: it is ONLINE now. Nothing for a
        device already known (restored from a checkpoint, or seen by a sweep)."""
        if device in self._last:
            return
        self._last[device] = "ONLINE"
        self._emit(device, "ONLINE", "", f"{device} is ONLINE (first message)")

    def restored(self, device: str) -> None:
        """`device` was taken back from a checkpoint: no arrival; the next sweep records its status."""
        self._last.setdefault(device, _RESTORED)

    def forget(self, device: str) -> None:
        """`device` was forgotten: if it publishes again, it arrives anew."""
        self._last.pop(device, None)
        self._returns.pop(device, None)
        self._flapping.pop(device, None)

    def sweep(self, statuses: Mapping[str, object], now: float | None = None) -> None:
        """`statuses`: device -> its status now (a DeviceStatus or its string); `now`: a monotonic time, for
        the flapping rule (the watch's own clock reading when not given)."""
        at = time.monotonic() if now is None else now
        last = self._last
        for device, status in statuses.items():
            current = str(status)
            before = last.get(device)
            if before == current:
                continue
            last[device] = current
            if before is None:
                # Never told of (`arrived` or `restored`): the mirror sweeps the arms heard from only, and
                # tells each arrival first, so this is a baseline, not an event; its changes are reported.
                continue
            if not self._flapped(device, before, current, at):
                self._changed(device, before, current)
        if self._flapping:
            self._sweep_flapping(statuses, at)

    def _changed(self, device: str, before: str, now: str) -> None:
        level = _STATUS_LEVEL.get(now, EventLevel.INFO)
        if before == _RESTORED:
            message, before = f"{device} is {now} (restored)", ""
        elif before == "OFFLINE" and now == "STALE":
            # Heard again, but the sweep met it past its stale line: a return, not a worsening.
            message = f"{device} went STALE (was OFFLINE): heard again, not yet at its rate"
            level = EventLevel.INFO
        else:
            message = f"{device} went {now} (was {before})"
        self._emit(device, now, before, message, level)

    def _flapped(self, device: str, before: str, now: str, at: float) -> bool:
        """Whether the change of `device` from `before` to `now` is told as flapping (or held in it)."""
        flap = self._flapping.get(device)
        if flap is not None:
            return self._held(flap, device, before, now, at)
        if now != "ONLINE" or before not in ("STALE", "OFFLINE"):
            return False
        returns = self._returns.setdefault(device, deque(maxlen=FLAP_ROUND_TRIPS))
        returns.append((at, before == "OFFLINE"))
        first = returns[0][0]
        if len(returns) < FLAP_ROUND_TRIPS or at - first > FLAP_WINDOW_S:
            return False
        del self._returns[device]
        flap = _Flapping(at, at, FLAP_ROUND_TRIPS, 0, at + FLAP_SUMMARY_S, any(o for _, o in returns))
        self._flapping[device] = flap
        hold = f" (OFFLINE: {FLAP_OFFLINE_HOLD_S:.0f} s, then told)" if flap.offline else ""
        if flap.offline:
            cause = (
                f"An edge publishing less often than [health] offline_after_s ({self._offline_after_s:g} s) "
                "goes OFFLINE between its messages: make it publish more often, or set offline_after_s "
                "above its period"
            )
        else:
            cause = (
                "An edge publishing slower than [health] expected_rate_hz (its gaps pass the stale line, "
                "stale_periods / expected_rate_hz) does this, and so does a link that delivers in bursts"
            )
        self._emit(
            device,
            now,
            before,
            f"{device} is flapping between {flap.between}: back ONLINE {FLAP_ROUND_TRIPS} times within "
            f"{at - first:.0f} s. Its changes are summarised every {FLAP_SUMMARY_S / 60:.0f} min until "
            f"it keeps one status for {FLAP_SETTLE_S:.0f} s{hold}; the Fleet page shows its status as it is. "
            + cause,
            EventLevel.WARNING,
            flapping="started",
            trips=FLAP_ROUND_TRIPS,
        )
        return True

    def _held(self, flap: _Flapping, device: str, before: str, now: str, at: float) -> bool:
        """Whether a flapping device's change is held in its episode: one between the statuses it flaps
        between is; any other (OFFLINE for one that flapped through STALE only) is told, and ends it."""
        held = ("ONLINE", "STALE", "OFFLINE") if flap.offline else ("ONLINE", "STALE")
        if now not in held:
            del self._flapping[device]
            return False
        if before == _RESTORED:  # its worker was started again: no change of its own, nor a round trip
            if now == "OFFLINE":
                flap.changed = at  # its hold runs from here: the restart's gap is no time seen OFFLINE
            return True
        flap.changed = at
        if now == "ONLINE":
            flap.trips += 1
            flap.pending += 1
        return True

    def _sweep_flapping(self, statuses: Mapping[str, object], at: float) -> None:
        """A summary of each flapping device whose interval is up, and the end of those that settled."""
        for device in list(self._flapping):
            flap = self._flapping[device]
            if device not in statuses:  # forgotten, evicted or moved to another worker
                del self._flapping[device]
                continue
            status = str(statuses[device])
            kept = at - flap.changed
            if kept >= FLAP_SETTLE_S or (status == "OFFLINE" and kept >= FLAP_OFFLINE_HOLD_S):
                del self._flapping[device]
                message = (
                    f"{device} no longer flaps: {status} for {kept:.0f} s, after {flap.trips} round trips "
                    f"between {flap.between} over {(flap.changed - flap.since) / 60:.0f} min"
                )
                level = _STATUS_LEVEL.get(status, EventLevel.INFO)
                self._emit(device, status, "", message, level, flapping="settled", trips=flap.trips)
            elif at >= flap.next_summary and flap.pending:
                message = (
                    f"{device} still flaps between {flap.between}: {flap.pending} round trips in the last "
                    f"{(at - flap.next_summary + FLAP_SUMMARY_S) / 60:.0f} min ({flap.trips} in all); "
                    f"{status} now"
                )
                self._emit(
                    device, status, "", message, EventLevel.WARNING, flapping="still", trips=flap.pending
                )
                flap.pending, flap.next_summary = 0, at + FLAP_SUMMARY_S

    def _emit(
        self,
        device: str,
        now: str,
        before: str,
        message: str,
        level: EventLevel = EventLevel.INFO,
        *,
        flapping: str = "",
        trips: int = 0,
    ) -> None:
        data: dict[str, object] = {"status": now, "previous": before}
        if flapping:
            data |= {"flapping": flapping, "round_trips": trips}
        self._store.emit(EventKind.STATUS, level, message, device=device, data=data)


class ConnectionCounters(Protocol):
    """What BrokerWatch reads of one broker connection."""

    @property
    def index(self) -> int: ...
    @property
    def client_id(self) -> str: ...
    @property
    def connection_successes(self) -> int: ...
    @property
    def disconnections(self) -> int: ...
    @property
    def last_error(self) -> str: ...
    @property
    def refused(self) -> tuple[str, ...]: ...
    @property
    def connected_at(self) -> float | None: ...


class BrokerWatch:
    """Disconnects and (re)connects of the broker connections, from their running counters (the pool counts
    them on its own threads; reading the counters keeps the transport free of any event code)."""

    def __init__(self, store: EventStore) -> None:
        self._store = store
        self._seen: dict[int, tuple[int, int]] = {}
        self._refused: dict[int, frozenset[str]] = {}

    def sweep(self, connections: Iterable[ConnectionCounters]) -> None:
        """`connections`: the pool's connections now (twin.transport.pool.ConnectionInfo)."""
        for c in connections:
            index, client_id, last_error = c.index, c.client_id, c.last_error
            successes, disconnections = c.connection_successes, c.disconnections
            before = self._seen.get(index, (0, 0))
            self._seen[index] = (successes, disconnections)
            dropped = disconnections - before[1]
            if dropped > 0:
                self._store.emit(
                    EventKind.BROKER,
                    EventLevel.WARNING,
                    f"broker connection {index} lost"
                    + (f" ({dropped} times)" if dropped > 1 else "")
                    + (f": {last_error}" if last_error else ""),
                    data={"connection": index, "client_id": client_id, "error": last_error},
                )
            if successes > before[0]:
                again = successes > 1
                # At the connect's own time: read up to a sweep later, it came after the arms it let in.
                self._store.emit(
                    EventKind.BROKER,
                    EventLevel.INFO,
                    f"broker connection {index} {'reconnected' if again else 'connected'}",
                    data={"connection": index, "client_id": client_id, "connects": successes},
                    at=c.connected_at,
                )
            self._sweep_refused(index, client_id, frozenset(c.refused), last_error)

    def _sweep_refused(self, index: int, client_id: str, refused: frozenset[str], last_error: str) -> None:
        """A filter the broker began to refuse (an IoT policy that does not allow it), or granted again."""
        before = self._refused.get(index, frozenset())
        self._refused[index] = refused
        for topic_filter in sorted(refused - before):
            self._store.emit(
                EventKind.BROKER,
                EventLevel.ERROR,
                f"broker connection {index}: the subscription to {topic_filter} is refused, so its arms are "
                "not heard; the agent's IAM identity must allow iot:Subscribe on it",
                data={
                    "connection": index,
                    "client_id": client_id,
                    "filter": topic_filter,
                    "error": last_error,
                },
            )
        for topic_filter in sorted(before - refused):
            self._store.emit(
                EventKind.BROKER,
                EventLevel.INFO,
                f"broker connection {index}: the subscription to {topic_filter} is granted now",
                data={"connection": index, "client_id": client_id, "filter": topic_filter},
            )


# A device whose valid messages arrive at CROWDED_RATIO times [health] expected_rate_hz or more, for
# CROWDED_HOLD_S, is reported (a warning), and again (info) once under CROWDED_CLEAR_RATIO times. The
# likeliest cause is two edges publishing under one device id (the edge component's default is arm-001 on
# every arm), which makes one twin jump between poses; the other, an edge that really publishes faster than
# the setting.
# The hold lets an edge's burst after a reconnect (a spooled backlog) pass; the gap between the two ratios
# keeps a rate near the line from reporting at every sweep.
CROWDED_RATIO = 1.8
CROWDED_CLEAR_RATIO = 1.3
CROWDED_HOLD_S = 30.0
# A device whose valid messages arrive at SLOW_RATIO times [health] expected_rate_hz or less (but some do)
# for SLOW_HOLD_S is reported too, and again once at SLOW_CLEAR_RATIO times or more: the crowded lines turned
# the other way (about 1 / 1.8 and 1 / 1.3). Under them an edge at 5 Hz against the default 10 is caught,
# whose every gap is two nominal periods, so core.loss reads it as half its messages lost; an edge at 6 Hz,
# whose gaps fit no whole number of periods and read as no loss, is not. Below a third of the rate (the
# stale_periods default) the arm also goes STALE between its messages. The hold lets the dip of a pause or a
# reconnect (at most one 5 s rate window) pass, and a fresh rate meter fill. An arm sending less than once a
# rate window (one message every 8 s) reads 0 in some windows: a 0 does not begin a time under the line,
# but it goes on with one while the arm is not OFFLINE (it has not stopped, its next message is due), and
# the rate reported is the mean of the readings over the hold.
SLOW_RATIO = 0.55
SLOW_CLEAR_RATIO = 0.75
SLOW_HOLD_S = 30.0
# A device reported before its worker was started again (the checkpoint carries the reported devices): its
# rate starts again from nothing in the new process, so it is not said to be back for this long.
RESTORED_SETTLE_S = 10.0


class RateWatch:
    """Devices publishing well above the expected rate ("crowded"), and those whose messages arrive well
    under it ("slow"), from successive readings of their rates (`sweep`). Holds only the devices near a line
    now or reported and not yet back: bounded by the fleet."""

    def __init__(
        self,
        store: EventStore,
        expected_rate_hz: float,
        *,
        stale_after_s: float | None = None,
        connection_limit: ConnectionLimit | None = None,
    ) -> None:
        self._store = store
        self._expected = expected_rate_hz
        # The broker's publishes per second per connection and its source (None: no limit), which the slow
        # warning names as a cause only where there is one.
        self._limit = connection_limit
        # [health] stale_after_s, which the slow warning names (the default stale_periods' when not given)
        if stale_after_s is None:
            stale_after_s = HealthThresholds(expected_rate_hz=expected_rate_hz).stale_after_s
        self._stale_after_s = stale_after_s
        self._over_since: dict[str, float] = {}
        # Each device under the slow line -> when that began, and the sum and count of its readings since
        # (their mean is what is reported).
        self._under: dict[str, tuple[float, float, int]] = {}
        self._reported: set[str] = set()
        self._slow: set[str] = set()
        self._settling: dict[str, float] = {}  # restored device -> until when it cannot be back

    @property
    def reported(self) -> tuple[str, ...]:
        return tuple(sorted(self._reported))

    @property
    def slow(self) -> tuple[str, ...]:
        """The devices reported well under the expected rate and not yet back."""
        return tuple(sorted(self._slow))

    @property
    def slowing(self) -> frozenset[str]:
        """The devices reported slow and those under the slow line now, not yet held there long enough."""
        return frozenset(self._slow.union(self._under))

    def restore(self, devices: Iterable[str], now: float, slow: Iterable[str] = ()) -> None:
        """Devices a checkpoint says were reported crowded (`reported`) or `slow`, before the mirror's process
        was started again: not reported a second time while they stay past the line, and not said to be back
        before RESTORED_SETTLE_S, while their rates fill again."""
        for device in devices:
            self._reported.add(device)
            self._settling[device] = now + RESTORED_SETTLE_S
        for device in slow:
            self._slow.add(device)
            self._settling[device] = now + RESTORED_SETTLE_S

    def forget(self, device: str) -> None:
        """`device` was forgotten: nothing of it stays (it is judged anew if it publishes again)."""
        self._over_since.pop(device, None)
        self._under.pop(device, None)
        self._reported.discard(device)
        self._slow.discard(device)
        self._settling.pop(device, None)

    def sweep(
        self, rates: Mapping[str, float], now: float, *, statuses: Mapping[str, object] | None = None
    ) -> None:
        """`rates`: each device heard from -> its valid messages per second now; `now` a monotonic time;
        `statuses`: their statuses at the same point (StatusWatch's reading), without which a rate of 0 ends a
        device's time under the slow line."""
        for near in (self._over_since, self._under):
            for device in [d for d in near if d not in rates]:
                del near[device]
        # Evicted or restarted elsewhere: nothing to clear here.
        self._reported.intersection_update(rates)
        self._slow.intersection_update(rates)
        reported = self._reported | self._slow
        for device in [d for d, until in self._settling.items() if d not in reported or now >= until]:
            del self._settling[device]
        expected = self._expected
        for device, rate in rates.items():
            if device in self._reported:
                if device not in self._settling and rate < CROWDED_CLEAR_RATIO * expected:
                    self._reported.discard(device)
                    self._back(device, rate)
            elif device in self._slow:
                if device not in self._settling and rate >= SLOW_CLEAR_RATIO * expected:
                    self._slow.discard(device)
                    self._back(device, rate, was="under")
            elif _held(self._over_since, device, rate >= CROWDED_RATIO * expected, now, CROWDED_HOLD_S):
                self._reported.add(device)
                self._crowded(device, rate)
            else:
                held = self._held_under(device, rate, now, statuses)
                if held is not None:
                    self._slow.add(device)
                    self._slowed(device, held)

    def _held_under(
        self, device: str, rate: float, now: float, statuses: Mapping[str, object] | None
    ) -> float | None:
        """The mean rate of `device` over its time under the slow line once that is SLOW_HOLD_S, else None.
        Some messages, but few: an arm that stopped reads 0 and its status events tell of it; a 0 between the
        messages of an arm sending less than once a rate window goes on with its time under, not OFFLINE."""
        if 0.0 < rate <= SLOW_RATIO * self._expected:
            under = True
        elif rate == 0.0 and statuses is not None and device in self._under:
            under = str(statuses.get(device, "OFFLINE")) != "OFFLINE"
        else:
            under = False
        if not under:
            self._under.pop(device, None)
            return None
        since, total, count = self._under.get(device, (now, 0.0, 0))
        total, count = total + rate, count + 1
        # Told at a reading with messages in it, not in a silence that may be the arm stopping.
        if rate == 0.0 or now - since < SLOW_HOLD_S:
            self._under[device] = (since, total, count)
            return None
        self._under.pop(device, None)
        return total / count

    def _crowded(self, device: str, rate: float) -> None:
        message = (
            f"{device} sends {rate:.1f} valid messages/s, {rate / self._expected:.1f} times the expected "
            f"{self._expected:g} Hz, for {CROWDED_HOLD_S:.0f} s: two edges may publish under its device id "
            "(each arm needs its own deviceId; the twin jumps between their poses), or the edge publishes "
            "faster than [health] expected_rate_hz says"
        )
        self._say(device, rate, "crowded", message)

    def _slowed(self, device: str, rate: float) -> None:
        # The checks first, the setting last: set on a guess, it hid a loss as a slower edge.
        limit = self._limit
        quota = (
            ""
            if limit is None
            else f"If the Fleet page has a notice of the broker's per-connection quota ({limit.per_s:g} "
            f"messages/s a connection, {limit.source}), the quota discards them: its notice says what "
            "to change. "
        )
        message = (
            f"{device} sends {rate:.1f} valid messages/s, well under the expected {self._expected:g} Hz, "
            f"for {SLOW_HOLD_S:.0f} s: its messages are lost on the way in, or its edge publishes slower. "
            f"{quota}Read the rate configured on its edge: if it is {self._expected:g} Hz, its edge's "
            f"network loses them; only if it is {rate:.1f} Hz set [health] expected_rate_hz = {_hz(rate)} "
            "in your agent config (on the twin host the stack's armRateHz), as until then its loss reads "
            f"about {max(0.0, 1.0 - rate / self._expected):.0%} and it goes STALE whenever a gap passes "
            f'{self._stale_after_s:.2g} s (docs/agent.md, "Loss")'
        )
        self._say(device, rate, "slow", message)

    def _back(self, device: str, rate: float, was: str = "above") -> None:
        # Also what a crowded arm that stops says on its way down: its status events tell that part.
        message = (
            f"{device} sends {rate:.1f} valid messages/s now, no longer far {was} the expected "
            f"{self._expected:g} Hz"
        )
        self._say(device, rate, "expected", message)

    def _say(self, device: str, rate: float, state: str, message: str) -> None:
        """One log line and one event: a warning when `state` is "crowded" or "slow", info when back to
        "expected"."""
        level = EventLevel.INFO if state == "expected" else EventLevel.WARNING
        data = {"rate_hz": f"{rate:.2f}", "expected_rate_hz": f"{self._expected:g}", "rate": state}
        extra = {"event": "device_rate", "rate_hz": rate}
        _tell(self._store, device, level, message, data=data, log_extra=extra)


def _hz(rate: float) -> str:
    """A measured rate as a setting would be written: whole hertz, or one decimal under 2 Hz."""
    return f"{round(rate):d}" if rate >= 2.0 else f"{round(rate, 1):g}"


# An arm that loses this share of its messages (core.loss's estimate over its recent window, at least
# LOSING_REPORT_MIN_LOST of them) in every sweep for LOSING_HOLD_S is reported; below LOSING_CLEAR_RATIO, that
# it is back. The fleet's LossPercent averages the arms, so one arm's loss shows there only as a fraction; the
# hold lets a reconnect's burst of loss pass, and the gap between the ratios keeps an arm near the line from
# reporting at every sweep.
LOSING_REPORT_RATIO = 0.10
LOSING_CLEAR_RATIO = 0.03
LOSING_REPORT_MIN_LOST = 5
LOSING_HOLD_S = 30.0


class LossWatch:
    """Arms losing a tenth of their messages or more, from successive readings of their recent loss
    (`sweep`): one warning an episode naming the arm, and one info when it is back. Holds only the arms
    over the line now or reported and not yet back: bounded by the fleet."""

    def __init__(self, store: EventStore) -> None:
        self._store = store
        self._over_since: dict[str, float] = {}
        self._reported: set[str] = set()

    @property
    def reported(self) -> tuple[str, ...]:
        return tuple(sorted(self._reported))

    def restore(self, devices: Iterable[str]) -> None:
        """Arms a checkpoint says were reported: not reported again while they keep losing (their loss
        estimates come back with the checkpoint, their recent windows too)."""
        self._reported.update(devices)

    def forget(self, device: str) -> None:
        self._over_since.pop(device, None)
        self._reported.discard(device)

    def sweep(
        self,
        recent: Mapping[str, tuple[int, int]],
        now: float,
        crowded: Collection[str] = (),
        *,
        slow: Collection[str] = (),
    ) -> None:
        """`recent`: each arm heard from -> (received, lost) over its recent window; `now` monotonic;
        `crowded`: the devices RateWatch reports far above their rate (their "loss" is named for that);
        `slow`: those it reports, or is about to, well under it. Their loss is not reported here: the rate
        warning names it as one reading (an edge at 2 Hz against 10 reads as 80 % lost, every arm of it)."""
        for device in [d for d in self._over_since if d not in recent]:
            del self._over_since[device]
        self._reported.intersection_update(recent)  # evicted or restarted elsewhere: nothing to clear
        for device, (received, lost) in recent.items():
            ratio = lost / (received + lost) if received + lost else 0.0
            if device in self._reported:
                if ratio < LOSING_CLEAR_RATIO:
                    self._reported.discard(device)
                    self._say(device, ratio, lost, losing=False)
                continue
            over = ratio >= LOSING_REPORT_RATIO and lost >= LOSING_REPORT_MIN_LOST and device not in slow
            if _held(self._over_since, device, over, now, LOSING_HOLD_S):
                self._reported.add(device)
                self._say(device, ratio, lost, losing=True, crowded=device in crowded)

    def _say(self, device: str, ratio: float, lost: int, *, losing: bool, crowded: bool = False) -> None:
        if losing and crowded:
            # Two edges under one id interleave two timestamp grids: the loss estimate reads the finer
            # step between them as the period and counts its empty slots as lost, though nothing was.
            level = EventLevel.WARNING
            message = (
                f"{device} seems to lose {ratio:.0%} of its messages ({lost} in its last seconds), for "
                f"{LOSING_HOLD_S:.0f} s, while it sends far more than its expected rate: two edges "
                "publishing under its device id look like this, each with its own timestamps; give each arm "
                "its own deviceId (docs/getting-started.md, part 3) before looking at the network"
            )
        elif losing:
            level = EventLevel.WARNING
            message = (
                f"{device} is losing {ratio:.0%} of its messages ({lost} in its last seconds), for "
                f"{LOSING_HOLD_S:.0f} s: its edge's network, or its broker connection over IoT Core's 100 "
                'publishes/s (docs/agent.md, "Loss")'
            )
        else:
            level = EventLevel.INFO
            message = f"{device} no longer loses messages ({ratio:.0%} now)"
        data = {"loss_ratio": f"{ratio:.3f}", "recent_lost": lost, "loss": "losing" if losing else "whole"}
        _tell(self._store, device, level, message, data=data, log_extra={"event": "device_loss"})


# An edge clock this far from the agent's (the window's least receive-minus-timestamp; transit alone is well
# under it) in two sweeps CLOCK_INTERVAL_S apart is reported; once within CLOCK_BACK_S, that it is back.
CLOCK_SKEW_S = 2.0
CLOCK_BACK_S = 1.0
CLOCK_INTERVAL_S = 30.0


class ClockWatch:
    """Edge clocks far from the agent's: a Raspberry Pi without a battery clock boots with the wrong time,
    and the twin then shows it only as a number (edge_clock_offset_s). Holds the devices seen off once and
    those reported, bounded by the fleet."""

    def __init__(self, store: EventStore) -> None:
        self._store = store
        self._off_once: set[str] = set()
        self._reported: set[str] = set()

    @property
    def reported(self) -> tuple[str, ...]:
        return tuple(sorted(self._reported))

    def restore(self, devices: Iterable[str]) -> None:
        """Arms a checkpoint says were reported: not reported again while their clocks stay off."""
        self._reported.update(devices)

    def forget(self, device: str) -> None:
        self._off_once.discard(device)
        self._reported.discard(device)

    def sweep(self, offsets: Mapping[str, float]) -> None:
        """`offsets`: each device with samples in its window -> receive wall time minus edge timestamp."""
        self._off_once.intersection_update(offsets)
        self._reported.intersection_update(offsets)
        for device, offset in offsets.items():
            if device in self._reported:
                if abs(offset) <= CLOCK_BACK_S:
                    self._reported.discard(device)
                    self._say(
                        device,
                        offset,
                        EventLevel.INFO,
                        f"the clock of {device} agrees with the agent's again (within {abs(offset):.1f} s)",
                    )
            elif abs(offset) < CLOCK_SKEW_S:
                self._off_once.discard(device)
            elif device not in self._off_once:
                # Once may be a burst of transit; twice, CLOCK_INTERVAL_S apart, is the clock.
                self._off_once.add(device)
            else:
                self._off_once.discard(device)
                self._reported.add(device)
                self._say(device, offset, EventLevel.WARNING, _skew_message(device, offset))

    def _say(self, device: str, offset: float, level: EventLevel, message: str) -> None:
        data = {"clock_offset_s": f"{offset:.3f}"}
        extra = {"event": "edge_clock", "offset_s": offset}
        _tell(self._store, device, level, message, data=data, log_extra=extra)


def _held(over_since: dict[str, float], device: str, over: bool, now: float, hold_s: float) -> bool:
    """Whether `device` has been `over` its line in every reading for `hold_s` (then its time starts again):
    the hold the rate and loss watches put before a report. `over_since` keeps when each began."""
    if not over:
        over_since.pop(device, None)
        return False
    if now - over_since.setdefault(device, now) < hold_s:
        return False
    del over_since[device]
    return True


def _tell(
    store: EventStore,
    device: str,
    level: EventLevel,
    message: str,
    *,
    data: Mapping[str, object],
    log_extra: Mapping[str, object],
) -> None:
    """One log line (a warning or info, as the event) and one `twin` event about `device`: what the rate,
    loss and clock watches say. The log line's extra has the device, `log_extra` and the event's `data`."""
    log_level = logging.WARNING if level is EventLevel.WARNING else logging.INFO
    log.log(log_level, "%s", message, extra={**data, **log_extra, "device": device})
    store.emit(EventKind.TWIN, level, message, device=device, data=data)


def _skew_message(device: str, offset: float) -> str:
    # offset = receive time - edge timestamp: an edge clock ahead makes it negative.
    way = "ahead of" if offset < 0 else "behind"
    return (
        f"the clock of {device} is about {abs(offset):.0f} s {way} the agent's: its messages carry that "
        "time, so its latency figures, its history's edge times and a replay of it are off by as much; set "
        "the edge's time from NTP (chrony or systemd-timesyncd; `timedatectl` says if it is synchronised)"
    )


_ALARM_LEVEL = {"raised": EventLevel.WARNING, "cleared": EventLevel.INFO}
# The [health] settings of a watch not given any (tests, a demo's store).
_DEFAULT_HEALTH = HealthThresholds()


def alarm_level(event: AlarmEvent) -> EventLevel:
    """An alarm transition's own level: a raise a warning (a critical one an error), the rest info. Its event
    and its log line (twin.service.mirror) both go at it, unless it is one of a burst (FleetWatch.alarm)."""
    if event.action == "raised" and str(event.severity) == "critical":
        return EventLevel.ERROR
    return _ALARM_LEVEL.get(event.action, EventLevel.INFO)


# A change of what publishes for the arms (another edge or simulator taking over their device ids, with
# another model, calibration or servo version) makes every still servo of every arm mismatch the model at
# once: each is an alarm of its own (listed, e-mailed, counted in its session), but told one by one a swap of
# simulators was 160 warnings in a second, on the Events page and in the log. Of the model_mismatch raises
# within MISMATCH_BURST_WINDOW_S of the first, the first MISMATCH_BURST_TOLD are told as ever (a contact on
# one arm is a warning at once); the rest are info events and log lines, and one warning at the window's end
# says how many, on how many arms, and what to check (`MismatchBurst`).
MISMATCH_BURST_TOLD = 3
MISMATCH_BURST_WINDOW_S = 5.0
# The arms a burst's warning names (the count says how many more).
MISMATCH_BURST_NAMED = 5
# How often FleetWatch reads the fleet's statuses and the broker's counters.
WATCH_INTERVAL_S = 0.5
# How often it reads the devices' rates (RateWatch): a sum over each one's rate buckets, not every sweep.
RATE_INTERVAL_S = 5.0


class MismatchBurst:
    """The model_mismatch raises of one window (MISMATCH_BURST_TOLD above): which are told at their own
    level, and the one warning that sums up the rest. Times are the alarm engine's (monotonic seconds)."""

    def __init__(self, store: EventStore) -> None:
        self.store = store
        self._opened: float | None = None
        self._told = 0
        self._arms: dict[str, int] = {}  # raises per arm in the window, in the order first raised
        self._joints: dict[str, int] = {}

    def raised(self, event: AlarmEvent) -> bool:
        """A model_mismatch raise: True to tell it at its own level, False to tell it at info (the window's
        warning counts it)."""
        self.sweep(event.at)
        if self._opened is None:
            self._opened, self._told = event.at, 0
        self._arms[event.device] = self._arms.get(event.device, 0) + 1
        self._joints[event.joint] = self._joints.get(event.joint, 0) + 1
        if self._told < MISMATCH_BURST_TOLD:
            self._told += 1
            return True
        return False

    def sweep(self, now: float) -> None:
        """End the window once MISMATCH_BURST_WINDOW_S have passed since its first raise: its warning, if
        more were raised than were told."""
        opened = self._opened
        if opened is None or now - opened < MISMATCH_BURST_WINDOW_S:
            return
        raised = sum(self._arms.values())
        if raised > self._told:
            self._summary(raised)
        self._opened = None
        self._arms, self._joints = {}, {}

    def _summary(self, raised: int) -> None:
        arms = list(self._arms)
        named = ", ".join(arms[:MISMATCH_BURST_NAMED])
        more = f" and {len(arms) - MISMATCH_BURST_NAMED} more" if len(arms) > MISMATCH_BURST_NAMED else ""
        joints = ", ".join(f"{joint} {n}" for joint, n in sorted(self._joints.items(), key=lambda x: -x[1]))
        message = (
            f"model_mismatch raised on {raised} servos of {len(arms)} arms within "
            f"{MISMATCH_BURST_WINDOW_S:g} s ({named}{more}; {joints}); the first {self._told} told one by "
            "one, the rest as info events. So many at once is rarely contact: check what publishes for these "
            "arms (another edge or simulator on their device ids, another model or calibration) and [alarms] "
            "servo_version; each alarm stays listed in /alarms, acknowledge them together once explained"
        )
        data = {"action": "burst", "kind": "model_mismatch", "raised": raised, "arms": len(arms)}
        log.warning("%s", message, extra={**data, "event": "servo_alarm_burst", "joints": dict(self._joints)})
        self.store.emit(EventKind.ALARM, EventLevel.WARNING, message, data={**data, "told": self._told})


class FleetWatch:
    """The runtime's one handle on its events: status and broker sweeps (`due`, `statuses`, `broker`), and
    the alarm transitions and twin rebuilds it is told about."""

    interval_s = WATCH_INTERVAL_S

    def __init__(
        self,
        store: EventStore,
        *,
        health: HealthThresholds = _DEFAULT_HEALTH,
        connection_limit: ConnectionLimit | None = None,
    ) -> None:
        self.store = store
        self._statuses = StatusWatch(store, health.offline_after_s)
        self._broker = BrokerWatch(store)
        self._rates = RateWatch(
            store,
            health.expected_rate_hz,
            stale_after_s=health.stale_after_s,
            connection_limit=connection_limit,
        )
        self._losses = LossWatch(store)
        self._clocks = ClockWatch(store)
        self._mismatches = MismatchBurst(store)
        self._next = 0.0
        self._next_rates = 0.0
        self._next_clocks = 0.0

    def due(self, now: float) -> bool:
        if now < self._next:
            return False
        self._next = now + self.interval_s
        return True

    def rates_due(self, now: float) -> bool:
        if now < self._next_rates:
            return False
        self._next_rates = now + RATE_INTERVAL_S
        return True

    def rates(
        self, rates: Mapping[str, float], now: float, statuses: Mapping[str, object] | None = None
    ) -> None:
        """`statuses`: the arms' statuses read at the same point (an arm not OFFLINE has not stopped)."""
        self._rates.sweep(rates, now, statuses=statuses)

    def losses(self, recent: Mapping[str, tuple[int, int]], now: float) -> None:
        """Read with the rates (`rates_due`): each arm's (received, lost) over its recent window."""
        self._losses.sweep(recent, now, self._rates.reported, slow=self._rates.slowing)

    @property
    def losing(self) -> tuple[str, ...]:
        """The arms reported losing messages and not yet back (LossWatch)."""
        return self._losses.reported

    def losing_restored(self, devices: Iterable[str]) -> None:
        self._losses.restore(devices)

    def clocks_due(self, now: float) -> bool:
        if now < self._next_clocks:
            return False
        self._next_clocks = now + CLOCK_INTERVAL_S
        return True

    def clocks(self, offsets: Mapping[str, float]) -> None:
        self._clocks.sweep(offsets)

    @property
    def clocks_off(self) -> tuple[str, ...]:
        """The arms whose edge clocks were reported off and not yet back (ClockWatch)."""
        return self._clocks.reported

    def clocks_restored(self, devices: Iterable[str]) -> None:
        self._clocks.restore(devices)

    @property
    def crowded(self) -> tuple[str, ...]:
        """The devices reported publishing far above the expected rate and not yet back (RateWatch)."""
        return self._rates.reported

    @property
    def slow(self) -> tuple[str, ...]:
        """The devices reported sending well under the expected rate and not yet back (RateWatch)."""
        return self._rates.slow

    def crowded_restored(self, devices: Iterable[str], now: float, slow: Iterable[str] = ()) -> None:
        """Devices a checkpoint carried as `crowded` and as `slow`: RateWatch.restore."""
        self._rates.restore(devices, now, slow)

    def statuses(self, statuses: Mapping[str, object], now: float | None = None) -> None:
        """`now`: a monotonic time (for StatusWatch's flapping rule)."""
        self._statuses.sweep(statuses, now)

    @property
    def flapping(self) -> tuple[FlapRow, ...]:
        """The arms' flapping episodes, for a worker's checkpoint (StatusWatch.flapping_rows)."""
        return self._statuses.flapping_rows()

    def flapping_restored(self, rows: Iterable[FlapRow]) -> None:
        self._statuses.restore_flapping(rows)

    def arrived(self, device: str) -> None:
        self._statuses.arrived(device)

    def restored(self, device: str) -> None:
        self._statuses.restored(device)

    def broker(self, connections: Iterable[ConnectionCounters]) -> None:
        self._broker.sweep(connections)

    def forgotten(
        self, device: str, status: str, alarms_removed: Mapping[str, int], reason: str = ""
    ) -> None:
        """An operator forgot `device` (it was `status`), or the agent did for `reason`: its memory here goes,
        and one event says what was removed with it."""
        self._statuses.forget(device)
        self._rates.forget(device)
        self._losses.forget(device)
        self._clocks.forget(device)
        alarms = ", ".join(f"{n} {state}" for state, n in sorted(alarms_removed.items())) or "none"
        # The agent dropping alarms no person has seen (telemetry.forget_unseen_after_s) is a loss to look at.
        unseen = reason and any(alarms_removed.get(state) for state in WAITING_STATES)
        self.store.emit(
            EventKind.TWIN,
            EventLevel.WARNING if unseen else EventLevel.INFO,
            f"{device} forgotten {reason or 'by an operator'} (it was {status}): its twin, health and "
            f"counters removed; alarms removed: {alarms}",
            device=device,
            data={
                "action": "forgotten",
                "status": status,
                "by": "agent" if reason else "operator",
                **{f"alarms_{state}": n for state, n in sorted(alarms_removed.items())},
            },
        )

    def alarm(self, event: AlarmEvent) -> bool:
        """An alarm transition as an event; False when it is told at info, as one of a burst (`MismatchBurst`,
        whose warning counts it): its log line goes at info too."""
        level, told = alarm_level(event), True
        # A critical raise is never held (its level is ERROR).
        mismatch = level is EventLevel.WARNING and event.kind == "model_mismatch"
        if mismatch and not self._mismatches.raised(event):
            level, told = EventLevel.INFO, False
        self.store.emit(
            EventKind.ALARM,
            level,
            f"{event.alarm_id} {event.action}: {event.message}",
            device=event.device,
            data={
                "alarm_id": event.alarm_id,
                "action": event.action,
                "severity": str(event.severity),
                "state": str(event.state),
                "previous": str(event.previous),
                "joint": event.joint,
                "kind": str(event.kind),
                "value": event.value,
                "threshold": event.threshold,
                "unit": ALARM_UNITS.get(event.kind, ""),
                "text": event.message,
            },
        )
        return told

    def alarm_bursts(self, now: float) -> None:
        """Sum up a burst of alarm raises whose window has passed (MismatchBurst), on the status sweep."""
        self._mismatches.sweep(now)

    def clock_reset(
        self, device: str, last_ms: int | None, now_ms: int, *, how: str = "jumped backwards", untold: int = 0
    ) -> None:
        """`how` the clock went ("jumped backwards", "stands still"); `untold`: the rebuilds since the last
        such event that made none (the mirror tells them once a minute)."""
        more = f" ({untold} more rebuilds since the last word)" if untold else ""
        self.store.emit(
            EventKind.TWIN,
            EventLevel.WARNING,
            f"edge clock of {device} {how}; twin rebuilt on the new timeline{more}; fix: set the edge's "
            "clock by NTP",
            device=device,
            data={"last_ms": last_ms, "now_ms": now_ms, "untold": untold},
        )


# The throttle remembers at most this many (device, reason) keys.
MAX_THROTTLE_KEYS = 4096
# Rejected events in all per interval. Each invented device id is a key of its own, so without this a flood
# of them made an event per message and pushed every alarm out of the store (the newest 20,000) in minutes.
MAX_REJECTED_EVENTS_PER_INTERVAL = 50


class RejectionThrottle:
    """At most one "rejected" event per (device, reason) per `interval_s`; the next one carries how many
    rejections it stands for. And at most MAX_REJECTED_EVENTS_PER_INTERVAL in all per interval (one
    throttle per mirror): the next event after those says how many it held back (`held_back`)."""

    def __init__(
        self,
        store: EventStore,
        interval_s: float = REJECTION_INTERVAL_S,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._store = store
        self._interval_s = interval_s
        self._clock = clock
        self._next: dict[tuple[str, str], float] = {}
        self._pending: dict[tuple[str, str], int] = {}
        self._window_end = -math.inf
        self._in_window = 0
        self._held_back = 0  # rejections the fleet-wide cap kept from the events since its last event

    def rejected(self, device: str | None, reason: str, detail: str) -> None:
        key = (device or "", reason)
        count = self._pending.get(key, 0) + 1
        now = self._clock()
        if now < self._next.get(key, 0.0):
            self._pending[key] = count
            return
        if now >= self._window_end:
            self._window_end, self._in_window = now + self._interval_s, 0
        if self._in_window >= MAX_REJECTED_EVENTS_PER_INTERVAL:
            self._held_back += 1  # not per key: the keys of a flood of invented ids would be the table
            return
        self._in_window += 1
        self._pending.pop(key, None)
        self._next[key] = now + self._interval_s
        if len(self._next) > MAX_THROTTLE_KEYS:
            # Device ids come from topics anyone may invent: the oldest keys go (dicts keep insertion order).
            oldest = next(iter(self._next))
            del self._next[oldest]
            self._pending.pop(oldest, None)
        where = device or "a message with no usable device"
        times = f" ({count} since the last report)" if count > 1 else ""
        held, self._held_back = self._held_back, 0
        others = f" ({held} more rejected messages held back: too many at once)" if held else ""
        self._store.emit(
            EventKind.REJECTED,
            EventLevel.WARNING,
            f"telemetry from {where} rejected: {reason}{times}: {detail}{others}",
            device=device or "",
            data={"reason": reason, "count": count, **({"held_back": held} if held else {})},
        )


# --------------------------------------------------------------------------------------------------- export

EXPORT_COLUMNS = ("id", "time", "iso_time", "level", "kind", "device", "message", "data")
_FORMULA_START = ("=", "+", "-", "@")


def neutralise_cell(text: str) -> str:
    """A text cell a spreadsheet would run as a formula (`=`, `+`, `-`, `@` first, also after leading tabs or
    carriage returns) gets a leading apostrophe, the usual way to make it plain text."""
    stripped = text.lstrip("\t\r\n ")
    if stripped.startswith(_FORMULA_START) or text.startswith(("\t", "\r")):
        return "'" + text
    return text


def export_name(extension: str, epoch_s: float) -> str:
    """An export's file name, with its UTC time to the second: a second export of the day is a file of its
    own, not `(1)` beside the first, and the name says when the selection was taken."""
    return time.strftime(f"twin-events-%Y%m%dT%H%M%SZ.{extension}", time.gmtime(epoch_s))


def _iso(epoch_s: float) -> str:
    """To the millisecond, rounded as the export's `time` column (%.3f) is: the two columns of a row agree."""
    seconds, ms = divmod(round(epoch_s * 1000), 1000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds)) + f".{ms:03d}Z"


def events_csv(events: Iterable[Event]) -> str:
    """The events as CSV (a header, then one row each); every text cell neutralised."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(EXPORT_COLUMNS)
    for e in events:
        data = ";".join(f"{k}={v}" for k, v in e.data.items())
        writer.writerow(
            [
                e.id,
                f"{e.time:.3f}",
                _iso(e.time),
                neutralise_cell(e.level),
                neutralise_cell(e.kind),
                neutralise_cell(e.device),
                neutralise_cell(e.message),
                neutralise_cell(data),
            ]
        )
    return out.getvalue()


def events_json(events: Iterable[Event]) -> bytes:
    """The events as one JSON document, {"events": [...]}, with the same neutralised text as the CSV: an
    export is opened in spreadsheets too."""
    rows = [
        {
            "id": e.id,
            "time": e.time,
            "iso_time": _iso(e.time),
            "level": neutralise_cell(e.level),
            "kind": neutralise_cell(e.kind),
            "device": neutralise_cell(e.device),
            "message": neutralise_cell(e.message),
            "data": {neutralise_cell(k): neutralise_cell(v) for k, v in e.data.items()},
        }
        for e in events
    ]
    return msgspec.json.encode({"events": rows})
