"""twin.output.sinks: the queued sink never blocks its caller, drops the oldest when full and counts it,
survives a failing worker, and delivers everything queued on close; RobotModel.body_poses matches a twin."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from twin.core.telemetry import Telemetry, Units
from twin.core.twin import DeviceTwin
from twin.output.sinks import AppliedSample, QueuedSink, RejectedSample
from twin.robot import so101
from twin.robot.model import RobotModel


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

    def handle_applied(self, sample: AppliedSample) -> None:
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


def test_a_stalled_worker_never_blocks_the_caller_and_drops_the_oldest() -> None:
    gate = threading.Event()
    worker = _Recorder(gate=gate)
    sink = QueuedSink("slow", worker, max_pending=10)
    started = time.monotonic()
    for i in range(1000):
        sink.applied(_sample(i))
    put_time = time.monotonic() - started
    gate.set()
    sink.close()
    # The worker held one item when the gate closed; of the rest only the newest 10 survive.
    assert worker.applied[-10:] == list(range(990, 1000))
    assert len(worker.applied) <= 11
    stats = sink.stats()
    assert stats.dropped == 1000 - len(worker.applied)
    # Not a timing assertion of the design's speed: a generous bound that only a blocking put would break.
    assert put_time < 5.0


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
    deadline = time.monotonic() + 5
    while worker.idles < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    sink.close()
    assert worker.idles >= 2


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
