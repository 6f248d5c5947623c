"""The twin's events: the bounded store (ids, the tail, filters, subscribers), the emitters the runtime calls,
and the exports whose formula-like cells are neutralised."""

from __future__ import annotations

import csv
import functools
import io
import json
import logging
import os
import pickle
import random
import re
import signal
import subprocess
import threading
import time
from collections.abc import Sequence
from multiprocessing import Pipe
from pathlib import Path
from typing import Any

import msgspec
import pytest
from conftest import NO_BROKER, unbrokered_agent, wait_for
from twin.core.health import DeviceStatus
from twin.edge.payload import encode, make_payload
from twin.rig.local import LocalRig
from twin.service import console, events
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.events import (
    LOSING_HOLD_S,
    MAX_REJECTED_EVENTS_PER_INTERVAL,
    BrokerWatch,
    ClockWatch,
    Event,
    EventKind,
    EventLevel,
    EventQuery,
    EventStore,
    LossWatch,
    RateWatch,
    RejectionThrottle,
    StatusWatch,
    events_csv,
    events_json,
    export_name,
    neutralise_cell,
)
from twin.service.mirror import Mirror, PipeInbox, QueuedMessage, QueueInbox
from twin.service.shards import EVENTS_PER_ASK, EventsRequest, WorkerExit, WorkerPlan, events_of
from twin.transport.mailbox import InboundQueue


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def store(capacity: int = 100) -> tuple[EventStore, Clock]:
    clock = Clock()
    return EventStore(capacity, wall_clock=clock), clock


def test_events_are_numbered_and_the_oldest_go_first() -> None:
    s, _ = store(capacity=3)
    for i in range(5):
        s.emit(EventKind.STATUS, EventLevel.INFO, f"e{i}", device="arm-001")
    assert [e.message for e in s.query(EventQuery())] == ["e2", "e3", "e4"]
    assert [e.id for e in s.query(EventQuery())] == [3, 4, 5]
    assert s.last_id == 5 and s.dropped == 2 and len(s) == 3
    # The tail after an id: what a reader has not seen; after an id that fell out, what is left.
    assert [e.id for e in s.after(4)] == [5]
    assert [e.id for e in s.after(0)] == [3, 4, 5]
    assert s.after(5) == [] and s.after(99) == []
    assert [e.id for e in s.after(2, limit=2)] == [3, 4]


def raise_alarms(s: EventStore, devices: Sequence[str]) -> list[Event]:
    raised = [s.emit(EventKind.AGENT, EventLevel.INFO, "the agent started")]
    for device in devices:
        data = {"action": "raised", "alarm_id": f"{device}/elbow_flex/over_temperature"}
        raised.append(s.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device=device, data=data))
    return raised


def flood_statuses(s: EventStore, n: int) -> list[Event]:
    devices = [f"arm-{i % 300:03d}" for i in range(n)]
    return [s.emit(EventKind.STATUS, EventLevel.WARNING, f"{d} went STALE", device=d) for d in devices]


def test_a_flood_of_status_events_does_not_push_the_alarm_raises_out() -> None:
    # 300 arms on a loaded host going STALE and ONLINE filled the store and the raises went: the Sessions page
    # read "alarms raised: not known" on every row and "warning and worse" listed only STALE events.
    s, _ = store(capacity=100)
    raised = raise_alarms(s, ["arm-001", "arm-002", "arm-003"])
    flood = flood_statuses(s, 3 * s.capacity)
    assert len(s) == s.capacity and s.dropped == len(raised) + len(flood) - s.capacity
    assert s.query(EventQuery(kinds=frozenset({"alarm", "agent"}))) == raised
    warnings = s.query(EventQuery(min_level=EventLevel.WARNING))
    assert warnings[:3] == raised[1:] and warnings[3:] == flood[-(s.capacity - len(raised)) :]
    everything = s.after(0)
    assert everything == raised + flood[-(s.capacity - len(raised)) :] == s.query(EventQuery())
    assert [e.id for e in everything] == sorted({e.id for e in everything})  # in id order, once each
    assert s.last_id == len(raised) + len(flood)


def test_a_reader_that_saw_an_id_gets_exactly_the_kept_events_after_it() -> None:
    s, _ = store(capacity=50)
    made = raise_alarms(s, ["arm-001", "arm-002"]) + flood_statuses(s, 60)
    made += raise_alarms(s, ["arm-003"]) + flood_statuses(s, 90)
    held = {e.id for e in s.query(EventQuery())}
    kept = [e for e in made if e.id in held]  # made is in id order
    assert len(kept) == s.capacity and s.after(0) == kept
    assert [e.message for e in kept if e.kind != "status"] == [
        "the agent started",
        "hot",
        "hot",
        "the agent started",
        "hot",
    ]
    for seen in range(s.last_id + 2):
        expected = [e for e in kept if e.id > seen]
        assert s.after(seen) == expected, seen
        assert s.after(seen, limit=7) == expected[:7], seen


def test_the_kinds_that_are_not_bulk_have_a_share_a_flood_of_them_takes_no_more_than() -> None:
    # Either part takes what the other leaves: a flood of alarms pushes out older alarms once past its share.
    # The agent's start (alarms[0]) stays: the lifecycle kinds' reserve, which the alarms cannot take.
    s, _ = store(capacity=10)
    statuses = flood_statuses(s, 3)
    alarms = raise_alarms(s, [f"arm-{i:03d}" for i in range(20)])
    assert s.after(0) == statuses + alarms[:1] + alarms[-6:]
    more = flood_statuses(s, 30)
    assert s.after(0) == alarms[:1] + alarms[-4:] + more[-5:]  # each part down to its share


def lifecycle_events(s: EventStore) -> list[Event]:
    return [
        s.emit(EventKind.AGENT, EventLevel.INFO, "the agent started"),
        s.emit(EventKind.BROKER, EventLevel.WARNING, "broker connection lost"),
        s.emit(EventKind.WORKER, EventLevel.ERROR, "worker 1 exited (code -9)", data={"worker": 1}),
        s.emit(EventKind.CALIBRATION, EventLevel.INFO, "arm-001 calibration picked up", device="arm-001"),
        s.emit(EventKind.WORKER, EventLevel.INFO, "worker 1 running again", data={"worker": 1}),
    ]


def test_a_store_says_from_when_its_alarms_are_all_there_were() -> None:
    """The Sessions page's counts hold from this time: the store answers it from its own parts, so no reader
    rebuilds which kinds sit in which part."""
    s, _ = store(capacity=100)
    assert s.alarms_complete_from() is None  # holds nothing: not known
    s.emit(EventKind.STATUS, EventLevel.INFO, "arm-001 is ONLINE", device="arm-001", at=900.0)
    assert s.alarms_complete_from() == 900.0  # of the oldest event, when it holds no alarm or lifecycle one
    # The oldest alarm or lifecycle event, by the order the store took them (a collected round may date an
    # event just before one the agent made as it collected), not an older bulk one.
    s.emit(EventKind.WORKER, EventLevel.ERROR, "worker 1 exited", at=1_000.5)
    s.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-002", at=1_000.2)
    assert s.alarms_complete_from() == 1_000.5
    # A flood of alarms lets the oldest go while the worker's exit stays in its reserve: after the newest.
    for i in range(3 * s.capacity):
        s.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-002", at=2_000.0 + i)
    let_go = s.alarms_let_go_until
    assert let_go is not None and let_go > 2_000.0 and s.query(EventQuery(kinds=frozenset({"worker"})))
    assert s.alarms_complete_from() == let_go


def test_a_flood_of_alarms_does_not_push_the_agent_worker_and_broker_events_out() -> None:
    # An alarm storm (every arm of a hot cell raising and clearing) took the whole non-bulk share and pushed
    # out the agent's start, the worker that died and the broker loss that explain it.
    s, _ = store(capacity=100)
    lifecycle = lifecycle_events(s)
    storm = [
        s.emit(
            EventKind.ALARM, EventLevel.WARNING, "hot", device=f"arm-{i % 40:03d}", data={"action": "raised"}
        )
        for i in range(3 * s.capacity)
    ]
    assert len(s) == s.capacity and s.last_id == len(lifecycle) + len(storm)
    held = storm[-(s.capacity - len(lifecycle)) :]
    everything = lifecycle + held
    assert s.after(0) == everything == s.query(EventQuery(limit=1_000))
    assert [e.id for e in everything] == sorted({e.id for e in everything})  # in id order, once each
    for seen in (0, lifecycle[2].id, lifecycle[-1].id, held[0].id, held[50].id, s.last_id):
        expected = [e for e in everything if e.id > seen]
        assert s.after(seen) == expected and s.after(seen, limit=3) == expected[:3], seen
        assert s.query(EventQuery(after_id=seen, limit=1_000)) == expected, seen
    kinds = frozenset({"agent", "worker", "broker", "calibration"})
    assert s.query(EventQuery(kinds=kinds)) == lifecycle
    assert s.query(EventQuery(kinds=frozenset({"worker"}))) == [lifecycle[2], lifecycle[4]]
    assert s.query(EventQuery(kinds=frozenset({"alarm"}), limit=1_000)) == held
    worse = s.query(EventQuery(min_level=EventLevel.WARNING, limit=1_000))
    assert worse == lifecycle[1:3] + held
    assert s.query(EventQuery(min_level=EventLevel.ERROR)) == [lifecycle[2]]
    assert s.alarms_let_go_until == storm[len(storm) - len(held) - 1].time
    # Past their reserve, the lifecycle kinds' oldest go as the alarms' do: the reserve is a floor, not more.
    s, _ = store(capacity=100)
    many = [s.emit(EventKind.WORKER, EventLevel.INFO, f"worker {i} running") for i in range(20)]
    storm = [s.emit(EventKind.ALARM, EventLevel.WARNING, "hot") for _ in range(3 * s.capacity)]
    assert s.query(EventQuery(kinds=frozenset({"worker"}))) == many[-5:]


def test_a_restored_store_keeps_the_lifecycle_events_an_alarm_flood_came_after() -> None:
    s, _ = store(capacity=1000)
    made = lifecycle_events(s) + [s.emit(EventKind.ALARM, EventLevel.WARNING, "hot") for _ in range(900)]
    again, _ = store(capacity=100)
    assert again.restore(made) == 100
    assert again.after(0) == made[:5] + made[-95:]
    assert again.emit(EventKind.AGENT, EventLevel.INFO, "the agent started").id == len(made) + 1


def test_a_restored_store_keeps_the_alarms_a_flood_came_after() -> None:
    s, _ = store(capacity=1000)
    made = raise_alarms(s, ["arm-001"]) + flood_statuses(s, 900)
    again, _ = store(capacity=100)
    assert again.restore(made) == 100
    assert again.after(0) == made[:2] + made[-98:]
    assert again.emit(EventKind.AGENT, EventLevel.INFO, "the agent started").id == len(made) + 1


def test_queries_filter_by_device_level_kind_text_and_time() -> None:
    s, clock = store()
    clock.t = 10.0
    s.emit(EventKind.STATUS, EventLevel.INFO, "arm-001 is ONLINE", device="arm-001")
    clock.t = 20.0
    s.emit(EventKind.ALARM, EventLevel.WARNING, "Elbow hot", device="arm-002")
    clock.t = 30.0
    s.emit(EventKind.ALARM, EventLevel.ERROR, "elbow critical", device="arm-001")
    clock.t = 40.0
    s.emit(EventKind.BROKER, EventLevel.WARNING, "broker connection 0 lost")

    def messages(**filters: Any) -> list[str]:
        return [e.message for e in s.query(EventQuery(**filters))]

    assert messages(device="arm-001") == ["arm-001 is ONLINE", "elbow critical"]
    assert messages(min_level=EventLevel.WARNING) == [
        "Elbow hot",
        "elbow critical",
        "broker connection 0 lost",
    ]
    assert messages(min_level=EventLevel.ERROR) == ["elbow critical"]
    assert messages(kinds=frozenset({"alarm"})) == ["Elbow hot", "elbow critical"]
    assert messages(text="ELBOW") == ["Elbow hot", "elbow critical"]  # case-insensitive
    assert messages(text="arm-002") == ["Elbow hot"]  # the device matches too
    assert messages(since=20.0, until=40.0) == ["Elbow hot", "elbow critical"]
    assert messages(limit=2) == ["elbow critical", "broker connection 0 lost"]  # the newest
    with pytest.raises(ValueError, match="kind nope is not one of"):
        EventQuery(kinds=frozenset({"nope"}))
    with pytest.raises(ValueError, match="level 'loud' is not one of info, warning, error"):
        EventLevel.parse("loud")


def test_an_event_crosses_a_process_boundary_and_is_renumbered() -> None:
    worker, _ = store()
    worker.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-001", data={"value": 63.5, "x": None})
    (event,) = worker.after(0)
    assert event.data == {"value": "63.5", "x": ""}
    copied = pickle.loads(pickle.dumps(event))
    assert copied == event
    assert msgspec.json.decode(msgspec.json.encode(event), type=Event) == event
    front, _ = store()
    front.emit(EventKind.WORKER, EventLevel.INFO, "worker 0 running again")
    (ingested,) = front.ingest([copied])
    assert ingested.id == 2 and ingested.message == "hot" and ingested.time == event.time


def test_a_mirror_hands_a_burst_of_events_over_oldest_first_over_the_rounds() -> None:
    # More than one ask's worth between two rounds (2,000 arms going STALE at once, say): each ask takes the
    # next EVENTS_PER_ASK after the last one collected, so none is skipped.
    config = load_config(None, {"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    mirror = Mirror(config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(4))
    burst = 2 * EVENTS_PER_ASK + 7
    for n in range(burst):
        device = f"arm-{n:05d}"
        mirror._events.emit(EventKind.STATUS, EventLevel.WARNING, f"{device} is STALE", device=device)
    handed: list[Event] = []
    while len(handed) < burst:
        answer = events_of(mirror.answer(EventsRequest(handed[-1].id if handed else 0))).events
        assert 0 < len(answer) <= EVENTS_PER_ASK
        handed.extend(answer)
    assert [e.id for e in handed] == list(range(1, burst + 1))
    assert events_of(mirror.answer(EventsRequest(burst))).events == ()


def test_a_store_tells_a_reader_of_the_alarms_it_let_go_of_before_the_reader_had_them() -> None:
    store = EventStore(100)
    raised = {"action": "raised", "alarm_id": "arm-001/wrist_roll/over_temperature"}
    emitted = [
        store.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-001", data=raised, at=1_000.0 + i)
        for i in range(150)
    ]
    kept = {e.id for e in store.after(0, 1000)}
    lost = [e for e in emitted if e.id not in kept]
    assert lost and store.alarms_let_go_until == lost[-1].time
    assert store.alarms_let_go_after(0) == lost[-1].time
    assert store.alarms_let_go_after(lost[-1].id - 1) == lost[-1].time  # the newest one went unread
    assert store.alarms_let_go_after(lost[-1].id) is None  # each went after the reader had it
    assert store.alarms_let_go_after(store.last_id) is None


def test_alarms_a_mirror_let_go_of_before_the_agent_collected_them_leave_the_counts_unknown(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A mirror's store let go of alarm events before the agent's round collected them (a flood faster than
    the rounds): the agent's store, which never had them, held its raises complete from its own oldest event,
    so the Sessions page counted a session that had them as raising fewer. The mirror's answer now says
    until when they were lost, and the agent's store holds its alarms complete only after that. The mirror's
    store is made smaller than the agent's here, so the agent's lets go of none itself: with two workers its
    own letting go takes the oldest alarms of every worker, which need not be the lost ones' time."""
    small = functools.partial(EventStore, 100)
    monkeypatch.setattr("twin.service.mirror.EventStore", lambda _capacity, **kw: small(**kw))
    agent = unbrokered_agent(tmp_path, workers=1)
    try:
        assert agent._events.capacity > 1000
        mirror = agent._mirror
        assert mirror is not None
        raised = {"action": "raised", "alarm_id": "arm-001/wrist_roll/over_temperature"}
        with agent._events_lock:  # no round collects while the flood is made
            start = time.time()
            for i in range(150):
                at = start + i * 0.001
                mirror._events.emit(
                    EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-001", data=raised, at=at
                )
            lost_until = mirror._events.alarms_let_go_until
        assert lost_until is not None

        def complete_from() -> float | None:
            since = agent.alarms_complete_from()
            return since if since is not None and since >= lost_until else None

        wait_for(complete_from, 30, "the agent's alarms complete only after those the mirror let go of")
    finally:
        agent.stop()


def test_the_agent_and_each_mirror_keep_as_many_events_as_configured(tmp_path: Path) -> None:
    # [twin] events_capacity bounds a host's memory: the store a worker process's mirror keeps its events in
    # until the agent collects them, and the agent's own.
    overrides = {"telemetry.devices": ["*"], "telemetry.units": "ticks", "twin.events_capacity": 150}
    mirror = Mirror(
        load_config(None, overrides), inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(4)
    )
    for n in range(3 * 150):
        mirror._events.emit(
            EventKind.STATUS, EventLevel.WARNING, f"arm-{n:03d} is STALE", device=f"arm-{n:03d}"
        )
    assert len(events_of(mirror.answer(EventsRequest(0))).events) == 150
    agent = unbrokered_agent(tmp_path, workers=1, **{"twin.events_capacity": 150})
    try:
        assert agent._events.capacity == 150
    finally:
        agent.stop()


def test_subscribers_see_every_new_event_once() -> None:
    s, _ = store()
    seen: list[int] = []
    unsubscribe = s.subscribe(lambda e: seen.append(e.id))
    threads = [
        threading.Thread(target=lambda: [s.emit(EventKind.TWIN, EventLevel.INFO, "x") for _ in range(50)])
        for _ in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(seen) == list(range(1, 201))
    unsubscribe()
    s.emit(EventKind.TWIN, EventLevel.INFO, "after")
    assert len(seen) == 200


def test_status_watch_reports_transitions_only() -> None:
    s, _ = store()
    watch = StatusWatch(s)
    watch.arrived("arm-001")
    watch.sweep({"arm-001": "ONLINE"})
    watch.sweep({"arm-001": "ONLINE"})
    watch.sweep({"arm-001": "STALE"})
    # arm-002 was never told of: the first sweep that meets it is its baseline, no event; then its changes.
    watch.sweep({"arm-001": "OFFLINE", "arm-002": "ONLINE"})
    watch.sweep({"arm-001": "OFFLINE", "arm-002": "STALE"})
    # An OFFLINE arm heard once, then met by the sweep past its stale line: a return, told as such.
    watch.sweep({"arm-001": "STALE", "arm-002": "STALE"})
    got = [(e.device, e.level, e.data["status"], e.data["previous"]) for e in s.query(EventQuery())]
    assert got == [
        ("arm-001", "info", "ONLINE", ""),
        ("arm-001", "warning", "STALE", "ONLINE"),
        ("arm-001", "warning", "OFFLINE", "STALE"),
        ("arm-002", "warning", "STALE", "ONLINE"),
        ("arm-001", "info", "STALE", "OFFLINE"),
    ]
    assert s.query(EventQuery())[-1].message == (
        "arm-001 went STALE (was OFFLINE): heard again, not yet at its rate"
    )


def test_an_arrival_is_told_by_its_message_and_a_late_sweep_only_adds_a_transition() -> None:
    """The arrival is ONLINE whatever the first sweep after it reads (a busy host sweeps late: STALE); a
    device taken back from a checkpoint makes no arrival, and its first sweep says it was restored."""
    s, _ = store()
    watch = StatusWatch(s)
    watch.arrived("arm-001")
    watch.arrived("arm-001")  # a second record for the same arm (another message of the first batch)
    watch.sweep({"arm-001": "STALE"})
    watch.restored("arm-002")
    watch.arrived("arm-002")  # restored without its twin: its next message is no arrival
    watch.sweep({"arm-001": "STALE", "arm-002": "ONLINE"})
    watch.sweep({"arm-001": "STALE", "arm-002": "ONLINE"})
    got = [(e.device, e.message, e.data["status"], e.data["previous"]) for e in s.query(EventQuery())]
    assert got == [
        ("arm-001", "arm-001 is ONLINE (first message)", "ONLINE", ""),
        ("arm-001", "arm-001 went STALE (was ONLINE)", "STALE", "ONLINE"),
        ("arm-002", "arm-002 is ONLINE (restored)", "ONLINE", ""),
    ]


class _StarvedClock:
    """The mirror's monotonic clock as a function of what its worker has handled, so the test needs no
    timing: `at` (processed count, time) steps, the last one reached wins; `now` overrides them all."""

    def __init__(self, steps: list[tuple[int, float]]) -> None:
        self._steps = steps
        self.mirror: Mirror | None = None  # none yet while the mirror is made: nothing handled
        self.now: float | None = None

    def __call__(self) -> float:
        if self.now is not None:
            return self.now
        processed = self.mirror.processed if self.mirror is not None else 0
        return max(t for at, t in self._steps if processed >= at)


class _StarvedMirror:
    """A mirror on a _StarvedClock with a queue to feed: `put` hands it one message of each device received
    at `recv` and waits until the worker has handled them."""

    def __init__(self, steps: list[tuple[int, float]], seed: int) -> None:
        self.clock = _StarvedClock(steps)
        config = load_config(
            None, {"broker.url": NO_BROKER, "telemetry.devices": ["*"], "telemetry.units": "ticks"}
        )
        self.queue: InboundQueue[QueuedMessage] = InboundQueue()
        self.mirror = Mirror(config, inbox=QueueInbox(self.queue), budget=DeviceBudget(100), clock=self.clock)
        self.clock.mirror = self.mirror
        self.rng, self.sent = random.Random(seed), 0

    def put(self, devices: list[str], recv: float, edge_t: float) -> None:
        for d in devices:
            stamp = round((1.7e9 + recv) * 1000)
            payload = encode(make_payload(d, edge_t, "ticks", self.rng, timestamp_ms=stamp))
            self.queue.put(d, (f"dt/lerobot/{d}/telemetry", payload, recv, 1.7e9 + recv))
        self.sent += len(devices)
        sent = self.sent
        wait_for(lambda: self.mirror.processed >= sent, 60, f"{sent} messages handled")


def test_a_worker_behind_its_input_reports_no_arm_stale_and_a_silent_fleet_still_goes_stale() -> None:
    """A worker starved of CPU for 0.5 s takes its backlog in pieces (a pipe holds so much). The status
    sweep after the first piece used to read every other arm's silence on the wall clock: all of them went
    STALE, then ONLINE again, two events an arm for a hiccup of the host. Silence is now read on the time of
    the newest message handled, so only a fleet that is silent in the stream itself goes STALE."""
    arms = [f"arm-{n:03d}" for n in range(20)]
    # Round one is handled at 1000.0; the piece (two arms) at 1000.5, the worker having slept 0.5 s.
    starved = _StarvedMirror([(0, 1000.0), (len(arms) + 2, 1000.5)], seed=11)
    mirror, clock, put = starved.mirror, starved.clock, starved.put

    def status_events() -> list[tuple[str, str]]:
        found = mirror.events(EventQuery(kinds=frozenset({EventKind.STATUS.value})))
        return [(e.device, e.data["status"]) for e in found]

    mirror.start()
    try:
        put(arms, 999.9, 0.0)
        put(arms[:2], 1000.0, 0.1)  # the oldest of the backlog: received just after round one
        for k in range(5):
            put(arms, 1000.0 + 0.1 * k, 0.2 + 0.1 * k)
        assert status_events() == [(d, "ONLINE") for d in arms]
        clock.now = 1001.5  # then nothing: the inbox is empty, the silence real
        wait_for(lambda: len(status_events()) == 2 * len(arms), 60, "every arm STALE")
        assert sorted(status_events()[len(arms) :]) == [(d, "STALE") for d in arms]
    finally:
        mirror.stop()


def test_a_worker_behind_its_input_shows_its_arms_online_and_says_how_far_behind() -> None:
    """What a person reads (/state, the Fleet page, /healthz's statuses, the DevicesStale metric) is read
    where the worker stands in its input too, as the status events are: a worker 2 s behind used to show
    every arm STALE, and three minutes of that paged ArmsStale with advice about the arms. The lag itself
    is shown instead (`behind_s`, a Fleet page notice, the AgentBehind alarm on the internal latency)."""
    arms = [f"arm-{n:03d}" for n in range(5)]
    # The first round is handled at 1000.0; the second, received at 1000.0, only at 1002.0.
    starved = _StarvedMirror([(0, 1000.0), (2 * len(arms), 1002.0)], seed=5)
    mirror, clock = starved.mirror, starved.clock

    mirror.start()
    try:
        starved.put(arms, 999.9, 0.0)
        starved.put(arms, 1000.0, 0.1)
        wait_for(lambda: mirror.behind_s == pytest.approx(2.0), 60, "the worker 2 s behind")
        assert set(mirror.statuses().values()) == {DeviceStatus.ONLINE}
        rows = mirror.fleet_rows()
        assert {(r.status, r.behind_s) for r in rows} == {("ONLINE", 2.0)}
        report = mirror.report()
        assert {d.health.status for d in report.devices.values()} == {DeviceStatus.ONLINE}
        assert report.worker.behind_s == pytest.approx(2.0)
        _, (notice,), _, _ = console.fleet_parts(mirror)  # the Fleet page's parts
        assert notice.startswith("the agent is 2.0 s behind the arms' messages")
        assert "docs/scaling.md" in notice
        clock.now = 1003.0  # nothing more comes: an empty turn, and the silence is real
        wait_for(lambda: mirror.behind_s == 0.0, 60, "the worker caught up")
        assert set(mirror.statuses().values()) == {DeviceStatus.STALE}
        assert console.fleet_parts(mirror)[1] == []
    finally:
        mirror.stop()


def test_a_worker_held_in_one_batch_shows_its_lag_growing() -> None:
    """The lag used to be taken at the worker's status sweep only, after a batch: a worker held in one long
    batch (or hung in it) kept the low figure of the sweep before, and /state, the metric and the Fleet
    page's notice stayed quiet exactly while it fell behind. It is now read when asked: the age of the
    oldest message of the batch being handled counts too."""
    arms = [f"arm-{n:03d}" for n in range(3)]
    starved = _StarvedMirror([(0, 1000.0)], seed=7)
    mirror, clock = starved.mirror, starved.clock
    decode = mirror._decode_all
    held, entered, release = threading.Event(), threading.Event(), threading.Event()

    def held_decode(*args: Any) -> Any:
        if held.is_set():  # the worker thread waits here, in its batch, until the test lets it go
            entered.set()
            release.wait(60)
        return decode(*args)

    mirror._decode_all = held_decode  # type: ignore[method-assign]
    mirror.start()
    try:
        starved.put(arms, 999.9, 0.0)
        wait_for(lambda: mirror.behind_s < 1.0, 60, "the worker caught up")
        held.set()
        for d in arms:  # the next round, received at 1000.0, stays in the worker's hands
            stamp = round((1.7e9 + 1000.0) * 1000)
            payload = encode(make_payload(d, 0.1, "ticks", starved.rng, timestamp_ms=stamp))
            starved.queue.put(d, (f"dt/lerobot/{d}/telemetry", payload, 1000.0, 1.7e9 + 1000.0))
        assert entered.wait(60), "the worker never took the round"
        clock.now = 1005.0  # five seconds later, the worker still in that batch
        assert mirror.behind_s == pytest.approx(5.0)
        assert mirror.report().worker.behind_s == pytest.approx(5.0)
        assert {r.behind_s for r in mirror.fleet_rows()} == {5.0}
        _, (notice,), _, _ = console.fleet_parts(mirror)
        assert notice.startswith("the agent is 5.0 s behind the arms' messages")
    finally:
        release.set()
        mirror.stop()


class Conn:
    def __init__(
        self, successes: int, disconnections: int, last_error: str = "", refused: tuple[str, ...] = ()
    ) -> None:
        self.index, self.client_id = 0, "so101-twin-x-0"
        self.connection_successes, self.disconnections, self.last_error = (
            successes,
            disconnections,
            last_error,
        )
        self.refused = refused
        self.connected_at: float | None = None


def test_broker_watch_reports_connects_losses_and_reconnects() -> None:
    s, _ = store()
    watch = BrokerWatch(s)
    watch.sweep([Conn(0, 0)])
    watch.sweep([Conn(1, 0)])
    watch.sweep([Conn(1, 1, "AWS_ERROR_MQTT_UNEXPECTED_HANGUP")])
    watch.sweep([Conn(2, 1)])
    assert [e.message for e in s.query(EventQuery())] == [
        "broker connection 0 connected",
        "broker connection 0 lost: AWS_ERROR_MQTT_UNEXPECTED_HANGUP",
        "broker connection 0 reconnected",
    ]


def test_a_connect_event_carries_the_connects_own_time() -> None:
    """A walk's Events page had the broker's connect after the arms it let in: the watch read it up to a
    sweep later and stamped it then. The event now has the connection's own time."""
    s, _ = store()
    watch = BrokerWatch(s)
    connected = Conn(1, 0)
    connected.connected_at = 1_796_423_809.95
    watch.sweep([connected])
    assert [e.time for e in s.query(EventQuery())] == [1_796_423_809.95]


def test_broker_watch_reports_a_refused_subscription_once_and_its_grant() -> None:
    s, _ = store()
    watch = BrokerWatch(s)
    topic = "dt/lerobot/arm-001/telemetry"
    watch.sweep([Conn(1, 0)])
    for _ in range(3):  # refused for three sweeps: one event
        watch.sweep([Conn(1, 0, "subscribe: refused (NOT_AUTHORIZED)", refused=(topic,))])
    watch.sweep([Conn(1, 0)])
    events = s.query(EventQuery(kinds=frozenset({"broker"})))
    assert [(e.level, e.message) for e in events[1:]] == [
        (
            "error",
            f"broker connection 0: the subscription to {topic} is refused, so its arms are not heard; the "
            "agent's IAM identity must allow iot:Subscribe on it",
        ),
        ("info", f"broker connection 0: the subscription to {topic} is granted now"),
    ]
    assert events[1].data["error"] == "subscribe: refused (NOT_AUTHORIZED)"


def test_a_rejection_flood_makes_one_event_per_interval_with_its_count() -> None:
    s, _ = store()
    clock = Clock(0.0)
    throttle = RejectionThrottle(s, interval_s=10.0, clock=clock)
    for i in range(100):
        clock.t = i * 0.1  # 10 a second for 10 s
        throttle.rejected("arm-001", "not_json", "payload is not JSON")
    throttle.rejected("arm-002", "not_json", "payload is not JSON")  # another device is its own
    clock.t = 10.5
    throttle.rejected("arm-001", "not_json", "payload is not JSON")
    got = [(e.device, e.data["count"]) for e in s.query(EventQuery())]
    assert got == [("arm-001", "1"), ("arm-002", "1"), ("arm-001", "100")]
    assert "(100 since the last report)" in s.query(EventQuery())[-1].message


def test_a_flood_of_invented_device_ids_cannot_push_the_alarms_out_of_the_events() -> None:
    """Each invented device id is a key of its own: a walk's flood of garbage under random ids made 7,714
    rejected events in two minutes, on the way to pushing every alarm out of the newest 20,000."""
    s, _ = store(capacity=1000)
    clock = Clock(0.0)
    throttle = RejectionThrottle(s, interval_s=10.0, clock=clock)
    s.emit(EventKind.ALARM, EventLevel.ERROR, "arm-001/shoulder_lift/over_temperature_critical raised")
    for i in range(30_000):
        clock.t = i * 0.001  # 30 s of 1,000 a second
        throttle.rejected(f"junk-{i}", "not_json", "payload is not JSON")
    events = s.query(EventQuery(limit=100_000))
    cap = MAX_REJECTED_EVENTS_PER_INTERVAL
    assert events[0].kind == EventKind.ALARM and len(events) == 1 + 3 * cap  # three intervals' worth
    # The first event of each interval after the first says how many the one before held back.
    held = [int(e.data.get("held_back", 0)) for e in events[1:]]
    assert held[cap] == held[2 * cap] == 10_000 - cap and sum(held) == 2 * (10_000 - cap)
    assert f"({10_000 - cap} more rejected messages held back" in events[1 + cap].message


@pytest.mark.parametrize(
    ("cell", "expected"),
    [
        ('=HYPERLINK("http://x")', '\'=HYPERLINK("http://x")'),
        ("+1", "'+1"),
        ("-2+3", "'-2+3"),
        ("@SUM(A1)", "'@SUM(A1)"),
        ("  =1", "'  =1"),
        ("\t=1", "'\t=1"),
        ("arm-001", "arm-001"),
        ("", ""),
    ],
)
def test_formula_cells_are_neutralised(cell: str, expected: str) -> None:
    assert neutralise_cell(cell) == expected


def test_an_exports_two_time_columns_agree_to_the_millisecond() -> None:
    """A walk found `time` 1796423526.955 beside `iso_time` ...:06.954Z: one rounded, the other truncated."""
    s, _ = store()
    s.emit(EventKind.TWIN, EventLevel.INFO, "x")
    event = s.query(EventQuery())[0]
    for epoch in (1_796_423_526.9549, 1_796_423_526.9995, 1_796_423_526.0004):
        row = next(csv.DictReader(io.StringIO(events_csv([msgspec.structs.replace(event, time=epoch)]))))
        seconds, ms = row["time"].split(".")
        assert row["iso_time"].endswith(f"{int(seconds) % 60:02d}.{ms}Z"), row


def test_an_exports_file_is_named_by_its_utc_time() -> None:
    assert export_name("csv", 1_796_422_500.9) == "twin-events-20261204T221500Z.csv"


def test_exports_neutralise_text_and_keep_numbers() -> None:
    s, _ = store()
    s.emit(EventKind.REJECTED, EventLevel.WARNING, "=cmd|' /C calc'!A0", device="@arm", data={"reason": "-x"})
    rows = list(csv.DictReader(io.StringIO(events_csv(s.query(EventQuery())))))
    assert rows[0]["message"] == "'=cmd|' /C calc'!A0"
    assert rows[0]["device"] == "'@arm" and rows[0]["data"] == "reason=-x"
    assert rows[0]["id"] == "1" and float(rows[0]["time"]) == 1000.0
    doc = json.loads(events_json(s.query(EventQuery())))
    assert doc["events"][0]["message"].startswith("'=") and doc["events"][0]["data"] == {"reason": "'-x"}
    assert doc["events"][0]["time"] == 1000.0


def test_a_time_range_whose_end_is_not_after_its_start_is_a_bad_query(tmp_path: Path) -> None:
    """A walk swapped since and until and got an empty list, as if nothing had happened then."""
    from conftest import http_get

    agent = unbrokered_agent(tmp_path, 1)
    try:
        for path in ("/api/events", "/api/events.csv"):
            status, _, body = http_get(f"{agent.http_url}{path}?since=1796423900&until=1796423500")
            doc = json.loads(body)
            assert status == 400 and doc["error"] == "bad_query", doc
            assert "until (1796423500.0) must be after since (1796423900.0)" in doc["detail"]
        assert http_get(f"{agent.http_url}/api/events?since=1796423500&until=1796423900")[0] == 200
        # A walk: `after=xyz`, `limit=-1` and `limit=abc` were ignored (all events again); `limit=0` gave one.
        for query in ("after=xyz", "after=-3", "limit=-1", "limit=abc", "limit=0"):
            for path in ("/api/events", "/api/events.csv", "/api/stream/events"):
                if path.endswith("stream/events") and not query.startswith("after"):
                    continue
                status, _, body = http_get(f"{agent.http_url}{path}?{query}")
                doc = json.loads(body)
                assert status == 400 and doc["error"] == "bad_query", (path, query, doc)
                name, _, value = query.partition("=")
                assert f"{name} = {value!r} is not a whole number" in doc["detail"], doc
        assert http_get(f"{agent.http_url}/api/events?after=0&limit=1")[0] == 200
    finally:
        agent.stop()


def arm_001_heard(tmp_path: Path) -> Any:
    """An agent without a broker that has had one message of arm-001, and its arrival event."""
    agent = unbrokered_agent(tmp_path, 1, **{"telemetry.devices": ["arm-001"]})
    try:
        rng = random.Random(5)
        agent.feed("dt/lerobot/arm-001/telemetry", encode(make_payload("arm-001", 0.0, "ticks", rng)))
        wait_for(lambda: agent.events(EventQuery(device="arm-001")), 30, "arm-001's arrival event")
    except BaseException:
        agent.stop()
        raise
    return agent


def test_a_known_arm_whose_events_aged_out_is_not_called_a_slip_of_the_id(tmp_path: Path) -> None:
    """The detail for an id with no event told the operator to check the id, untrue of an arm on the Fleet
    page whose events a flood of other arms' pushed out of the store."""
    from conftest import http_get

    settings = {"telemetry.devices": ["*"], "twin.events_capacity": 100}
    agent = unbrokered_agent(tmp_path, 1, **settings)
    try:
        rng, others = random.Random(5), iter(range(100, 10_000))
        agent.feed("dt/lerobot/arm-001/telemetry", encode(make_payload("arm-001", 0.0, "ticks", rng)))
        wait_for(lambda: agent.events(EventQuery(device="arm-001")), 30, "arm-001's arrival event")

        def aged_out() -> bool:
            for _ in range(10):
                other = f"arm-{next(others)}"
                agent.feed(f"dt/lerobot/{other}/telemetry", encode(make_payload(other, 0.0, "ticks", rng)))
            return not agent.events(EventQuery(device="arm-001"))

        wait_for(aged_out, 60, "arm-001's events pushed out by other arms'", interval=0.1)
        doc = json.loads(http_get(f"{agent.http_url}/api/events?device=arm-001")[2])
        assert doc["events"] == [] and "knows 'arm-001'" in doc["detail"], doc
        assert "events_capacity" in doc["detail"] and "check the id" not in doc["detail"], doc
    finally:
        agent.stop()


def test_a_listed_arm_never_heard_is_said_to_have_no_event_yet(tmp_path: Path) -> None:
    """A review: an arm listed in telemetry.devices and never heard was said to have had its events aged
    out, and told to raise events_capacity, which does nothing for it."""
    from conftest import http_get

    agent = unbrokered_agent(tmp_path, 1, **{"telemetry.devices": ["arm-007"]})
    try:
        doc = json.loads(http_get(f"{agent.http_url}/api/events?device=arm-007")[2])
        assert doc["events"] == [] and "no message of it since it started" in doc["detail"], doc
        assert "events_capacity" not in doc["detail"], doc
    finally:
        agent.stop()


def test_a_filter_that_matches_nothing_answers_the_newest_id(tmp_path: Path) -> None:
    """The Events page starts its stream at `last_id`: a device filter with no match answered the `after` it
    was given, so the page's stream began again at every other arm's first event."""
    from conftest import http_get

    agent = arm_001_heard(tmp_path)
    try:
        url = f"{agent.http_url}/api/events"
        everything = json.loads(http_get(url)[2])
        newest = everything["events"][-1]["id"]
        assert everything["last_id"] == newest > 0, everything
        for query in ("device=arm-999", "device=arm-999&after=0", "kind=broker&level=error"):
            doc = json.loads(http_get(f"{url}?{query}")[2])
            assert doc["events"] == [] and doc["last_id"] >= newest, (query, doc)
        # A filter with matches still ends at its last match or later, never before it.
        doc = json.loads(http_get(f"{url}?device=arm-001")[2])
        assert doc["events"] and doc["last_id"] >= doc["events"][-1]["id"], doc
        # An id from beyond this store (a page from a run before) is kept, as before.
        assert json.loads(http_get(f"{url}?after={newest + 500}")[2])["last_id"] == newest + 500
    finally:
        agent.stop()


def test_a_device_the_agent_holds_no_event_of_is_named_in_the_answer(tmp_path: Path) -> None:
    """A walk asked for the events of a mistyped id and got an empty list, as for a known arm whose filters
    match nothing. An id with no event at all is said so, with what to check; a known one's empty
    selection is not."""
    from conftest import http_get

    agent = arm_001_heard(tmp_path)
    try:
        url = f"{agent.http_url}/api/events"
        doc = json.loads(http_get(f"{url}?device=ARM-001")[2])
        assert doc["events"] == [] and "no event of 'ARM-001' at all" in doc["detail"], doc
        assert "Fleet page" in doc["detail"] and "device_part=" in doc["detail"], doc
        # Known, but its selection empty (no broker event of it): no such word.
        assert "detail" not in json.loads(http_get(f"{url}?device=arm-001&kind=broker")[2])
        assert "detail" not in json.loads(http_get(f"{url}?device=arm-001")[2])
    finally:
        agent.stop()


def test_a_servo_error_bit_is_an_alarm_and_an_event_naming_the_servo(tmp_path: Path) -> None:
    """A walk: the servo's status bits (the overload bit on wrist_flex) were shown and raised nothing."""
    from conftest import http_get

    agent = unbrokered_agent(tmp_path, 2, **{"telemetry.devices": ["arm-001"]})
    try:
        rng = random.Random(5)
        t0 = int(time.time() * 1000)
        for i in range(3):
            payload = make_payload("arm-001", 0.1 * i, "ticks", rng, timestamp_ms=t0 + 100 * i)
            payload["joints"]["wrist_flex"]["status"] = 32 if i else 0
            agent.feed("dt/lerobot/arm-001/telemetry", encode(payload))

        def raised() -> Any:
            doc = json.loads(http_get(f"{agent.http_url}/alarms")[2])
            return next((a for a in doc["alarms"] if a["kind"] == "servo_error"), None)

        alarm = wait_for(raised, 60, "the servo_error alarm of arm-001")
        assert (alarm["joint"], alarm["severity"], alarm["state"]) == ("wrist_flex", "critical", "ACTIVE"), (
            alarm
        )
        assert "wrist_flex servo (motor id 4) reports an error of its own: overload" in alarm["message"]
        found = wait_for(
            lambda: agent.events(EventQuery(kinds=frozenset({"alarm"}), device="arm-001")), 30, "its event"
        )
        assert "wrist_flex servo (motor id 4)" in found[-1].message, found
    finally:
        agent.stop()


def test_clock_watch_reports_an_edge_clock_far_off_twice_in_a_row_once_and_its_return() -> None:
    """A walk set an arm's clock 300 s ahead: accepted, and shown only as edge_clock_offset_s = -300."""
    s, _ = store()
    watch = ClockWatch(s)

    def sweep(**offsets: float) -> list[tuple[str, str, str]]:
        watch.sweep({d.replace("_", "-"): o for d, o in offsets.items()})
        return [(e.device, e.level, e.message) for e in s.query(EventQuery())]

    # One sweep off is no report (a burst of transit); back under the line forgets it.
    assert sweep(arm_001=-300.0, arm_002=0.05) == []
    assert sweep(arm_001=0.1, arm_002=0.05) == []
    assert sweep(arm_001=-300.0, arm_002=3.5) == []
    (ahead, behind) = sweep(arm_001=-300.2, arm_002=3.4)
    assert ahead[:2] == ("arm-001", "warning") and "about 300 s ahead of the agent's" in ahead[2]
    assert "NTP" in ahead[2] and "timedatectl" in ahead[2]
    assert behind[:2] == ("arm-002", "warning") and "about 3 s behind the agent's" in behind[2]
    assert len(sweep(arm_001=-299.0, arm_002=3.0)) == 2  # once, however long it lasts
    assert len(sweep(arm_001=-1.5, arm_002=3.0)) == 2  # not yet within the back line
    (*_, back) = sweep(arm_001=0.2, arm_002=3.0)
    assert back[:2] == ("arm-001", "info") and "agrees with the agent's again" in back[2]
    # A forgotten arm, or one with no sample in its window, leaves nothing behind.
    watch.forget("arm-002")
    assert len(sweep(arm_001=0.2)) == 3


def test_an_agent_tells_of_an_arm_whose_clock_is_minutes_ahead(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(events, "CLOCK_INTERVAL_S", 0.2)
    agent = unbrokered_agent(tmp_path, 1, **{"telemetry.devices": ["arm-001"]})
    try:
        rng = random.Random(5)

        def told() -> Any:
            ahead_ms = int(time.time() * 1000) + 300_000
            payload = encode(make_payload("arm-001", 0.0, "ticks", rng, timestamp_ms=ahead_ms))
            agent.feed("dt/lerobot/arm-001/telemetry", payload)
            found = agent.events(EventQuery(kinds=frozenset({"twin"}), device="arm-001"))
            return next((e for e in found if "clock of arm-001" in e.message), None)

        event = wait_for(told, 60, "the event of arm-001's clock", interval=0.05)
        assert event.level == "warning" and "300 s ahead" in event.message, event
    finally:
        agent.stop()


@pytest.mark.slow
def test_rate_watch_reports_a_device_held_over_the_line_once_and_its_return() -> None:
    s, _ = store()
    watch = RateWatch(s, expected_rate_hz=10.0)
    hold = events.CROWDED_HOLD_S

    def sweep(at: float, **rates: float) -> list[tuple[str, str, str, float]]:
        watch.sweep({d.replace("_", "-"): r for d, r in rates.items()}, at)
        return [(e.device, e.level, e.data["rate"], float(e.data["rate_hz"])) for e in s.query(EventQuery())]

    # A burst shorter than the hold (a spooled backlog after a reconnect) is no report.
    assert sweep(0.0, arm_001=25.0, arm_002=10.0) == []
    assert sweep(hold - 1.0, arm_001=25.0, arm_002=10.0) == []
    assert sweep(hold, arm_001=10.0, arm_002=10.0) == []
    # Held over the line for the hold: once, however long it lasts.
    assert sweep(hold + 1.0, arm_001=20.0, arm_002=10.0) == []
    assert sweep(2 * hold + 1.0, arm_001=20.0, arm_002=10.0) == [("arm-001", "warning", "crowded", 20.0)]
    assert len(sweep(3 * hold, arm_001=19.0, arm_002=10.0)) == 1
    # Under the report line but over the clearing one: still reported, no new event.
    assert len(sweep(3 * hold + 5.0, arm_001=15.0, arm_002=10.0)) == 1
    assert watch.reported == ("arm-001",)
    # Back near the expected rate: one info event.
    assert sweep(3 * hold + 10.0, arm_001=10.2, arm_002=10.0)[1:] == [("arm-001", "info", "expected", 10.2)]
    assert watch.reported == ()
    (warning, back) = s.query(EventQuery())
    assert warning.kind == "twin" and "two edges may publish under its device id" in warning.message
    assert (
        "2.0 times the expected 10 Hz" in warning.message
        and "arm-001 sends 10.2 valid messages/s now" in back.message
    )
    # A device no longer heard from (evicted, or moved to another worker) is forgotten, not cleared.
    sweep(4 * hold, arm_002=30.0)
    sweep(5 * hold + 1.0, arm_002=30.0)
    assert watch.reported == ("arm-002",)
    sweep(5 * hold + 2.0, arm_001=10.0)
    assert watch.reported == () and len(s.query(EventQuery())) == 3


def test_rate_watch_takes_back_a_report_and_waits_for_the_rates_to_fill_before_a_return() -> None:
    # What a restarted worker does with its checkpoint's crowded devices: no second report while the arm stays
    # over the line; the rates start again from nothing, so no "back" before the settle time either.
    s, _ = store()
    watch = RateWatch(s, expected_rate_hz=10.0)
    settle = events.RESTORED_SETTLE_S
    watch.restore(["arm-001", "arm-009"], 100.0)
    assert watch.reported == ("arm-001", "arm-009")
    watch.sweep({"arm-001": 0.5}, 100.0 + settle / 2)  # a fresh meter's first reading; arm-009 not heard
    assert watch.reported == ("arm-001",) and s.query(EventQuery()) == []
    for at in (120.0, 140.0, 160.0):
        watch.sweep({"arm-001": 20.0}, at)
    assert s.query(EventQuery()) == []
    watch.sweep({"arm-001": 10.0}, 165.0)
    (back,) = s.query(EventQuery())
    assert (back.level, back.data["rate"]) == ("info", "expected") and watch.reported == ()


def test_two_edges_under_one_device_id_are_reported(
    rig: LocalRig, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # The edge component's default id is arm-001 on every arm: three simulators publish as arm-001 at 10 Hz
    # each (30 Hz against the 18 Hz line: a margin for a loaded host's slower edges), one of them arm-002
    # too. The hold and the sweep interval are shortened here (30 s and 5 s in service).
    monkeypatch.setattr(events, "CROWDED_HOLD_S", 2.0)
    monkeypatch.setattr(events, "RATE_INTERVAL_S", 0.5)
    caplog.set_level(logging.WARNING, logger="twin.service.events")
    agent = rig.start_agent({"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    rig.start_edge(["arm-001", "arm-002"], rate_hz=10.0, seed=1)
    rig.start_edge(["arm-001"], rate_hz=10.0, seed=2)
    rig.start_edge(["arm-001"], rate_hz=10.0, seed=3)
    # Only arm-001's are looked at: the thresholds themselves are the test above's (a loaded host's edge
    # that stalls and catches up could hold arm-002 over the line for the shortened hold).
    crowded = EventQuery(kinds=frozenset({EventKind.TWIN.value}), device="arm-001")
    wait_for(lambda: agent.events(crowded), 60, "the crowded arm's event")
    (event, *_) = agent.events(crowded)
    assert event.level == "warning" and float(event.data["rate_hz"]) >= 18.0, event
    assert "each arm needs its own deviceId" in event.message
    logged = [r.getMessage() for r in caplog.records if r.getMessage().startswith("arm-001 sends")]
    assert logged[0] == event.message


def test_an_arm_arrives_in_the_events_with_its_first_message_not_before(rig: LocalRig) -> None:
    # Configured arms not heard from count as silent since start-up: STALE after 0.3 s, OFFLINE after
    # offline_after_s. That is no arrival: arm-001 never sends and makes no status event, and arm-002's first
    # status event is its arrival, made once its messages come (after both were OFFLINE, so status sweeps ran
    # over the whole of their silence first).
    overrides = {"telemetry.devices": ["arm-001", "arm-002"], "telemetry.units": "ticks"}
    agent = rig.start_agent({**overrides, "health.offline_after_s": 2.0})
    wait_for(
        lambda: all(d.health.status is DeviceStatus.OFFLINE for d in agent.state().devices.values()),
        30,
        "both configured arms OFFLINE before any message",
    )
    rig.start_edge(["arm-002"], variant="ticks", rate_hz=10.0)
    status = EventQuery(kinds=frozenset({EventKind.STATUS.value}))
    wait_for(lambda: any(e.device == "arm-002" for e in agent.events(status)), 30, "arm-002's arrival event")
    events = [(e.device, e.message) for e in agent.events(status)]
    assert [d for d, _ in events] == ["arm-002"] * len(events), events
    assert events[0][1] == "arm-002 is ONLINE (first message)", events


def test_the_broker_connect_comes_before_the_arrivals_it_let_in(rig: LocalRig) -> None:
    """An edge already publishing when the agent starts: its arm arrives within milliseconds of the connect.
    The connect was stamped when a sweep read it, up to half a second later, so the Events page put it after
    the arrivals (a walk's incident timeline). It carries the connect's own time now."""
    rig.start_edge(["arm-005"], variant="ticks", rate_hz=10.0)
    agent = rig.start_agent({"telemetry.devices": ["arm-005"], "telemetry.units": "ticks"})
    broker = EventQuery(kinds=frozenset({EventKind.BROKER.value}))
    status = EventQuery(kinds=frozenset({EventKind.STATUS.value}), device="arm-005")
    arrival = wait_for(lambda: agent.events(status), 30, "arm-005's arrival")[0]
    connect = wait_for(lambda: agent.events(broker), 30, "the broker connect event")[0]
    assert connect.message == "broker connection 0 connected"
    assert connect.time <= arrival.time, (connect, arrival)


@pytest.mark.slow
def test_two_workers_arrivals_are_numbered_in_the_order_they_happened(tmp_path: Path) -> None:
    # Each worker's events reach the agent's store every half second; one round's are merged by time, so
    # arrivals handled alternately by the two workers come out alternately, not one worker's all first.
    plan = WorkerPlan(2)
    names = (f"arm-{n:03d}" for n in range(1, 100))
    by_worker: dict[int, list[str]] = {0: [], 1: []}
    for name in names:
        if len(by_worker[plan.worker_of(name)]) < 4:
            by_worker[plan.worker_of(name)].append(name)
    alternate = [d for pair in zip(by_worker[0], by_worker[1], strict=True) for d in pair]
    agent = unbrokered_agent(tmp_path, 2)
    try:
        rng = random.Random(3)
        for device in alternate:  # each handled before the next is fed: the order they happened in
            agent.feed(f"dt/lerobot/{device}/telemetry", encode(make_payload(device, 0.0, "ticks", rng)))
            wait_for(lambda d=device: d in agent.state().devices, 30, f"{device} handled")
        status = EventQuery(kinds=frozenset({EventKind.STATUS.value}))

        def arrivals() -> list[Event]:  # (each arm, silent after its message, goes STALE later on)
            return [e for e in agent.events(status) if e.message.endswith("(first message)")]

        wait_for(lambda: len(arrivals()) == len(alternate), 30, "every arm's arrival collected")
        arrived = arrivals()
        assert [e.device for e in arrived] == alternate, [(e.device, e.time) for e in arrived]
        assert [e.time for e in arrived] == sorted(e.time for e in arrived)
    finally:
        agent.stop()


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_events_a_mirror_makes_as_the_agent_stops_are_listed(tmp_path: Path, workers: int) -> None:
    # Fed and stopped at once: the messages are handled while the mirrors drain their queues at the stop,
    # after the last round that collects events. Their arrivals (an alarm's raise, likewise) still reach the
    # agent's list, and through it the alert publisher.
    agent = unbrokered_agent(tmp_path, workers)
    devices = [f"arm-{n:03d}" for n in range(1, 5)]
    try:
        rng = random.Random(4)
        for device in devices:
            agent.feed(f"dt/lerobot/{device}/telemetry", encode(make_payload(device, 0.0, "ticks", rng)))
    finally:
        agent.stop()
    status = EventQuery(kinds=frozenset({EventKind.STATUS.value}))
    arrived = [e.device for e in agent.events(status) if e.message.endswith("(first message)")]
    assert sorted(arrived) == devices


@pytest.mark.slow
def test_a_worker_started_again_just_before_the_stop_has_its_last_events_listed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The supervisor's restart can end as the stop begins, before a round notices the new process, which
    # numbers its events from 1: the stop must not take them for ones it collected from the old process.
    agent = unbrokered_agent(tmp_path, 2)
    plan, rng = WorkerPlan(2), random.Random(5)
    mine = [d for d in (f"arm-{n:03d}" for n in range(1, 200)) if plan.worker_of(d) == 0][:7]
    status = EventQuery(kinds=frozenset({EventKind.STATUS.value}))

    def arrived() -> list[str]:
        return [e.device for e in agent.events(status) if e.message.endswith("(first message)")]

    try:
        for device in mine[:6]:  # worker 0's events numbered past what its next process will make
            agent.feed(f"dt/lerobot/{device}/telemetry", encode(make_payload(device, 0.0, "ticks", rng)))
        wait_for(lambda: len(arrived()) == 6, 30, "the first arrivals collected")
        shard = agent._shards[0]
        # In its checkpoint too, so the next process, restored from it, is sent none of them again.
        wait_for(lambda: (c := shard.checkpoint) is not None and c.taken >= 6, 30, "a checkpoint with them")
        monkeypatch.setattr(agent, "_collect_events", lambda: None)  # no round sees what follows
        os.kill(shard.pid, signal.SIGKILL)
        wait_for(lambda: shard.restarts == 1 and shard.answering, 60, "worker 0 running again")
        last = mine[6]
        agent.feed(f"dt/lerobot/{last}/telemetry", encode(make_payload(last, 0.0, "ticks", rng)))
        wait_for(lambda: last in agent.state().devices, 30, f"{last} handled by the new process")
    finally:
        agent.stop()
    assert arrived() == [*mine[:6], last]


@pytest.mark.slow
def test_a_worker_started_again_before_a_round_saw_it_dead_is_told_as_an_exit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The supervisor starts a worker that ran a while again within the round that finds it dead, before that
    # round's watch; a walk's kill -9 left only "running again" (info) on the Events page, no error.
    agent = unbrokered_agent(tmp_path, 2)
    worker = EventQuery(kinds=frozenset({EventKind.WORKER.value}))
    try:
        shard = agent._shards[1]
        wait_for(lambda: shard.answering, 60, "worker 1 running")
        collect = agent._collect_events
        monkeypatch.setattr(agent, "_collect_events", lambda: None)  # no round sees it dead
        victim = shard.pid
        os.kill(victim, signal.SIGKILL)
        wait_for(lambda: shard.restarts == 1 and shard.answering, 60, "worker 1 running again")
        monkeypatch.setattr(agent, "_collect_events", collect)
        wait_for(
            lambda: any("running again" in e.message for e in agent.events(worker)), 30, "the restart told"
        )
        told = [e for e in agent.events(worker) if e.level == "error"]
    finally:
        agent.stop()
    # The exit names the process that died and how, not its successor (whose pid the state shows by then).
    assert [e.message for e in told] == [
        f"worker 1 (pid {victim}) exited, killed by SIGKILL (signal 9); it is started again from its last "
        "checkpoint, its arms kept"
    ]
    assert told[0].data == {"worker": "1", "pid": str(victim), "exit_code": str(-signal.SIGKILL)}
    assert shard.pid != victim


def test_a_worker_exit_says_how_it_ended_and_blames_no_worker_for_its_fork_servers_255() -> None:
    """The Events page said "(pid X) exited, exit code 255" of a worker that still ran when its fork server
    was killed (multiprocessing's code for a lost server); the log already named the fork server."""
    dead = WorkerExit.seen(_a_dead_pid(), 255)
    assert not dead.server_lost and dead.how() == "exited, exit code 255"
    running = WorkerExit.seen(os.getpid(), 255)
    assert running.server_lost
    assert running.how() == "can no longer be watched: the fork server that started it is gone (killed?)"
    assert WorkerExit.seen(os.getpid(), 1).how() == "exited, exit code 1"  # only 255 is the server's
    assert WorkerExit.seen(os.getpid(), None).how() == "exited, exit code unknown"
    assert WorkerExit.seen(os.getpid(), -9).how() == "exited, killed by SIGKILL (signal 9)"
    assert WorkerExit(1, -200).how() == "exited, killed by an unknown signal (signal 200)"


def _a_dead_pid() -> int:
    """The pid of a child that has exited and been reaped."""
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def test_the_events_page_offers_every_kind_in_its_filter() -> None:
    # The page's kind filter is written out in its script: a kind added to EventKind must be added there too,
    # or its events can be found only under "any kind".
    script = (Path(events.__file__).parent / "console_ui" / "events.js").read_text()
    (listed,) = re.findall(r'\.\.\.\[([^\]]*)\]\.map\(\(k\) => el\("option"', script)
    assert sorted(json.loads(f"[{listed}]")) == sorted(k.value for k in EventKind)


@pytest.mark.parametrize("arrives_at_read", [1, 2])
def test_an_event_stored_between_the_hubs_reads_reaches_the_first_page(arrives_at_read: int) -> None:
    """A flaky console test, traced under load: the hub read a page's backlog (nothing), then the store's
    newest id for its cursor; an event stored in between was in neither, and never reached the page."""
    import asyncio

    from twin.service.stream_hub import StreamHub

    class Source:
        def __init__(self) -> None:
            self.store, _ = store()
            self.reads = 0

        def state(self) -> Any:
            raise NotImplementedError

        def events(self, query: EventQuery) -> list[Event]:
            self.reads += 1
            if self.reads == arrives_at_read:  # the supervisor collects an event while the hub reads
                self.store.emit(EventKind.STATUS, EventLevel.INFO, "arm-001 is ONLINE", device="arm-001")
            return self.store.query(query)

    async def sent() -> list[str]:
        source = Source()
        hub = StreamHub(source, state_rate_hz=10.0, console_rate_hz=4.0)
        sub = await hub.subscribe_events(0)  # a page that loaded nothing
        await hub._tick_events(source)  # the next console tick
        joined = await sub.next()  # every frame pushed so far
        assert joined is not None
        lines = [line[len(b"data: ") :] for line in joined.split(b"\n") if line.startswith(b"data: ")]
        return [e["message"] for line in lines for e in json.loads(line)]

    assert asyncio.run(sent()) == ["arm-001 is ONLINE"]


def test_an_arm_whose_id_two_edges_share_is_not_sent_to_look_at_its_network() -> None:
    """A walk: two edge simulators as arm-003 (none lost) made "arm-003 is losing 75 % of its messages ...:
    its edge's network, or its broker connection" beside the two-edges warning; the loss estimate reads the
    two interleaved timestamp grids as one finer one with holes. The loss warning now names the shared id."""
    s, _ = store()
    watch = events.FleetWatch(s)
    for at in (0.0, max(events.CROWDED_HOLD_S, LOSING_HOLD_S)):  # as the mirror: rates, then losses
        watch.rates({"arm-003": 20.0, "arm-004": 10.0}, at)
        watch.losses({"arm-003": (100, 300), "arm-004": (60, 30)}, at)
    found = {(e.device, e.data.get("rate") or e.data.get("loss")): e.message for e in s.query(EventQuery())}
    assert set(found) == {("arm-003", "crowded"), ("arm-003", "losing"), ("arm-004", "losing")}, found
    assert "give each arm its own deviceId" in found["arm-003", "losing"], found
    assert "its edge's network" not in found["arm-003", "losing"]
    assert "its edge's network" in found["arm-004", "losing"]


def test_the_loss_watch_waits_out_a_burst_and_a_few_lost_samples_and_forgets_an_arm() -> None:
    s, _ = store()
    watch = LossWatch(s)
    # A reconnect's burst: a third lost for less than the hold, then whole. A slow arm: 40 % but 4 samples.
    watch.sweep({"burst": (60, 30), "slow": (6, 4)}, 0.0)
    watch.sweep({"burst": (95, 0), "slow": (6, 4)}, LOSING_HOLD_S / 2)
    watch.sweep({"burst": (60, 30), "slow": (6, 4)}, LOSING_HOLD_S - 1)
    watch.sweep({"burst": (60, 30), "slow": (6, 4)}, 2 * LOSING_HOLD_S - 2)
    assert s.query(EventQuery()) == []
    watch.sweep({"burst": (60, 30)}, 2 * LOSING_HOLD_S)
    assert [(e.device, e.data["loss"], e.data["loss_ratio"]) for e in s.query(EventQuery())] == [
        ("burst", "losing", "0.333")
    ]
    # Near the line (5 %) it stays reported; forgotten, it is judged anew.
    watch.sweep({"burst": (95, 5)}, 2 * LOSING_HOLD_S + 5)
    assert watch.reported == ("burst",)
    watch.forget("burst")
    assert watch.reported == () and len(s.query(EventQuery())) == 1


def test_only_the_agent_dropping_alarms_no_one_saw_makes_a_forget_a_warning() -> None:
    """An operator forgetting an arm with an alarm up chose to (info), as did the agent forgetting one with
    its alarms seen; the agent dropping an ACTIVE or LATCHED alarm (telemetry.forget_unseen_after_s) is a loss
    to look at (warning). Only the slow churning-fleet test of test_forget.py saw the level before."""
    s, _ = store()
    watch = events.FleetWatch(s)
    unseen = "by the agent: silent for 30 days with alarms no person has seen"
    watch.forgotten("by-hand", "OFFLINE", {"ACTIVE": 1, "LATCHED": 1})
    watch.forgotten("seen", "OFFLINE", {"ACKNOWLEDGED": 2}, reason="by the agent: silent for 7 days")
    watch.forgotten("active", "OFFLINE", {"ACTIVE": 1, "ACKNOWLEDGED": 1}, reason=unseen)
    watch.forgotten("latched", "OFFLINE", {"LATCHED": 1}, reason=unseen)
    levels = {e.device: e.level for e in s.query(EventQuery())}
    assert levels == {"by-hand": "info", "seen": "info", "active": "warning", "latched": "warning"}, levels


def test_events_not_collected_from_a_mirror_are_counted_between_as_well_as_before(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A worker's store lets go of bulk events before alarms, so what the agent collects can have holes
    between two events, not only before the first: the warning counts every id it never saw."""
    from twin.service.agent import _new_events

    collected = [Event("alarm", "warning", "raised", 0.0, id=n) for n in (5, 6, 9)]
    with caplog.at_level(logging.WARNING, logger="twin.service.agent"):
        fresh = _new_events(2, collected, seen=3)
    assert [e.id for e in fresh] == [5, 6, 9]
    # 4 before, 7 and 8 between.
    assert "3 events of mirror 2 were not collected" in caplog.text, caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="twin.service.agent"):
        assert [e.id for e in _new_events(0, collected, seen=4)] == [5, 6, 9]
        assert _new_events(0, collected, seen=9) == []
    assert "2 events of mirror 0" in caplog.text and caplog.text.count("not collected") == 1, caplog.text


def test_a_query_finds_part_of_an_id_in_any_case_or_one_whole_id() -> None:
    """The Events page's box finds part of an id as the Fleet and Sessions boxes do; an arm page's link asks
    for its whole id, where arm-1 must not bring arm-10's."""
    store = EventStore()
    for device in ("arm-1", "arm-10", "Lab-ARM-7", ""):
        store.emit(EventKind.STATUS, EventLevel.INFO, f"{device} is ONLINE", device=device)
    assert [e.device for e in store.query(EventQuery(device_part="arm-1"))] == ["arm-1", "arm-10"]
    assert [e.device for e in store.query(EventQuery(device_part="lab-arm"))] == ["Lab-ARM-7"]
    assert [e.device for e in store.query(EventQuery(device="arm-1"))] == ["arm-1"]
    assert store.query(EventQuery(device="arm-1", device_part="10")) == []
    assert len(store.query(EventQuery())) == 4


def test_a_query_after_an_id_gives_every_kept_event_after_it_from_both_parts() -> None:
    """A page that follows the events asks for those after the last it saw: read from that id on in each of
    the store's parts (not the whole store, then filtered), they must still be all of them, in id order."""
    store = EventStore(300)
    rng = random.Random(7)
    for n in range(1_000):
        kind = EventKind.ALARM if rng.random() < 0.3 else EventKind.STATUS
        store.emit(kind, EventLevel.INFO, f"event {n}", device=f"arm-{n % 9}")
    kept = store.query(EventQuery(limit=1_000))
    assert len(kept) == 300
    for seen in (0, kept[0].id - 1, kept[0].id, kept[150].id, kept[-2].id, kept[-1].id):
        expected = [e for e in kept if e.id > seen]
        assert store.query(EventQuery(after_id=seen, limit=1_000)) == expected, seen
        alarms = [e for e in expected if e.kind == "alarm"]
        assert store.query(EventQuery(after_id=seen, kinds=frozenset({"alarm"}), limit=1_000)) == alarms
