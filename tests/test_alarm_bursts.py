"""A burst of model_mismatch raises (one cause, many servos) is one warning, each alarm still its own.

Another edge simulator taking over the arms' device ids (another model, calibration or servo version) makes
every still servo mismatch the model at once. Each servo's alarm is real and stays listed, counted and in the
events (the Sessions page counts raises, e-mails name them); what changes is how loud the burst is: the first
few raises are warnings as ever, the rest info, and one warning sums them up (events.MismatchBurst).
"""

from __future__ import annotations

import logging
import random
from multiprocessing import Pipe

import pytest
from twin.core.alarms import AlarmEvent, AlarmKind, AlarmState, Severity
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.edge.servo_faults import ModelLoads
from twin.service import mirror as mirror_module
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.events import (
    MISMATCH_BURST_TOLD,
    MISMATCH_BURST_WINDOW_S,
    EventKind,
    EventQuery,
    EventStore,
    FleetWatch,
)
from twin.service.mirror import Mirror, PipeInbox
from twin.transport.pipe import Batch

ARMS = [f"arm-{i:03d}" for i in range(1, 33)]
MISMATCH = str(AlarmKind.MODEL_MISMATCH)


class _Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _still_fleet(mirror: Mirror, clock: _Clock, loads: ModelLoads, rounds: range, scale: float) -> None:
    """10 Hz rounds of every arm holding a pose of its own, its servos reporting the model's holding loads
    times `scale` (1: the simulator the agent's model agrees with; 2: one with another model)."""
    rng = random.Random(1)
    for r in rounds:
        clock.now += 0.1
        messages = []
        for i, device in enumerate(ARMS):
            doc = make_payload(device, i * 0.37, "ticks", rng, timestamp_ms=1_700_000_000_000 + r * 100,
                               model_loads=loads)  # fmt: skip
            for joint in doc["joints"].values():
                magnitude, sign = joint["load"] & 1023, joint["load"] & 1024
                joint["velocity"] = 0
                joint["load"] = min(1000, round(magnitude * scale)) | sign
            messages.append((device, telemetry_topic(DEFAULT_TOPIC_PREFIX, device), encode(doc)))
        for k in range(0, len(messages), 8):
            part = messages[k : k + 8]
            n = len(part)
            batch = Batch(
                tuple(d for d, _, _ in part),
                tuple(t for _, t, _ in part),
                tuple(p for _, _, p in part),
                (clock.now,) * n,
                (1.7e9 + clock.now,) * n,
            )
            mirror._handle(batch, 0)


def test_a_simulator_swap_is_one_warning_and_every_mismatching_servo_keeps_its_alarm(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = _Clock()
    config = load_config(None, {"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    mirror = Mirror(
        config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(64), clock=clock, wall_clock=clock
    )
    loads = ModelLoads()
    _still_fleet(mirror, clock, loads, range(0, 30), scale=1.0)
    assert mirror.alarms() == ()
    first = mirror._events.last_id
    caplog.set_level(logging.INFO, logger="twin")
    _still_fleet(mirror, clock, loads, range(30, 60), scale=2.0)  # the other simulator takes over
    clock.now += MISMATCH_BURST_WINDOW_S
    mirror._watch_statuses()

    # The truth: one alarm per servo that mismatches, each raised once, listed, counted and in the events.
    listed = [a for a in mirror.alarms() if a.kind == MISMATCH]
    assert len(listed) > 40 and all(a.state == "ACTIVE" for a in listed)
    assert mirror.report().alarms.raised_total[MISMATCH] == len(listed)
    alarm_events = [e for e in mirror._events.query(EventQuery(after_id=first)) if e.kind == EventKind.ALARM]
    raised = [e for e in alarm_events if e.data.get("action") == "raised" and e.data["kind"] == MISMATCH]
    assert sorted(e.data["alarm_id"] for e in raised) == sorted(a.alarm_id for a in listed)
    # The noise: the first few are warnings, the rest info, and one warning says how many and what to check.
    assert [e.level for e in raised].count("warning") == MISMATCH_BURST_TOLD
    bursts = [e for e in alarm_events if e.data.get("action") == "burst"]
    assert len(bursts) == 1 and bursts[0].level == "warning"
    assert bursts[0].data["raised"] == str(len(listed)) and bursts[0].data["arms"] == str(len(ARMS))
    assert "check what publishes for these arms" in bursts[0].message
    # The log the same way; every state change is still a line with its fields.
    lines = [r for r in caplog.records if getattr(r, "event", None) == "servo_alarm" and r.kind == MISMATCH]
    assert len(lines) == len(listed)
    assert [r.levelno for r in lines].count(logging.WARNING) == MISMATCH_BURST_TOLD
    summaries = [r for r in caplog.records if getattr(r, "event", None) == "servo_alarm_burst"]
    assert len(summaries) == 1 and summaries[0].levelno == logging.WARNING


def _raise(device: str, joint: str, at: float, kind: AlarmKind = AlarmKind.MODEL_MISMATCH) -> AlarmEvent:
    return AlarmEvent(
        alarm_id=f"{device}/{joint}/{kind}",
        device=device,
        joint=joint,
        kind=kind,
        severity=Severity.CRITICAL if kind is AlarmKind.OVER_CURRENT else Severity.WARNING,
        previous=AlarmState.NORMAL,
        state=AlarmState.ACTIVE,
        action="raised",
        value=30.0,
        threshold=15.0,
        at=at,
        message="differs",
    )


def test_a_lone_mismatch_is_a_warning_at_once_and_a_burst_window_ends() -> None:
    store = EventStore(100)
    watch = FleetWatch(store)
    # A contact on one arm: told at once, nothing to sum up.
    assert watch.alarm(_raise("arm-001", "elbow_flex", 10.0))
    watch.alarm_bursts(10.0 + MISMATCH_BURST_WINDOW_S)
    assert [e.data.get("action") for e in store.query(EventQuery())] == ["raised"]
    # A burst: the first few told, the rest held; a critical raise among them is never held.
    told = [watch.alarm(_raise(f"arm-{i:03d}", "shoulder_lift", 100.0 + i * 0.01)) for i in range(10)]
    assert told == [True] * MISMATCH_BURST_TOLD + [False] * (10 - MISMATCH_BURST_TOLD)
    assert watch.alarm(_raise("arm-050", "gripper", 100.5, AlarmKind.OVER_CURRENT))
    watch.alarm_bursts(100.0 + MISMATCH_BURST_WINDOW_S - 0.1)  # not yet
    assert not [e for e in store.query(EventQuery()) if e.data.get("action") == "burst"]
    # A raise after the window: the burst is summed up first, and a new window tells it.
    assert watch.alarm(_raise("arm-060", "elbow_flex", 100.0 + MISMATCH_BURST_WINDOW_S))
    bursts = [e for e in store.query(EventQuery()) if e.data.get("action") == "burst"]
    assert [(e.data["raised"], e.data["arms"], e.data["told"]) for e in bursts] == [("10", "10", "3")]


def test_a_raised_alarms_log_line_says_what_to_do_at_the_arm(caplog: pytest.LogCaptureFixture) -> None:
    """A walk: the e-mail and /alarms said what to do about a hot servo, the log line only what it was; on a
    host whose e-mail is off the log is what a person reads. A clear needs nothing done at the arm."""

    def event(action: str, state: AlarmState, value: float) -> AlarmEvent:
        return AlarmEvent(
            "arm-003/wrist_flex/servo_error", "arm-003", "wrist_flex", AlarmKind.SERVO_ERROR,
            Severity.CRITICAL, AlarmState.NORMAL, state, action, value, 1.0, 0.0,
            "wrist_flex servo (motor id 4) reports overload",
        )  # fmt: skip

    caplog.set_level(logging.INFO, logger="twin.service.mirror")
    mirror_module._log_alarm_event(event("raised", AlarmState.ACTIVE, 32.0))
    mirror_module._log_alarm_event(event("cleared", AlarmState.LATCHED, 0.0))
    raised, cleared = [r for r in caplog.records if getattr(r, "event", None) == "servo_alarm"]
    advice: str = vars(raised)["advice"]
    # The servo's own bits narrow it: overload's advice, not the voltage supply's.
    assert advice.startswith("the arm may not hold its pose") and "Overload:" in advice
    assert "Voltage" not in advice
    assert raised.getMessage().startswith("servo alarm raised on arm-003: wrist_flex servo (motor id 4) ")
    assert raised.getMessage().endswith(f"; what to do: {advice}")
    assert not hasattr(cleared, "advice") and "what to do" not in cleared.getMessage()
