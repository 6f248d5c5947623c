"""twin.output.sinks: the queued sink never blocks its caller, drops the oldest when full and counts it,
survives a failing worker, and delivers everything queued on close; RobotModel.body_poses matches a twin."""

from __future__ import annotations

import random
import threading
import time
from multiprocessing import Pipe
from pathlib import Path

import numpy as np
import pytest
from conftest import fed_agent, full_disk, metric, parse_metrics, wait_for
from twin.core import heap
from twin.core.health import DeviceStatus
from twin.core.telemetry import Telemetry, Units
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.core.twin import DeviceTwin
from twin.edge.payload import encode, make_payload
from twin.output import sinks
from twin.output.sinks import (
    RESCUE_MIN_ARMS,
    AppliedSample,
    QueuedSink,
    RejectedSample,
    SinkStats,
    StatusChange,
)
from twin.robot import so101
from twin.robot.model import RobotModel
from twin.service.admission import DeviceBudget
from twin.service.config import ConfigError, load_config
from twin.service.events import FleetWatch
from twin.service.metrics import render_metrics
from twin.service.mirror import Mirror, PipeInbox
from twin.transport.pipe import send_batch, send_end


def _sample(i: int) -> AppliedSample:
    angles = dict.fromkeys(so101.JOINT_NAMES, 0.01 * i)
    telemetry = Telemetry(
        device_id="arm-001",
        timestamp_ms=1_706_000_000_000 + i,
        units=Units.DEGREES,
        angles_rad=angles,
        gripper_percent=None,
        diagnostics={},
    )
    return AppliedSample("arm-001", 1.0 * i, 2.0 * i, telemetry, angles)


class _Recorder:
    def __init__(self, gate: threading.Event | None = None, fail_on: int | None = None) -> None:
        self.gate = gate
        self.fail_on = fail_on
        self.applied: list[int] = []
        self.rejected: list[str] = []
        self.closed = 0
        self.idles = 0
        # Set when the worker first enters handle_applied: from then on it holds exactly the batch it took.
        self.entered = threading.Event()

    def handle_applied(self, sample: AppliedSample) -> None:
        self.entered.set()
        if self.gate is not None:
            self.gate.wait(10)
        if sample.timestamp_ms - 1_706_000_000_000 == self.fail_on:
            raise OSError("disk full")
        self.applied.append(sample.timestamp_ms - 1_706_000_000_000)

    def handle_rejected(self, sample: RejectedSample) -> None:
        self.rejected.append(sample.reason)

    def idle(self) -> None:
        self.idles += 1

    def close(self) -> None:
        self.closed += 1


def test_close_delivers_everything_queued_in_order() -> None:
    worker = _Recorder()
    sink = QueuedSink("t", worker, max_pending=1000)
    for i in range(500):
        sink.applied(_sample(i))
    sink.rejected(RejectedSample(None, "dt/lerobot/x/telemetry", 0.0, "not_json", "bad", b"{"))
    sink.close()
    assert worker.applied == list(range(500))
    assert worker.rejected == ["not_json"]
    assert worker.closed == 1
    stats = sink.stats()
    assert (stats.delivered, stats.dropped, stats.errors, stats.pending) == (500, 0, 0, 0)


class _StatusRecorder(_Recorder):
    def __init__(self) -> None:
        super().__init__()
        self.order: list[str] = []

    def handle_applied(self, sample: AppliedSample) -> None:
        self.order.append("sample")

    def handle_status(self, change: StatusChange) -> None:
        self.order.append(f"{change.device_id} {change.status}")


def test_status_changes_reach_only_the_workers_that_show_them_in_order_with_samples() -> None:
    stale = StatusChange("arm-001", DeviceStatus.ONLINE, DeviceStatus.STALE, at_mono_s=5.0, at_wall_s=5.0)
    shows = _StatusRecorder()
    sink = QueuedSink("shows", shows)
    sink.applied(_sample(0))
    sink.status(stale)
    sink.close()
    assert shows.order == ["sample", "arm-001 STALE"]
    assert (sink.stats().delivered, sink.stats().errors) == (1, 0)
    # A worker with no `handle_status` (the USD recording, ROS 2) is handed none: held on its first sample,
    # its queue stays empty, so a change takes no room from samples, and no error is counted.
    gate = threading.Event()
    ignores = _Recorder(gate=gate)
    sink = QueuedSink("ignores", ignores)
    sink.applied(_sample(0))
    assert ignores.entered.wait(30), "the sink's thread never took the first sample"
    sink.status(stale)
    assert sink.stats().pending == 1
    gate.set()
    sink.close()
    assert ignores.applied == [0]
    assert (sink.stats().delivered, sink.stats().errors) == (1, 0)


class _GatedStatusRecorder(_Recorder):
    """Stalls on its first sample (the gate); records the samples and status changes it gets, in order."""

    def __init__(self, gate: threading.Event) -> None:
        super().__init__(gate=gate)
        self.order: list[int | str] = []

    def handle_applied(self, sample: AppliedSample) -> None:
        super().handle_applied(sample)
        self.order.append(self.applied[-1])

    def handle_status(self, change: StatusChange) -> None:
        forgotten = f" forgotten (was {change.previous})" if change.forgotten else ""
        self.order.append(f"{change.device_id} {change.status}{forgotten}")


def _change(device: str, previous: DeviceStatus, status: DeviceStatus) -> StatusChange:
    return StatusChange(device, previous, status, at_mono_s=5.0, at_wall_s=5.0)


def _sink_held_at_its_first_sample() -> tuple[threading.Event, _GatedStatusRecorder, QueuedSink]:
    """A sink of two items whose thread took sample 0 and waits at the gate: what comes next queues."""
    gate = threading.Event()
    worker = _GatedStatusRecorder(gate)
    sink = QueuedSink("shows", worker, max_pending=2)
    sink.applied(_sample(0))
    assert worker.entered.wait(30), "the sink's thread never took the first sample"
    return gate, worker, sink


def test_a_full_queue_drops_samples_but_each_arms_newest_status_change_gets_through() -> None:
    """A review: status changes shared the drop-oldest queue with samples, so under overload a change could
    be dropped, and a quiet arm (which sends no sample to correct it) stayed unlabelled in Rerun until its
    next change. An arm's newest change the queue drops now waits beside it and goes first; one a newer change
    of the arm replaced is dropped and counted, like a sample."""
    gate, worker, sink = _sink_held_at_its_first_sample()
    sink.status(_change("arm-002", DeviceStatus.ONLINE, DeviceStatus.STALE))
    sink.status(_change("arm-001", DeviceStatus.ONLINE, DeviceStatus.STALE))
    for i in (1, 2):
        sink.applied(_sample(i))  # the queue holds two: both changes leave it, and are kept
    assert sink.stats().pending == 1 + 2 + 2
    sink.applied(_sample(3))  # sample 1 goes
    sink.status(_change("arm-001", DeviceStatus.STALE, DeviceStatus.OFFLINE))  # arm-001's STALE and 2 go
    gate.set()
    sink.close()
    assert worker.order == [0, "arm-002 STALE", 3, "arm-001 OFFLINE"]
    assert (sink.stats().dropped, sink.stats().delivered, sink.stats().pending) == (3, 2, 0)


def test_an_arms_older_change_dropped_while_its_newer_one_waits_is_dropped_not_kept() -> None:
    """A review: no test dropped an arm's older change from the queue while its newer change was still queued
    behind it. Only the newest is kept aside: the older is dropped and counted, and never reaches the worker
    (kept, it would go first, and a viewer would show the arm's old status before its new one)."""
    gate, worker, sink = _sink_held_at_its_first_sample()
    sink.status(_change("arm-001", DeviceStatus.ONLINE, DeviceStatus.STALE))
    sink.status(_change("arm-001", DeviceStatus.STALE, DeviceStatus.OFFLINE))
    sink.applied(_sample(1))  # the STALE change, the oldest, goes: its OFFLINE change is still queued
    assert sink.stats().pending == 1 + 2
    gate.set()
    sink.close()
    assert worker.order == [0, "arm-001 OFFLINE", 1]
    assert (sink.stats().dropped, sink.stats().delivered) == (1, 2)


def test_the_slot_keeps_every_tracked_arms_newest_change_however_small_the_queue() -> None:
    """A review: the slot was bounded like the queue (two items here), so with more arms changing than that
    while the thread was stuck it threw the oldest away: a lost change to ONLINE (or a lost forget, with an
    arm of that name back) left a red OFFLINE label over a live arm. It keeps one per arm tracked at once."""
    gate, worker, sink = _sink_held_at_its_first_sample()
    for n in range(1, 6):
        sink.status(_change(f"arm-{n:03d}", DeviceStatus.OFFLINE, DeviceStatus.ONLINE))
    sink.applied(_sample(1))
    sink.applied(_sample(2))  # every change has left the queue: the slot keeps them all
    gate.set()
    sink.close()
    assert worker.order == [0, *(f"arm-{n:03d} ONLINE" for n in range(1, 6)), 1, 2]
    assert (sink.stats().dropped, sink.stats().delivered) == (0, 3)
    # It holds as many as one agent may track: telemetry.max_devices allows no more.
    with pytest.raises(ConfigError, match="max_devices"):
        load_config(None, {"telemetry.max_devices": RESCUE_MIN_ARMS + 1})


def test_a_full_slot_keeps_every_forget_and_every_tracked_arms_newest_change(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A walk: the slot of changes and forgets was bounded as one, and full it dropped the oldest forget; an
    arm of that id back before the stuck thread (ONLINE to the sinks from its first sample, with no change)
    kept the old arm's OFFLINE label. Forgets are bounded on their own, as many as the slot: the slot full of
    tracked arms' changes drops no forget, and the worker hears of each before the samples that came after."""
    monkeypatch.setattr(sinks, "RESCUE_MIN_ARMS", 2)
    gate, worker, sink = _sink_held_at_its_first_sample()
    for device in ("arm-001", "arm-004"):  # the slot's two places taken by tracked arms' changes
        sink.status(_change(device, DeviceStatus.ONLINE, DeviceStatus.STALE))
    for device in ("arm-002", "arm-003"):
        sink.status(_forget(device))
    sink.applied(_sample(1))
    sink.applied(_sample(2))  # every change and forget has left the queue: none is dropped
    assert (len(sink._rescued), len(sink._forgets), sink.stats().dropped) == (2, 2, 0)
    gate.set()
    sink.close()
    assert worker.order == [
        0,
        "arm-002 OFFLINE forgotten (was OFFLINE)",
        "arm-003 OFFLINE forgotten (was OFFLINE)",
        "arm-001 STALE",
        "arm-004 STALE",
        1,
        2,
    ]
    assert (sink.stats().dropped, sink.stats().delivered) == (0, 3)


def test_more_forgets_waiting_than_their_bound_drop_the_oldest_forget_only(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The forgets' queue is still bounded (a stuck thread with arms forgotten and replaced would fill it with
    every new device id): past it, the oldest forget is dropped, counted, never a tracked arm's change."""
    monkeypatch.setattr(sinks, "RESCUE_MIN_ARMS", 2)
    gate, worker, sink = _sink_held_at_its_first_sample()
    sink.status(_change("arm-001", DeviceStatus.ONLINE, DeviceStatus.STALE))
    for n in (2, 3, 4):
        sink.status(_forget(f"arm-{n:03d}"))
    sink.applied(_sample(1))
    sink.applied(_sample(2))  # the forgets' queue of two drops arm-002's forget
    gate.set()
    sink.close()
    assert worker.order == [
        0,
        "arm-003 OFFLINE forgotten (was OFFLINE)",
        "arm-004 OFFLINE forgotten (was OFFLINE)",
        "arm-001 STALE",
        1,
        2,
    ]
    assert (sink.stats().dropped, sink.stats().delivered) == (1, 3)


def _forget(device: str, previous: DeviceStatus = DeviceStatus.OFFLINE) -> StatusChange:
    return StatusChange(device, previous, DeviceStatus.OFFLINE, at_mono_s=5.0, at_wall_s=5.0, forgotten=True)


def test_an_arms_return_never_replaces_its_forget_waiting_in_the_slot() -> None:
    """A review: the returning arm's first change replaced its forget waiting in the slot, so the worker
    never saw the forget and the old arm's red OFFLINE label stayed over the live one. The forget stays,
    and goes before the return."""
    gate, worker, sink = _sink_held_at_its_first_sample()
    sink.status(_forget("arm-001"))
    sink.applied(_sample(1))
    sink.applied(_sample(2))  # the forget leaves the queue for the slot
    sink.status(_change("arm-001", DeviceStatus.OFFLINE, DeviceStatus.ONLINE))
    sink.applied(_sample(3))
    sink.applied(_sample(4))  # and so does the return
    gate.set()
    sink.close()
    assert worker.order == [0, "arm-001 OFFLINE forgotten (was OFFLINE)", "arm-001 ONLINE", 3, 4]
    assert (sink.stats().dropped, sink.stats().delivered, sink.stats().pending) == (2, 3, 0)


def test_an_arms_return_queued_behind_its_forget_never_lets_the_forget_be_dropped() -> None:
    """A review: the returning arm's change became its id's newest, so its forget still queued, no longer
    the newest, was dropped when the queue overflowed. A forget leaving the queue is always kept."""
    gate, worker, sink = _sink_held_at_its_first_sample()
    sink.status(_forget("arm-001"))
    sink.status(_change("arm-001", DeviceStatus.OFFLINE, DeviceStatus.ONLINE))
    sink.applied(_sample(1))  # the forget leaves the queue; the return is still in it
    gate.set()
    sink.close()
    assert worker.order == [0, "arm-001 OFFLINE forgotten (was OFFLINE)", "arm-001 ONLINE", 1]
    assert (sink.stats().dropped, sink.stats().delivered) == (0, 2)


def test_a_second_forget_of_an_id_whose_forget_waits_in_the_slot_is_dropped() -> None:
    """The slot keeps one forget per id: the first, of the arm the worker drew. A second one dropped from the
    queue behind it stands for an arm of which everything older than it went first, so the worker saw none
    of it: it is counted dropped, and the worker is told of the forget of the arm it knows."""
    gate, worker, sink = _sink_held_at_its_first_sample()
    sink.status(_forget("arm-001"))
    sink.applied(_sample(1))
    sink.applied(_sample(2))  # the forget leaves the queue for the slot
    sink.status(_change("arm-001", DeviceStatus.OFFLINE, DeviceStatus.ONLINE))
    sink.status(_forget("arm-001", DeviceStatus.STALE))  # samples 1 and 2 go
    sink.applied(_sample(3))
    sink.applied(_sample(4))  # the return (no longer the newest) goes, and the second forget
    gate.set()
    sink.close()
    assert worker.order == [0, "arm-001 OFFLINE forgotten (was OFFLINE)", 3, 4]
    assert (sink.stats().dropped, sink.stats().delivered, sink.stats().pending) == (4, 3, 0)


def test_a_stalled_worker_never_blocks_the_caller_and_drops_the_oldest() -> None:
    gate = threading.Event()
    worker = _Recorder(gate=gate)
    sink = QueuedSink("slow", worker, max_pending=10)
    # The worker takes everything queued at each wake-up, so what it holds when it stalls depends on when it
    # woke. Hand it one sample and wait until it is stuck on it: from then on the batch in its hands is
    # exactly that one, and the queue alone decides what survives.
    sink.applied(_sample(0))
    assert worker.entered.wait(30), "the sink's thread never took the first sample"
    started = time.monotonic()
    for i in range(1, 1000):
        sink.applied(_sample(i))
    put_time = time.monotonic() - started
    gate.set()
    sink.close()
    # The held sample, then only the newest 10 of the 999 queued behind it.
    assert worker.applied == [0, *range(990, 1000)]
    stats = sink.stats()
    assert stats.dropped == 989
    assert stats.delivered == 11
    # Not a timing assertion of the design's speed: a generous bound that only a blocking put would break.
    assert put_time < 5.0


def test_a_drained_backlog_gives_its_memory_back_once(monkeypatch: pytest.MonkeyPatch) -> None:
    trims: list[int] = []
    monkeypatch.setattr(heap, "trim", lambda: trims.append(1) or True)
    gate = threading.Event()
    worker = _Recorder(gate=gate)
    sink = QueuedSink("backlog", worker, max_pending=1000, idle_s=0.01)
    sink.applied(_sample(0))
    assert worker.entered.wait(30), "the sink's thread never took the first sample"
    for i in range(1, 301):  # a batch of 300: at least max(256, max_pending // 10), a backlog
        sink.applied(_sample(i))
    assert trims == []  # nothing drained yet
    gate.set()
    wait_for(lambda: worker.idles >= 1 and len(worker.applied) == 301, 30, "the backlog drained")
    wait_for(lambda: trims, 30, "a trim after the backlog")
    sink.applied(_sample(301))  # small batches after it: no trim of their own
    wait_for(lambda: worker.idles >= 3, 30, "idle again")
    sink.close()
    assert trims == [1]


def test_a_failing_worker_is_counted_and_the_sink_keeps_going() -> None:
    worker = _Recorder(fail_on=3)
    sink = QueuedSink("flaky", worker)
    for i in range(6):
        sink.applied(_sample(i))
    sink.close()
    assert worker.applied == [0, 1, 2, 4, 5]
    stats = sink.stats()
    assert stats.errors == 1
    assert stats.delivered == 5
    assert "disk full" in stats.last_error


def test_items_after_close_are_counted_as_dropped() -> None:
    worker = _Recorder()
    sink = QueuedSink("closed", worker)
    sink.close()
    sink.applied(_sample(1))
    assert sink.stats().dropped == 1
    assert worker.applied == []


def test_idle_is_called_when_nothing_arrives() -> None:
    worker = _Recorder()
    sink = QueuedSink("idle", worker, idle_s=0.01)
    wait_for(lambda: worker.idles >= 2, 30, "two idle calls")
    sink.close()
    assert worker.idles >= 2


def test_a_hand_off_takes_samples_in_batches_in_order() -> None:
    # 300 samples over 0.3 s into a sink that pauses 0.1 s after each batch: its thread wakes a handful of
    # times, not 300 (each wake hands the GIL over), and still sees every sample once, in order. A batch is a
    # run of samples handled less than 0.5 ms apart; one by one, they come about 1 ms apart.
    worker = _Recorder()
    batches: list[float] = []
    last: list[float] = []
    handle = worker.handle_applied

    def timed(sample: AppliedSample) -> None:
        now = time.monotonic()
        if not last or now - last[0] > 0.0005:
            batches.append(now)
        last[:] = [now]
        handle(sample)

    worker.handle_applied = timed  # type: ignore[method-assign]
    sink = QueuedSink("t", worker, max_pending=1000, hand_off_s=0.1)
    for i in range(300):
        sink.applied(_sample(i))
        time.sleep(0.001)  # arrivals spread over 0.3 s (at least), what the hand-off batches
    wait_for(lambda: len(worker.applied) == 300, 30, "every sample handled")
    assert sink.stats().pending == 0
    sink.close()
    assert worker.applied == list(range(300))
    # 0.3 s of arrivals / 0.1 s per hand-off: about 4 batches (a preempted thread splits one now and then).
    assert len(batches) <= 30, len(batches)
    with pytest.raises(ValueError, match="hand_off_s"):
        QueuedSink("t", _Recorder(), hand_off_s=-1.0)


def test_max_pending_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_pending"):
        QueuedSink("x", _Recorder(), max_pending=0)


def test_body_poses_equal_the_twins_forward_kinematics() -> None:
    robot = RobotModel.load()
    twin = DeviceTwin(robot, "arm-001")
    angles = {
        "shoulder_pan": 0.3,
        "shoulder_lift": -0.7,
        "elbow_flex": 0.9,
        "wrist_flex": 0.2,
        "wrist_roll": -1.1,
        "gripper": 0.5,
    }
    assert twin.apply(angles, 1_706_000_000_000)
    expected = twin.body_poses()
    got = robot.body_poses(angles)
    assert set(got) == set(expected) == set(so101.BODY_NAMES)
    for name, (pos, quat) in expected.items():
        np.testing.assert_allclose(got[name][0], pos, atol=1e-12)
        np.testing.assert_allclose(got[name][1], quat, atol=1e-12)
    # The gripper tip moved away from the reference pose: the angles were really used.
    ref = robot.body_poses({})
    assert np.linalg.norm(ref["gripper"][0] - got["gripper"][0]) > 0.05


# -- wired into the agent ------------------------------------------------------------------------------------


class _Sink:
    """A sink that keeps what the worker hands it (fast and non-blocking: a list append)."""

    name = "collect"

    def __init__(self) -> None:
        self.applied_samples: list[AppliedSample] = []
        self.rejected_samples: list[RejectedSample] = []
        self.closed = False

    def applied(self, sample: AppliedSample) -> None:
        self.applied_samples.append(sample)

    def rejected(self, sample: RejectedSample) -> None:
        self.rejected_samples.append(sample)

    def stats(self) -> SinkStats:
        return SinkStats(name=self.name, delivered=len(self.applied_samples), pending=0)

    def close(self, timeout: float = 5.0) -> None:
        self.closed = True


class _StatusSink(_Sink):
    def __init__(self) -> None:
        super().__init__()
        self.changes: list[tuple[str, str, str]] = []
        self.told: list[StatusChange] = []

    def status(self, change: StatusChange) -> None:
        self.changes.append((change.device_id, change.previous, change.status))
        self.told.append(change)


class _Clock:
    def __init__(self, t: float) -> None:
        self.now = t

    def __call__(self) -> float:
        return self.now


def test_a_worker_process_mirror_hands_its_sinks_each_status_change() -> None:
    """The mirror a worker process runs (`worker_main`: fed by its pipe, its sinks built from the config),
    on its own thread, on an injected clock: each change its sweeps read reaches its sinks."""
    config = load_config(None, {"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    clock, rng = _Clock(1000.0), random.Random(1)
    reader, writer = Pipe(duplex=False)
    sink = _StatusSink()
    mirror = Mirror(
        config,
        inbox=PipeInbox(reader),
        budget=DeviceBudget(4),
        clock=clock,
        wall_clock=lambda: 1.7e9 + clock.now,
        sinks=[sink],
    )

    def send(received: float) -> None:
        stamp = 1.7e9 + received  # the edge's clock, in epoch seconds
        doc = make_payload("arm-001", stamp, "ticks", rng, timestamp_ms=round(stamp * 1000))
        topic = telemetry_topic(DEFAULT_TOPIC_PREFIX, "arm-001")
        send_batch(writer, [("arm-001", (topic, encode(doc), received, stamp))])

    mirror.start()
    try:
        send(clock.now)
        wait_for(lambda: sink.applied_samples, 30, "the first sample")
        health = config.health
        clock.now += health.stale_after_s + FleetWatch.interval_s
        wait_for(lambda: len(sink.changes) == 1, 30, "the arm to go STALE")
        clock.now += health.offline_after_s
        wait_for(lambda: len(sink.changes) == 2, 30, "the arm to go OFFLINE")
        # The arm publishes again, and the clock steps on until a sweep reads it back: a sweep may have read
        # the clock just before a sample came and put the next one an interval on. A step is taken only once
        # the worker has applied every sample sent, and is shorter than stale_after_s, so however the
        # threads interleave no sweep finds the returning arm silent long enough to go STALE again.
        step = health.stale_after_s / 3
        sent = len(sink.applied_samples)

        def back_online() -> bool:
            nonlocal sent
            if len(sink.changes) < 3 and len(sink.applied_samples) == sent:
                clock.now += step
                send(clock.now)
                sent += 1
            return len(sink.changes) == 3

        wait_for(back_online, 30, "the arm to come back")
    finally:
        send_end(writer)
        mirror.stop(timeout=30.0)
    assert sink.changes == [
        ("arm-001", "ONLINE", "STALE"),
        ("arm-001", "STALE", "OFFLINE"),
        ("arm-001", "OFFLINE", "ONLINE"),
    ]


def test_the_sinks_are_told_of_a_forget_and_the_mirror_keeps_nothing_of_the_arm() -> None:
    """The mirror kept what its sinks were last told of each arm it forgot (they still labelled it OFFLINE),
    a second record beside the sink's own. The sinks are told of the forget instead, and drop theirs."""
    config = load_config(None, {"telemetry.devices": ["*"], "telemetry.max_devices": 2})
    sink = _StatusSink()
    mirror = Mirror(config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(4), sinks=[sink])
    mirror._open_sinks()  # the sinks without the worker thread: the test calls the mirror's steps
    told = sink.told
    arms = ("arm-001", "arm-002", "arm-003")
    mirror._hand_statuses(dict.fromkeys(arms, DeviceStatus.OFFLINE), 1.0, 1.0)
    for arm in arms:
        mirror._sinks_forgot(arm)
    assert [(c.device_id, c.previous, c.forgotten) for c in told[3:]] == [
        (arm, DeviceStatus.OFFLINE, True) for arm in arms
    ]
    assert mirror._sinks_saw == {}
    told.clear()
    # An arm of that name that publishes again is new: ONLINE to the sinks from the start.
    mirror._hand_statuses(dict.fromkeys(arms, DeviceStatus.ONLINE), 2.0, 2.0)
    assert told == []


def test_a_stop_report_names_a_sinks_queued_status_changes_with_its_samples() -> None:
    """A review: the stop report counted what a queued sink still held as `<sink>_samples`, though a sink
    that shows statuses holds status changes too. Both count, under a name that says items."""
    gate = threading.Event()
    worker = _GatedStatusRecorder(gate)
    queued = QueuedSink("shows", worker, max_pending=10)
    config = load_config(None, {"telemetry.devices": ["*"]})
    mirror = Mirror(config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(4), sinks=[queued])
    mirror._open_sinks()  # the sinks without the worker thread: the test calls the mirror's steps
    try:
        queued.applied(_sample(0))
        assert worker.entered.wait(30), "the sink's thread never took the first sample"
        queued.status(_change("arm-001", DeviceStatus.ONLINE, DeviceStatus.STALE))
        queued.applied(_sample(1))
        assert mirror.stop_report().unwritten == {"shows_items": 1 + 2}
    finally:
        gate.set()
        queued.close()


@pytest.mark.slow
def test_an_agent_recording_onto_a_full_disk_still_starts_and_mirrors(tmp_path: Path) -> None:
    """A worker's first session on a full disk raised, so `twin run` exited 1 and a worker that died could
    not be started again (a walk's arms stayed OFFLINE, `worker 1 is not running`, until the disk had room):
    a recording stopped the mirroring. The recording starts set aside instead, its samples counted as the
    output's drops. A real full filesystem: a 1 MiB tmpfs, filled (the tests run as root)."""
    with (
        full_disk(tmp_path / "disk") as disk,
        fed_agent(12, **{"twin.record_dir": str(disk / "usd")}) as service,
    ):
        assert service.state().devices["arm-001"].health.counters.applied == 12

        # The sink takes the samples on a thread of its own, after the worker has handled them: its
        # counts are waited for, as the test below does, not read once.
        def usd_took_all() -> SinkStats | None:
            usd = next(s for s in service.state().agent.sinks if s.name == "usd")
            return usd if usd.delivered == 12 else None

        usd = wait_for(usd_took_all, 30, "the recording sink to take every applied sample")
        assert usd.dropped == 12


def test_the_agent_hands_every_sample_to_every_sink_and_reports_them(tmp_path: Path) -> None:
    sink = _Sink()
    with fed_agent(12, sinks=[sink], **{"twin.record_dir": str(tmp_path)}) as service:
        state = service.state()
        samples = parse_metrics(render_metrics(state))
        arm = state.devices["arm-001"]
        assert [s.name for s in service.sinks] == ["usd", "collect"]
        # Every applied sample reaches the recorder, which keeps at most 30 per second of receive time.
        wait_for(
            lambda: next(s for s in service.state().agent.sinks if s.name == "usd").delivered == 12,
            30,
            "the recording sink to take every applied sample",
        )
        recording = service.state().agent.recording
        assert recording is not None
        assert recording.samples_written >= 1
        assert recording.samples_written + recording.samples_dropped == 12
    assert sink.closed  # stop() closes the sinks it was given
    # One AppliedSample per applied message, carrying the decoded telemetry and the angles the twin shows.
    assert len(sink.applied_samples) == arm.health.counters.applied == 12
    last = sink.applied_samples[-1]
    assert last.device_id == "arm-001" and dict(last.joint_angles) == arm.joints_rad
    assert last.timestamp_ms == arm.timestamp_ms
    stamps = [s.timestamp_ms for s in sink.applied_samples]
    assert stamps == sorted(stamps)
    # One RejectedSample per rejection: the topic's device (tracked or not), the reason it was counted
    # under, and the raw payload.
    assert {(s.device_id, s.reason, s.payload) for s in sink.rejected_samples} == {
        ("arm-001", "not_json", b"{not json"),
        ("ghost", "not_utf8", b"\xff"),
    }
    # Sink figures in the typed state and in /metrics.
    by_name = {s.name: s for s in state.agent.sinks}
    assert by_name["collect"].delivered == 12
    assert metric(samples, "twin_sink_delivered_total", sink="collect") == 12
    assert metric(samples, "twin_sink_dropped_total", sink="usd") == by_name["usd"].dropped == 0
    assert Path(recording.path).parent == tmp_path.resolve() and Path(recording.path).is_file()


def test_a_stopped_agent_names_no_session_file_it_removed(tmp_path: Path) -> None:
    """A walk: after the stop, `agent.recording.path` named a session that recorded no sample, which the
    recorder removes at close. A stopped agent that recorded nothing names none."""
    with fed_agent(0, **{"twin.record_dir": str(tmp_path)}) as service:
        path = service.recording_path
        assert path is not None and path.is_file()
    recording = service.state().agent.recording
    assert recording is not None and recording.path == "" and service.recording_path is None
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_a_stopped_agent_still_reports_its_recording(tmp_path: Path, workers: int) -> None:
    """A walk: with worker processes, the state after the stop had no recording (the workers that held it
    were gone), so `twin run`'s last figures and a test reading them found none. The workers hand their
    recording's final figures back with their stop report, and the agent keeps them, as in one process."""
    with fed_agent(12, workers=workers, **{"twin.record_dir": str(tmp_path)}) as service:
        wait_for(
            lambda: next(s for s in service.state().agent.sinks if s.name == "usd").delivered == 12,
            30,
            "the recording sink to take every applied sample",
        )
    state = service.state()
    recording = state.agent.recording
    assert recording is not None, state.agent
    assert recording.samples_written >= 1 and recording.samples_written + recording.samples_dropped == 12
    assert recording.flushes >= 1
    # arm-001's session, the one kept; with two workers arm-002's recorded nothing and was removed.
    assert Path(recording.path).is_file() and list(tmp_path.iterdir()) == [Path(recording.path)]
    if workers > 1:
        assert [w.recording for w in state.agent.workers] == [recording.path, ""]


def test_body_pose_array_is_body_poses_stacked() -> None:
    robot = RobotModel.load()
    angles = {
        "shoulder_pan": -0.4,
        "shoulder_lift": 0.9,
        "elbow_flex": -1.2,
        "wrist_roll": 2.0,
        "gripper": 1.0,
    }
    poses = robot.body_poses(angles)
    stacked = robot.body_pose_array(angles)
    assert stacked.shape == (len(robot.body_ids), 7)
    for row, name in enumerate(robot.body_ids):
        np.testing.assert_array_equal(stacked[row, :3], poses[name][0])
        np.testing.assert_array_equal(stacked[row, 3:], poses[name][1])
    # A fresh array each call: a caller may keep it while the thread's workspace moves on.
    again = robot.body_pose_array({})
    assert not np.shares_memory(stacked, again)
    assert not np.allclose(stacked, again)


def test_device_rate_cap_shares_a_fleet_budget_among_the_devices() -> None:
    from twin.output.sinks import DeviceRateCap

    def passed(devices: int, seconds: float = 20.0) -> list[int]:
        cap = DeviceRateCap(10.0, burst=50.0, fleet_rate_hz=20.0)
        counts = [0] * devices
        for i in range(int(seconds * 10)):  # every device at 10 Hz, interleaved
            for d in range(devices):
                counts[d] += cap.take(f"arm-{d}", 100.0 + i / 10)
        return counts

    # Two arms at 10 Hz fit the fleet's 20 a second: nothing is held back.
    assert passed(2) == [200, 200]
    # Four get 5 a second each, after a burst scaled the same way (25 samples, 5 s of the share); the first,
    # alone for its first sample, started with the full burst.
    four = passed(4)
    assert all(5 * 20 <= n <= 5 * 20 + 50 for n in four), four
    assert sum(four[1:]) <= 3 * (5 * 20 + 25 + 1), four


def test_device_rate_cap_forgets_devices_that_went_silent() -> None:
    """The fleet's share counts the devices heard from lately: arms that left give their share back."""
    from twin.output.sinks import FORGET_DEVICE_AFTER_S, DeviceRateCap

    cap = DeviceRateCap(10.0, burst=10.0, fleet_rate_hz=20.0)

    def second(devices: range, start: float) -> list[int]:
        counts = [0] * len(devices)
        for i in range(10):  # one second of every device at 10 Hz
            for k, d in enumerate(devices):
                counts[k] += cap.take(f"arm-{d}", start + i / 10)
        return counts

    for t in range(5):  # four arms for 5 s: 5 Hz each once their (scaled) burst is spent
        second(range(4), 100.0 + t)
    assert cap.devices == 4
    # Two of them stop. While the other two are still counted as four, they get 5 Hz each ...
    early = second(range(2), 105.0)
    assert all(n <= 6 for n in early), early
    # ... and once the silent two are forgotten, the fleet's 20 a second is theirs: 10 Hz each.
    for t in range(1, int(FORGET_DEVICE_AFTER_S) + 2):
        second(range(2), 105.0 + t)
    assert cap.devices == 2
    assert second(range(2), 120.0) == [10, 10]
    # A device that comes back starts with a full bucket, as a bucket left alone that long would be.
    assert [cap.take("arm-3", 121.0) for _ in range(4)] == [True, True, True, True]
    assert cap.devices == 3


def test_device_rate_cap_holds_each_device_to_its_rate_after_the_burst() -> None:
    from twin.output.sinks import DeviceRateCap

    cap = DeviceRateCap(10.0, burst=3.0)
    # A backlog released at once: the burst passes, the rest is held until the bucket refills.
    assert [cap.take("arm-001", 100.0) for _ in range(5)] == [True, True, True, False, False]
    # Another arm has its own bucket.
    assert cap.take("arm-002", 100.0)
    # A quarter of a second later two and a half tokens are back (10 a second): two samples pass.
    assert [cap.take("arm-001", 100.25) for _ in range(3)] == [True, True, False]
    # A long pause refills to the burst, never beyond it.
    assert [cap.take("arm-001", 200.0) for _ in range(4)] == [True, True, True, False]
