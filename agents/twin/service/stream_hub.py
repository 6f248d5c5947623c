"""Live updates, built once per tick and shared by every client (the HTTP server's event loop runs it).

Before, every `/stream` client asked the agent for its whole state 30 times a second: ten viewers cost ten
times the state-building, and at a large fleet each state takes milliseconds. Here one task asks once per
tick, encodes each topic's frame once, and hands the same bytes to every subscriber of that topic:

- `state`: the /state document as an SSE frame, at `state_rate_hz`;
- `view:<device>`: one arm and the fleet's device ids (`DeviceView`), at `state_rate_hz`: what `twin view`
  reads. Asked of the arm's own mirror where the source can (console.ArmViewSource), so a viewer costs the
  same at two arms and at two thousand; the ids are read at most once a second. The whole state at
  `state_rate_hz` cost the agent 90 % of a core at 1,000 arms for a viewer that shows one arm, one arm's
  view 10 % (docs/performance.md, "The viewer's stream");
- `fleet`: the fleet summary (twin.service.console), at `console_rate_hz`;
- `arm:<device>`: one arm's state and alarms, at `console_rate_hz`, built only for devices someone watches;
- `events`: new events since the last tick, at `console_rate_hz`.

A subscriber keeps only the newest frame of a state-like topic (a slow client skips frames, it never queues
them) and a bounded backlog of event batches. The task sleeps while nobody subscribes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Sequence

import msgspec

from twin.service.console import (
    AlarmLister,
    ArmViewSource,
    EventSource,
    FleetRowSource,
    StateReader,
    arm_document,
    arm_view_of,
    fleet_parts,
    fleet_summary,
)
from twin.service.events import Event, EventQuery
from twin.service.state import AgentState, AlarmInfo, DeviceView, attention_mark, device_attention

log = logging.getLogger(__name__)

STATE = "state"
FLEET = "fleet"
EVENTS = "events"
ARM_PREFIX = "arm:"
VIEW_PREFIX = "view:"
# How old the device ids a view frame carries may be: a new arm shows in a viewer's list within this.
DEVICE_IDS_EVERY_S = 1.0
# Event batches a subscriber may fall behind before the oldest are dropped (the page then reloads the list).
EVENT_BACKLOG = 64
# Events fetched per tick at most; a burst larger than this arrives over the next ticks.
EVENTS_PER_TICK = 2000


def sse_frame(event: str, data: bytes) -> bytes:
    """One Server-Sent Event; `data` is one line of JSON (msgspec never puts a newline inside)."""
    return b"event: " + event.encode() + b"\ndata: " + data + b"\n\n"


class Subscription:
    """One client's view of one topic (on the event loop's thread only)."""

    def __init__(self, topic: str, backlog: int = 1) -> None:
        self.topic = topic
        self._frames: deque[bytes] = deque(maxlen=backlog)
        self._wake = asyncio.Event()
        self.closed = False
        self.skipped = 0

    def push(self, frame: bytes) -> None:
        if len(self._frames) == self._frames.maxlen:
            self.skipped += 1
        self._frames.append(frame)
        self._wake.set()

    def close(self) -> None:
        self.closed = True
        self._wake.set()

    async def next(self) -> bytes | None:
        """The frames pushed since the last call, joined; None once closed."""
        while not self._frames and not self.closed:
            self._wake.clear()
            await self._wake.wait()
        if self.closed:
            return None
        out = b"".join(self._frames)
        self._frames.clear()
        return out


def _state_rate(topic: str) -> bool:
    """Whether `topic` goes out at `state_rate_hz` (else at `console_rate_hz`)."""
    return topic == STATE or topic.startswith(VIEW_PREFIX)


class StreamHub:
    """The shared ticker (module doc). Create and use it on the server's event loop."""

    def __init__(self, source: StateReader, *, state_rate_hz: float, console_rate_hz: float) -> None:
        self._source = source
        self._state_interval = 1.0 / state_rate_hz
        self._console_interval = 1.0 / console_rate_hz
        self._subs: dict[str, set[Subscription]] = {}
        self._changed = asyncio.Event()
        self._closed = False
        self._event_cursor: int | None = None
        # (When read, on the loop's clock; the ids; their attention marks.)
        self._device_ids: tuple[float, list[str], dict[str, str]] | None = None
        self.ticks = 0

    @property
    def clients(self) -> int:
        return sum(len(subs) for subs in self._subs.values())

    def subscribe(self, topic: str, backlog: int = 1) -> Subscription:
        sub = Subscription(topic, backlog)
        if self._closed:
            sub.close()
            return sub
        self._subs.setdefault(topic, set()).add(sub)
        self._changed.set()
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        subs = self._subs.get(sub.topic)
        if subs is not None:
            subs.discard(sub)
            if not subs:
                del self._subs[sub.topic]
                if sub.topic == EVENTS:
                    self._event_cursor = None

    def close(self) -> None:
        self._closed = True
        for subs in self._subs.values():
            for sub in subs:
                sub.close()
        self._subs.clear()
        self._changed.set()

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        next_state = next_console = loop.time()
        while not self._closed:
            if not self._subs:
                self._changed.clear()
                await self._changed.wait()
                next_state = next_console = loop.time()
                continue
            now = loop.time()
            state_topics = any(_state_rate(t) for t in self._subs)
            console_topics = any(not _state_rate(t) for t in self._subs)
            state_due = state_topics and now >= next_state
            console_due = console_topics and now >= next_console
            if state_due or console_due:
                try:
                    await self._tick(state_due, console_due)
                except Exception:
                    log.exception("building the live update failed")
                self.ticks += 1
                now = loop.time()
                if state_due:
                    next_state = max(next_state + self._state_interval, now)
                if console_due:
                    next_console = max(next_console + self._console_interval, now)
            wake = min(
                next_state if any(_state_rate(t) for t in self._subs) else float("inf"),
                next_console if any(not _state_rate(t) for t in self._subs) else float("inf"),
            )
            self._changed.clear()
            if wake != float("inf"):
                # A new subscriber wakes the loop early: its first frame should not wait a whole interval.
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._changed.wait(), max(0.0, wake - loop.time()))

    async def _tick(self, state_due: bool, console_due: bool) -> None:
        source = self._source
        arms = [t for t in self._subs if t.startswith(ARM_PREFIX)] if console_due else []
        views = [t for t in self._subs if t.startswith(VIEW_PREFIX)] if state_due else []
        whole = state_due and STATE in self._subs
        fleet = console_due and FLEET in self._subs
        # The fleet's rows come without the whole state when the source can give them (building a state of
        # thousands of arms, in every worker of a sharded agent, is most of what a tick costs).
        rows_only = isinstance(source, FleetRowSource)
        # Likewise an arm page's arm, asked of its own mirror.
        arm_only = isinstance(source, ArmViewSource)
        whole_for_arms = bool(arms or views) and not arm_only
        state: AgentState | None = None
        if whole or whole_for_arms or (fleet and not rows_only):
            state = await asyncio.to_thread(source.state)
        if whole and state is not None:
            self._publish(STATE, sse_frame("state", state.to_json()))
        if views:
            await self._tick_views(views, state)
        alarms: Sequence[AlarmInfo] = ()
        if (whole_for_arms or (fleet and not rows_only)) and isinstance(source, AlarmLister):
            alarms = await asyncio.to_thread(source.alarms)
        if fleet:
            # The rows and the notices in one hop to a thread: both read the agent under its locks.
            rows, notices, listening, held = await asyncio.to_thread(fleet_parts, source, state, alarms)
            doc = fleet_summary(rows, time.time(), notices, listening, held=held)
            self._publish(FLEET, sse_frame("fleet", doc))
        for topic in arms:
            device = topic[len(ARM_PREFIX) :]
            view = await asyncio.to_thread(arm_view_of, source, device, state, alarms)
            self._publish(topic, sse_frame("arm", arm_document(device, view)))
        if console_due and EVENTS in self._subs and isinstance(source, EventSource):
            await self._tick_events(source)

    async def _tick_views(self, views: list[str], state: AgentState | None) -> None:
        """Each watched arm's view frame (module doc): the arm, and the device ids and marks as last read."""
        ids, attention = await self._ids(state)
        for topic in views:
            device = topic[len(VIEW_PREFIX) :]
            if state is not None:
                view = DeviceView(state.agent.time, state.devices.get(device), ids, attention)
            else:
                arm = await asyncio.to_thread(arm_view_of, self._source, device, None, ())
                view = DeviceView(arm.time, arm.state, ids, attention)
            self._publish(topic, sse_frame("device", view.to_json()))

    async def _ids(self, state: AgentState | None) -> tuple[list[str], dict[str, str]]:
        """The fleet's device ids, sorted, and the arms that want a look (DeviceView.attention): from `state`
        when there is one, else the source's fleet rows (or its state), read again when older than
        DEVICE_IDS_EVERY_S."""
        if state is not None:
            return sorted(state.devices), _attention_of(state)
        now = asyncio.get_running_loop().time()
        cached = self._device_ids
        if cached is not None and now - cached[0] < DEVICE_IDS_EVERY_S:
            return cached[1], cached[2]
        source = self._source
        if isinstance(source, FleetRowSource):
            rows = await asyncio.to_thread(source.fleet_rows)
            ids = sorted(row.device for row in rows)
            marks = ((r.device, attention_mark(r.status, r.alarm_severity, r.alarm_state)) for r in rows)
            attention = {device: mark for device, mark in marks if mark}
        else:
            whole = await asyncio.to_thread(source.state)
            ids, attention = sorted(whole.devices), _attention_of(whole)
        self._device_ids = (now, ids, attention)
        return ids, attention

    async def subscribe_events(self, after_id: int) -> Subscription:
        """A subscription to the events topic whose first frame holds the events after `after_id` (those a
        page has not loaded yet); the tail follows from where the hub is."""
        sub = self.subscribe(EVENTS, EVENT_BACKLOG)
        source = self._source
        if not isinstance(source, EventSource):
            return sub
        # The newest id before the backlog: an event stored between the two reads is then in the backlog, or
        # after the cursor, and so in the next tick. Read after it (as it was), such an event was in neither,
        # and a page that had loaded none missed it for good (a flaky test found it under load).
        newest = None if self._event_cursor is not None else await asyncio.to_thread(newest_event_id, source)
        backlog = await asyncio.to_thread(source.events, EventQuery(after_id=after_id, limit=EVENTS_PER_TICK))
        if self._event_cursor is None:
            # Nothing after `after_id`: the tail starts from the newest (a page from before a restart may
            # name an id this store has not reached).
            self._event_cursor = backlog[-1].id if backlog else newest
        sub.push(sse_frame("events", encode_events(backlog)))
        return sub

    async def _tick_events(self, source: EventSource) -> None:
        if self._event_cursor is None:
            return
        fresh = await asyncio.to_thread(
            source.events, EventQuery(after_id=self._event_cursor, limit=EVENTS_PER_TICK)
        )
        if fresh:
            self._event_cursor = fresh[-1].id
            self._publish(EVENTS, sse_frame("events", encode_events(fresh)))

    def _publish(self, topic: str, frame: bytes) -> None:
        for sub in self._subs.get(topic, ()):
            sub.push(frame)


def newest_event_id(source: EventSource) -> int:
    """The id of the newest event `source` holds (0 for none)."""
    newest = source.events(EventQuery(limit=1))
    return newest[-1].id if newest else 0


def encode_events(events: Sequence[Event]) -> bytes:
    return msgspec.json.encode(list(events))


def _attention_of(state: AgentState) -> dict[str, str]:
    marks = ((device, device_attention(d)) for device, d in state.devices.items())
    return {device: mark for device, mark in marks if mark}
