"""A worker's checkpoint, in one process: what crosses the control pipe, and a mirror started again from it.

The agent takes each worker's checkpoint every second and keeps it to start the worker again after a crash
(service.shards, `WorkerShard`); tests/test_restarts.py kills a real worker. Here the checkpoint of a mirror
fed the edge's mock fleet is pickled as the pipe pickles it, and a second mirror restores from the copy.
"""

from __future__ import annotations

import dataclasses
import itertools
import pickle
import random
from collections.abc import Iterator
from multiprocessing import Pipe
from multiprocessing.connection import Connection

import pytest
import twin.core.loss as loss_module
from twin.bench.worker import _feed, _fleet
from twin.core.alarms import AlarmKind, AlarmRecord, AlarmState
from twin.core.telemetry import RejectReason
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.events import (
    CLOCK_INTERVAL_S,
    CROWDED_HOLD_S,
    LOSING_HOLD_S,
    RATE_INTERVAL_S,
    RESTORED_SETTLE_S,
    EventKind,
    EventQuery,
)
from twin.service.mirror import Mirror, PipeInbox
from twin.service.shards import MirrorCheckpoint, MirrorReport, PackedDevices, UnheardArm
from twin.transport.pipe import Batch, send_end

ARMS = 12


def _mirror(reader: Connection) -> Mirror:
    config = load_config(
        None, {"telemetry.devices": ["*"], "telemetry.units": "auto", "telemetry.max_devices": 64}
    )
    return Mirror(config, inbox=PipeInbox(reader), budget=DeviceBudget(64))


@pytest.fixture(scope="module")
def fed() -> tuple[MirrorReport, MirrorCheckpoint]:
    """A mirror fed 90 rounds of the mock fleet (units=auto decides each arm's): its report and checkpoint."""
    reader, writer = Pipe(duplex=False)
    mirror = _mirror(reader)
    mirror.start()
    try:
        rounds = _fleet(ARMS, 90)
        del rounds[40][3]  # one arm loses a message: its loss estimate has something to carry
        _feed(mirror, writer, rounds)
        return mirror.report(), mirror.checkpoint()
    finally:
        send_end(writer)
        mirror.stop(timeout=30.0)


def test_the_pipe_carries_the_devices_as_pickled_chunks(fed: tuple[MirrorReport, MirrorCheckpoint]) -> None:
    _, checkpoint = fed
    assert isinstance(checkpoint.devices, PackedDevices)
    wire = pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL)
    copy = pickle.loads(wire)
    assert isinstance(copy.devices, PackedDevices)
    assert copy.devices.blobs == checkpoint.devices.blobs
    assert len(checkpoint.devices.blobs) == 1  # 12 arms, one chunk
    # Reading a device unpacks the chunks; pickling again still carries the chunks only.
    assert len(copy.devices) == ARMS
    assert pickle.dumps(copy, protocol=pickle.HIGHEST_PROTOCOL) == wire
    assert copy == checkpoint


def test_a_mirror_restored_from_the_copy_has_each_arms_counters_loss_units_and_pose(
    fed: tuple[MirrorReport, MirrorCheckpoint],
) -> None:
    report, checkpoint = fed
    copy = pickle.loads(pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL))
    restored = _mirror(Pipe(duplex=False)[0])  # never started: it restores on the calling thread
    assert restored.restore(copy).devices == ARMS
    after = restored.report()
    assert sorted(after.devices) == sorted(report.devices)
    lossy = [d for d in report.devices.values() if d.loss.lost]
    assert len(lossy) == 1 and lossy[0].loss.lost == 1
    for device, before in report.devices.items():
        now = after.devices[device]
        assert now.health.counters == before.health.counters
        assert now.health.counters.applied > 0
        assert now.units == before.units != "auto"
        assert now.timestamp_ms == before.timestamp_ms
        assert now.targets_rad == before.targets_rad
        assert (now.loss.lost, now.loss.received, now.loss.period_s) == (
            before.loss.lost,
            before.loss.received,
            before.loss.period_s,
        )


# --- taken across batches -----------------------------------------------------------------------------------


class _Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _batches(rounds: list[list[tuple[str, str, bytes]]], clock: _Clock, size: int) -> Iterator[Batch]:
    """Each round in batches of `size`, received 0.1 s after the previous round on `clock`."""
    for messages in rounds:
        clock.now += 0.1
        for i in range(0, len(messages), size):
            part = messages[i : i + size]
            n = len(part)
            yield Batch(
                tuple(d for d, _, _ in part),
                tuple(t for _, t, _ in part),
                tuple(p for _, _, p in part),
                (clock.now,) * n,
                (1.7e9 + clock.now,) * n,
            )


def _still_mirror(clock: _Clock) -> Mirror:
    """A mirror whose worker never runs: the test hands it batches and checkpoint steps itself."""
    config = load_config(
        None, {"telemetry.devices": ["*"], "telemetry.units": "auto", "telemetry.max_devices": 64}
    )
    return Mirror(
        config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(64), clock=clock, wall_clock=clock
    )


def test_rows_taken_over_later_batches_are_the_arms_as_they_were_when_it_began(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Copy before write (service.capture): a checkpoint whose rows are taken a few at a time while batches
    go on changing the arms equals the one taken in one go at its start, on a second mirror fed the same
    messages. A new arm after the start is not in it."""
    rounds = _fleet(ARMS, 60)
    del rounds[20][5]  # a loss to estimate
    later = _fleet(ARMS + 1, 70)[60:]  # one more arm from here on

    def fed(mirror: Mirror, clock: _Clock) -> None:
        # Each arm's loss estimator settles at a moment drawn from a shared counter: the same on both.
        monkeypatch.setattr(loss_module, "_STAGGER", itertools.count(0, 37))
        for batch in _batches(rounds, clock, size=5):
            mirror._handle(batch, 0)

    clock_a, clock_b = _Clock(), _Clock()
    at_once, spread = _still_mirror(clock_a), _still_mirror(clock_b)
    fed(at_once, clock_a)
    expected = at_once.checkpoint()
    fed(spread, clock_b)
    capture = spread._begin_capture(spread=True)
    steps = 0
    for batch in _batches(later, clock_b, size=5):
        spread._handle(batch, 0)  # changes arms whose rows are still to take
        if spread._capture is not None:
            spread._step_capture(spread._capture, 1)
            steps += 1
    assert capture.done.is_set() and capture.error is None and capture.result is not None
    assert steps > 1 and spread._capture is None
    got = capture.result
    assert isinstance(got.devices, PackedDevices) and len(got.devices.blobs) == 1
    arms = sorted(f"arm-{i:04d}" for i in range(1, ARMS + 1))
    assert sorted(got.devices) == sorted(expected.devices) == arms
    assert dict(got.devices) == dict(expected.devices)
    assert dataclasses.replace(got, at=0.0) == dataclasses.replace(expected, at=0.0)
    # ... while the arms themselves moved on.
    now = spread.report().devices
    assert all(now[d].health.counters.received > got.devices[d].health.counters.received for d in got.devices)
    assert f"arm-{ARMS + 1:04d}" in now


# --- the rate watch's reports -------------------------------------------------------------------------------


def _crowded_rounds(mirror: Mirror, clock: _Clock, rng: random.Random, seconds: float, hz: int) -> None:
    """arm-001 at `hz` valid messages a second (two edges under its id at 20), a batch every 0.1 s, each
    followed by the worker's sweep of statuses and rates."""
    for _ in range(round(seconds * 10)):
        clock.now += 0.1
        stamps = [round((1.7e9 + clock.now) * 1000) + 100 * k // (hz // 10) for k in range(hz // 10)]
        payloads = tuple(
            encode(make_payload("arm-001", s / 1000, "ticks", rng, timestamp_ms=s)) for s in stamps
        )
        n = len(payloads)
        mirror._handle(
            Batch(
                ("arm-001",) * n,
                (telemetry_topic(DEFAULT_TOPIC_PREFIX, "arm-001"),) * n,
                payloads,
                (clock.now,) * n,
                (1.7e9 + clock.now,) * n,
            ),
            0,
        )
        mirror._watch_statuses()


def _rate_events(mirror: Mirror) -> list[tuple[str, str]]:
    found = mirror.events(EventQuery(kinds=frozenset({EventKind.TWIN.value}), device="arm-001"))
    return [(e.level, e.data["rate"]) for e in found if "rate" in e.data]


def test_a_mirror_started_again_does_not_report_a_crowded_arm_twice() -> None:
    """The checkpoint carries the devices the rate watch reported: the mirror started from it says nothing
    while the arm stays over the line, and says it is back once it is (which it could not have without)."""
    clock, rng = _Clock(), random.Random(5)
    first = _still_mirror(clock)
    _crowded_rounds(first, clock, rng, CROWDED_HOLD_S + 2 * RATE_INTERVAL_S + 2, hz=20)
    assert _rate_events(first) == [("warning", "crowded")]
    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    assert checkpoint.crowded == ("arm-001",)

    again = _still_mirror(clock)
    again.restore(checkpoint)
    _crowded_rounds(again, clock, rng, CROWDED_HOLD_S + 2 * RATE_INTERVAL_S + 2, hz=20)
    assert _rate_events(again) == []
    _crowded_rounds(again, clock, rng, RESTORED_SETTLE_S + 2 * RATE_INTERVAL_S + 2, hz=10)
    assert _rate_events(again) == [("info", "expected")]


# --- the loss watch's reports -------------------------------------------------------------------------------


def _lossy_rounds(
    mirror: Mirror, clock: _Clock, rng: random.Random, seconds: float, *, drop: float, skew_s: float = 0.0
) -> None:
    """arm-001 and arm-002 at 10 Hz, a batch every 0.1 s; `drop` of arm-002's samples never arrive (its edge
    stamps them all: the gaps are what the loss estimate reads), and its clock is `skew_s` behind."""
    devices = ("arm-001", "arm-002")
    for _ in range(round(seconds * 10)):
        clock.now += 0.1
        stamp = round((1.7e9 + clock.now) * 1000)
        sent = [d for d in devices if d == "arm-001" or rng.random() >= drop]
        stamps = [stamp if d == "arm-001" else stamp - round(skew_s * 1000) for d in sent]
        payloads = tuple(
            encode(make_payload(d, t / 1000, "ticks", rng, timestamp_ms=t))
            for d, t in zip(sent, stamps, strict=True)
        )
        n = len(sent)
        topics = tuple(telemetry_topic(DEFAULT_TOPIC_PREFIX, d) for d in sent)
        mirror._handle(Batch(tuple(sent), topics, payloads, (clock.now,) * n, (1.7e9 + clock.now,) * n), 0)
        mirror._watch_statuses()


def _loss_events(mirror: Mirror) -> list[tuple[str, str, str]]:
    found = mirror.events(EventQuery(kinds=frozenset({EventKind.TWIN.value})))
    return [(e.device, e.level, e.data["loss"]) for e in found if "loss" in e.data]


def test_an_arm_losing_messages_is_named_once_and_a_mirror_started_again_does_not_name_it_twice() -> None:
    """The fleet's LossPercent averages the arms, so one arm losing a third of its messages moved it by a
    few per cent and nothing named the arm. The loss watch names it once it has lost a tenth or more for
    LOSING_HOLD_S, and once it is back; the checkpoint carries the report over a worker's restart."""
    clock, rng = _Clock(), random.Random(8)
    first = _still_mirror(clock)
    _lossy_rounds(first, clock, rng, 20.0, drop=0.0)  # the period settles on a whole stream
    _lossy_rounds(first, clock, rng, LOSING_HOLD_S + 3 * RATE_INTERVAL_S, drop=0.3)
    assert _loss_events(first) == [("arm-002", "warning", "losing")]
    message = first.events(EventQuery(kinds=frozenset({EventKind.TWIN.value})))[-1].message
    assert message.startswith("arm-002 is losing ") and "of its messages" in message
    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    assert checkpoint.losing == ("arm-002",)

    again = _still_mirror(clock)
    again.restore(checkpoint)
    _lossy_rounds(again, clock, rng, LOSING_HOLD_S + 2 * RATE_INTERVAL_S, drop=0.3)
    assert _loss_events(again) == []
    _lossy_rounds(again, clock, rng, 15.0 + 2 * RATE_INTERVAL_S, drop=0.0)
    assert _loss_events(again) == [("arm-002", "info", "whole")]


def _clock_events(mirror: Mirror) -> list[tuple[str, str]]:
    found = mirror.events(EventQuery(kinds=frozenset({EventKind.TWIN.value})))
    return [(e.device, e.level) for e in found if "clock_offset_s" in e.data]


def test_a_mirror_started_again_does_not_report_an_edge_clock_off_twice() -> None:
    """A worker started again read an arm's clock afresh and reported it off a second time; the checkpoint
    carries the arms reported, so it says nothing until the clock agrees again, and then says that."""
    clock, rng = _Clock(), random.Random(9)
    first = _still_mirror(clock)
    _lossy_rounds(first, clock, rng, 3 * CLOCK_INTERVAL_S, drop=0.0, skew_s=5.0)
    assert _clock_events(first) == [("arm-002", "warning")]
    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    assert checkpoint.clocks_off == ("arm-002",)

    again = _still_mirror(clock)
    again.restore(checkpoint)
    _lossy_rounds(again, clock, rng, 3 * CLOCK_INTERVAL_S, drop=0.0, skew_s=5.0)
    assert _clock_events(again) == []
    _lossy_rounds(again, clock, rng, 2 * CLOCK_INTERVAL_S, drop=0.0)
    assert _clock_events(again) == [("arm-002", "info")]


# --- arms the state file kept -------------------------------------------------------------------------------


def _kept(device: str) -> AlarmRecord:
    """A LATCHED alarm of `device` as the agent's state file hands it back after a restart."""
    return AlarmRecord(
        device=device,
        joint="gripper",
        kind=AlarmKind.OVER_CURRENT,
        state=AlarmState.LATCHED,
        since=1.0,
        present=False,
        raised=1,
        message="gripper servo draws 1.9 A",
    )


def test_an_arm_listed_for_its_kept_alarms_is_listed_again_by_a_mirror_restored_from_its_checkpoint() -> None:
    # After an agent restart, an arm whose alarms the state file kept is listed though it is not heard
    # (FleetHealth.keep), so a person can acknowledge them or forget the arm. A worker that died next came
    # back without those arms: the checkpoint carried their alarms but not that they were listed, so they
    # left /state and the Fleet page while their alarms stayed in /alarms.
    first = _mirror(Pipe(duplex=False)[0])  # never started: it restores on the calling thread
    first.restore(None, (_kept("gone-1"),))
    assert list(first.report().devices) == ["gone-1"]
    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    again = _mirror(Pipe(duplex=False)[0])
    again.restore(checkpoint)
    assert list(again.report().devices) == ["gone-1"]
    alarms = [(a.alarm_id, str(a.state)) for a in again.alarms()]
    assert alarms == [("gone-1/gripper/over_current", "LATCHED")]


def test_arms_listed_for_their_kept_alarms_hold_places_in_the_device_budget() -> None:
    # Every table keyed by device ids is bounded by telemetry.max_devices (docs/agent.md). The arms the
    # state file kept took no place, so each restart under a churning fleet let max_devices new arms in
    # beside them, and the next state file kept their alarms too: a run with max_devices = 1200 held 1498
    # arms after one restart and 2245 after two.
    config = load_config(
        None, {"telemetry.devices": ["*"], "telemetry.units": "auto", "telemetry.max_devices": 2}
    )
    budget = DeviceBudget(2)
    reader, writer = Pipe(duplex=False)
    mirror = Mirror(config, inbox=PipeInbox(reader), budget=budget)
    mirror.restore(None, (_kept("arm-0001"), _kept("gone-2")))
    assert budget.taken == 2
    mirror.start()
    try:
        _feed(mirror, writer, _fleet(3, 90))  # arm-0001, kept, and two arms new to this run
        report = mirror.report()
        checkpoint = mirror.checkpoint()
    finally:
        send_end(writer)
        mirror.stop(timeout=30.0)
    assert sorted(report.devices) == ["arm-0001", "gone-2"]
    assert report.devices["arm-0001"].health.counters.applied > 0  # heard again: no second place
    assert report.untracked_rejected["too_many_devices"] > 0
    assert budget.taken == 2
    # A worker started again gives its places back, and its kept arm takes one again.
    budget.release(0)
    clock = _Clock()
    again = Mirror(config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=budget, clock=clock)
    again.restore(checkpoint)
    assert sorted(again.report().devices) == ["arm-0001", "gone-2"]
    assert budget.taken == 2
    # Forgetting the silent kept arm gives its place back.
    clock.now += config.health.offline_after_s + 1.0
    again.forget_arm("gone-2")
    assert budget.taken == 1


# --- NORMAL alarms ------------------------------------------------------------------------------------------


def _hot_then_cool(mirror: Mirror, clock: _Clock, devices: list[str]) -> None:
    """10 Hz rounds of `devices`: the first one's wrist_roll at 62 C for 3 s (raised), then 40 C for 11 s
    (cleared, LATCHED), the others' as the mock sends them."""
    rng = random.Random(5)
    for r in range(140):
        messages = []
        for device in devices:
            doc = make_payload(device, r * 0.1, "ticks", rng, timestamp_ms=1_700_000_000_000 + r * 100)
            if device == devices[0]:
                doc["joints"]["wrist_roll"]["temp"] = 62 if r < 30 else 40
            messages.append((device, telemetry_topic(DEFAULT_TOPIC_PREFIX, device), encode(doc)))
        mirror._handle(next(_batches([messages], clock, size=len(messages))), 0)  # 0.1 s on


def test_a_mirror_started_again_keeps_its_normal_alarms_and_how_often_each_was_raised() -> None:
    # The checkpoint carried only the alarms that are not NORMAL (or are timing a raise): a restarted worker
    # counted NORMAL alarms only as its arms were heard again (a moving arm's model check, or an arm gone
    # quiet, never), and an alarm raised, cleared and acknowledged came back as never raised.
    clock = _Clock()
    first = _still_mirror(clock)
    devices = ["arm-0001", "arm-0002", "arm-0003"]
    _hot_then_cool(first, clock, devices)
    hot = "arm-0001/wrist_roll/over_temperature"
    assert [(a.alarm_id, str(a.state)) for a in first.alarms()] == [(hot, "LATCHED")]
    first.acknowledge_alarm(hot)  # back to NORMAL, raised once
    before = first.report().alarms
    assert before.by_state["warning"]["NORMAL"] > 10 and before.raised_total == {"over_temperature": 1}
    listed = {a.alarm_id: a for a in first.alarms(include_normal=True)}
    assert listed[hot].state == "NORMAL" and listed[hot].raised == 1

    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    assert hot not in {r.alarm_id for r in checkpoint.alarms}
    again = _still_mirror(clock)  # not a message since: only the checkpoint speaks
    again.restore(checkpoint)
    assert again.report().alarms == before
    restored = {a.alarm_id: a for a in again.alarms(include_normal=True)}
    assert sorted(restored) == sorted(listed)
    assert (restored[hot].state, restored[hot].raised) == ("NORMAL", 1)
    assert restored[hot].changed_at == listed[hot].changed_at  # when it went NORMAL (same clocks)
    assert restored[hot].message == listed[hot].message != ""

    # A checkpoint of an agent from before the field still restores (its NORMAL alarms come with messages).
    old = pickle.loads(pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL))
    del old.__dict__["idle_alarms"]
    assert old.idle_alarms == ()
    older = _still_mirror(clock)
    assert older.restore(old).devices == len(devices)


# --- a timer pending at the checkpoint ----------------------------------------------------------------------


def _held_arm(step: int, *, moving: bool) -> bytes:
    """arm-001 holding one pose, its shoulder_lift at 70 % load (contact: far off the model's), still or
    turning fast, one message every 0.1 s of edge time."""
    stamp = 1_700_000_000_000 + step * 100
    doc = make_payload("arm-001", 0.0, "ticks", random.Random(step), timestamp_ms=stamp)
    for joint in doc["joints"].values():
        joint["velocity"] = 0
    doc["joints"]["shoulder_lift"]["load"] = 700
    if moving:
        doc["joints"]["shoulder_lift"]["velocity"] = 500  # 0.77 rad/s
    return encode(doc)


def test_a_mirror_started_again_does_not_raise_on_a_timer_the_messages_sent_again_would_have_reset() -> None:
    # A worker killed and started again raised model_mismatch on all its arms at once: its checkpoint held
    # the model check's raise timer of a still reading, the messages since (the joint moving: each resets
    # it) came again as a backlog the mirror catches up on, taking each arm's newest only, and that one
    # still reading completed the timer. The timer must start again from it.
    topic = telemetry_topic(DEFAULT_TOPIC_PREFIX, "arm-001")
    clock = _Clock()
    first = _ticks_mirror(clock)
    rounds = [[("arm-001", topic, _held_arm(0, moving=False))]]
    first._handle(next(_batches(rounds, clock, size=1)), 0)
    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    sent: list[Batch] = []
    # 1.4 s turning, then still again, each message handled as it comes: nothing is raised.
    since = [[("arm-001", topic, _held_arm(step, moving=step < 15))] for step in range(1, 16)]
    for batch in _batches(since, clock, size=1):
        sent.append(batch)
        first._handle(batch, 0)
    assert first.alarms() == ()

    again = _ticks_mirror(clock)
    again.restore(checkpoint)
    backlog = Batch(*(tuple(item for part in field for item in part) for field in zip(*sent, strict=True)))
    again._handle(backlog, 0)  # received 1.4 s ago: caught up on, the newest message only
    assert again.report().devices["arm-001"].health.counters.coalesced == 14
    assert again.alarms() == ()
    # Still for the rule's 1 s from there: both raise it with the same message.
    held = [[("arm-001", topic, _held_arm(step, moving=False))] for step in range(16, 26)]
    for batch in _batches(held, clock, size=1):
        first._handle(batch, 0)
        again._handle(batch, 0)
    assert [a.alarm_id for a in again.alarms()] == ["arm-001/shoulder_lift/model_mismatch"]
    assert [a.changed_at for a in again.alarms()] == [a.changed_at for a in first.alarms()]


def _ticks_mirror(clock: _Clock) -> Mirror:
    config = load_config(
        None, {"telemetry.devices": ["*"], "telemetry.units": "ticks", "telemetry.max_devices": 64}
    )
    return Mirror(
        config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(64), clock=clock, wall_clock=clock
    )


def test_a_mirror_started_again_keeps_the_arms_whose_every_message_was_refused() -> None:
    # A held arm (its calibration refused) is never tracked: the Fleet page's count of its refused messages
    # is read from the checkpoint's `unheard`. A worker started again did not take them back, so the count
    # fell to 0 and the held arm's link said "none heard" after a crash.
    refused = str(RejectReason.CALIBRATION_REFUSED)
    checkpoint = MirrorCheckpoint(
        at=100.0,
        unheard=(UnheardArm("arm-b", 3, refused, 2.0), UnheardArm("arm-a", 5, refused, 10.0)),
    )
    clock = _Clock()
    clock.now = 104.0
    again = _still_mirror(clock)
    again.restore(checkpoint)
    # The most recent first still, each as long ago as it was (4 s passed since the checkpoint).
    expected = (UnheardArm("arm-b", 3, refused, 6.0), UnheardArm("arm-a", 5, refused, 14.0))
    assert again.unheard() == expected
