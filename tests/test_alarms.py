"""Servo alarms: each one raised, latched, acknowledged and cleared with hysteresis and minimum durations.

The clock is a number passed in, so time is exact and nothing sleeps. Figures are worked out by hand from the
servo facts (twin.robot.sts3215): the 7.4 V STS3215 stalls at 16.5 kg·cm = 1.61809725 N·m at 6 V.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping, Sequence
from typing import Any

import pytest
from twin.core.alarms import (
    SERVO_ERROR_LEAD,
    AlarmKind,
    AlarmNotFound,
    AlarmState,
    AlarmThresholds,
    NothingToAcknowledge,
    ServoAlarms,
    Severity,
    alarm_id,
    record_view,
    worst_first,
)
from twin.core.telemetry import JointDiagnostics
from twin.robot import so101, sts3215
from twin.service.shards import alarm_info

DEV = "arm-001"
STILL: dict[str, Any] = {"velocity_rad_s": 0.0, "moving": False}


def readings(joint: str = "elbow_flex", **fields: Any) -> dict[str, JointDiagnostics]:
    """Diagnostics for all six joints: `fields` on `joint`, a cool idle servo everywhere else."""
    idle = JointDiagnostics(temperature_c=35.0, current_a=0.2, load_percent=5.0, **STILL)
    return {
        name: JointDiagnostics(**{**STILL, **fields}) if name == joint else idle for name in so101.JOINT_NAMES
    }


def run(
    alarms: ServoAlarms,
    steps: list[tuple[float, dict[str, Any]]],
    *,
    joint: str = "elbow_flex",
    torques: dict[str, float] | None = None,
) -> list[tuple[float, str, AlarmKind, AlarmState]]:
    """Feed (time, fields) samples; returns (time, action, kind, new state) of every event."""
    out = []
    for now, fields in steps:
        for e in alarms.evaluate(DEV, readings(joint, **fields), torques or {}, now):
            assert e.joint == joint
            out.append((now, e.action, e.kind, e.state))
    return out


def state(alarms: ServoAlarms, kind: AlarmKind, joint: str = "elbow_flex") -> AlarmState:
    view = alarms.get(alarm_id(DEV, joint, kind))
    return AlarmState.NORMAL if view is None else view.state


# --- the servo figures the rules use ------------------------------------------------------------------------


def test_servo_figures() -> None:
    v74 = sts3215.servo_version("7.4v")
    assert v74.stall_torque_nm == pytest.approx(1.61809725)  # 16.5 x 0.0980665
    assert v74.stall_torque_at(5.0) == pytest.approx(1.348414375)  # x 5/6: stall torque follows the supply
    assert v74.stall_torque_at(None) == v74.stall_torque_at(0.0) == pytest.approx(1.61809725)
    assert v74.load_percent(0.5) == pytest.approx(30.900491, abs=1e-6)  # 0.5 / 1.61809725
    assert v74.load_percent(0.5, 5.0) == pytest.approx(37.080589, abs=1e-6)  # 0.5 / 1.348414375
    assert sts3215.servo_version("12v").stall_torque_nm == pytest.approx(2.941995)  # 30 x 0.0980665
    assert pytest.approx(3.25) == sts3215.PROTECTION_CURRENT_A  # 500 x 6.5 mA
    assert pytest.approx(1.625) == sts3215.GRIPPER_PROTECTION_CURRENT_A  # 250 x 6.5 mA
    with pytest.raises(ValueError, match=r"7\.4v, 12v"):
        sts3215.servo_version("6v")


def test_default_thresholds_come_from_the_servo_settings() -> None:
    t = AlarmThresholds()
    assert t.temperature_critical_c == 65.0  # 5 C before the 70 C cut-out
    assert t.current_a == pytest.approx(2.6)  # 80 % of 3.25 A
    assert t.gripper_current_a == pytest.approx(1.3)  # 80 % of LeRobot's 1.625 A
    assert t.current_raise_after_s == 1.0  # half the servo's 2 s over-current protection time
    assert (t.overload_percent, t.gripper_overload_percent) == (80.0, 25.0)
    assert t.rule(AlarmKind.OVERLOAD, "gripper").raise_at == 25.0
    assert t.rule(AlarmKind.OVERLOAD, "shoulder_lift").raise_at == 80.0


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"temperature_warning_clear_c": 60.0}, "over_temperature clears at 60"),
        ({"gripper_overload_clear_percent": 30.0}, "overload clears at 30"),
        (
            {"current_raise_after_s": -1.0},
            r"current_raise_after_s \(-1\) and current_clear_after_s \(2\) are",
        ),
        (
            {"servo_error_clear_after_s": -1.0},
            r"servo_error_clear_after_s \(-1\) are seconds a value must be held",
        ),
        ({"mismatch_percent": float("nan")}, "finite"),
        ({"servo_version": "24v"}, r"not one of 7\.4v, 12v"),
        ({"mismatch_joints": ("elbow",)}, "unknown joints"),
        ({"servo_error_bits": ("overheat",)}, r"unknown status bits \['overheat'\]; choose from \['voltage'"),
    ],
)
def test_bad_thresholds_are_refused_with_the_fix(changes: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        AlarmThresholds(**changes)


# --- over-temperature ---------------------------------------------------------------------------------------


def test_over_temperature_raised_acknowledged_cleared() -> None:
    alarms = ServoAlarms()
    events = run(
        alarms,
        [
            (0.0, {"temperature_c": 50.0}),
            (1.0, {"temperature_c": 60.0}),  # at the line: the 2 s timer starts
            (2.9, {"temperature_c": 61.0}),  # 1.9 s: not yet
            (3.0, {"temperature_c": 61.0}),  # 2.0 s: raised
        ],
    )
    assert events == [(3.0, "raised", AlarmKind.OVER_TEMPERATURE, AlarmState.ACTIVE)]
    view = alarms.get(alarm_id(DEV, "elbow_flex", AlarmKind.OVER_TEMPERATURE))
    assert view is not None
    assert (view.severity, view.value, view.threshold, view.unit, view.raised) == (
        Severity.WARNING,
        61.0,
        60.0,
        "C",
        1,
    )
    assert "61 C" in view.message and "70 C" in view.message
    # The servo as a person at the arm finds it: its joint and its bus id (LeRobot's 1..6).
    assert view.message.startswith("elbow_flex servo (motor id 3) at 61 C"), view.message

    ack = alarms.acknowledge(view.alarm_id, 4.0)
    assert (ack.previous, ack.state, ack.action) == (
        AlarmState.ACTIVE,
        AlarmState.ACKNOWLEDGED,
        "acknowledged",
    )
    # Every message of the alarm names the servo as its raise did (a walk: "cleared" had no motor id).
    assert ack.message.startswith("elbow_flex servo (motor id 3) over_temperature acknowledged"), ack.message
    with pytest.raises(NothingToAcknowledge, match="is ACKNOWLEDGED: only ACTIVE or LATCHED") as already:
        alarms.acknowledge(view.alarm_id, 4.5)
    assert already.value.state == "ACKNOWLEDGED"

    events = run(
        alarms,
        [
            (5.0, {"temperature_c": 57.0}),  # between 55 and 60: holds
            (30.0, {"temperature_c": 57.0}),
            (31.0, {"temperature_c": 55.0}),  # at the clear line: the 10 s timer starts
            (40.9, {"temperature_c": 54.0}),
            (41.0, {"temperature_c": 54.0}),  # 10 s: cleared, and acknowledged alarms go straight to NORMAL
        ],
    )
    assert events == [(41.0, "cleared", AlarmKind.OVER_TEMPERATURE, AlarmState.NORMAL)]


def test_every_message_of_an_alarm_names_its_servo_as_the_raise_did() -> None:
    """A walk: the raise said "elbow_flex servo (motor id 3)", the clear only "elbow_flex"."""
    alarms = ServoAlarms()
    run(alarms, [(0.0, {"temperature_c": 62.0}), (2.0, {"temperature_c": 62.0})])
    events = [e for now in (3.0, 13.0) for e in alarms.evaluate(DEV, readings(temperature_c=50.0), {}, now)]
    (cleared,) = [e for e in events if e.action == "cleared"]
    assert cleared.message.startswith(
        "elbow_flex servo (motor id 3) over_temperature cleared: at or below 55 C"
    )
    assert cleared.message.endswith("(latched until acknowledged)"), cleared.message
    reset = alarms.acknowledge(cleared.alarm_id, 14.0)
    assert reset.message == "elbow_flex servo (motor id 3) over_temperature reset by a person", reset.message


def test_unacknowledged_alarm_latches_until_acknowledged() -> None:
    alarms = ServoAlarms()
    run(alarms, [(0.0, {"temperature_c": 62.0}), (2.0, {"temperature_c": 62.0})])
    assert state(alarms, AlarmKind.OVER_TEMPERATURE) is AlarmState.ACTIVE
    events = run(alarms, [(3.0, {"temperature_c": 40.0}), (13.0, {"temperature_c": 40.0})])
    assert events == [(13.0, "cleared", AlarmKind.OVER_TEMPERATURE, AlarmState.LATCHED)]
    # Latched: the condition is gone but nobody saw it; acknowledging resets it to NORMAL.
    assert alarms.present_by_severity() == {Severity.WARNING: 0, Severity.CRITICAL: 0}
    reset = alarms.acknowledge(alarm_id(DEV, "elbow_flex", AlarmKind.OVER_TEMPERATURE), 20.0)
    assert (reset.previous, reset.state, reset.action) == (AlarmState.LATCHED, AlarmState.NORMAL, "reset")
    with pytest.raises(NothingToAcknowledge, match="is NORMAL, already cleared: nothing waits") as cleared:
        alarms.acknowledge(reset.alarm_id, 21.0)
    assert cleared.value.state == "NORMAL"


def test_latched_alarm_that_returns_is_active_again() -> None:
    alarms = ServoAlarms()
    steps = [(0.0, 62.0), (2.0, 62.0), (3.0, 40.0), (13.0, 40.0), (14.0, 63.0), (16.0, 63.0)]
    events = run(alarms, [(t, {"temperature_c": c}) for t, c in steps])
    assert [(t, s) for t, _, _, s in events] == [
        (2.0, AlarmState.ACTIVE),
        (13.0, AlarmState.LATCHED),
        (16.0, AlarmState.ACTIVE),
    ]
    assert alarms.get(alarm_id(DEV, "elbow_flex", AlarmKind.OVER_TEMPERATURE)).raised == 2  # type: ignore[union-attr]


def test_without_latching_a_cleared_alarm_returns_to_normal() -> None:
    alarms = ServoAlarms(AlarmThresholds(latch=False))
    events = run(
        alarms, [(t, {"temperature_c": c}) for t, c in [(0, 62.0), (2, 62.0), (3, 40.0), (13, 40.0)]]
    )
    assert [s for *_, s in events] == [AlarmState.ACTIVE, AlarmState.NORMAL]


def test_a_reading_that_dips_restarts_the_timers() -> None:
    alarms = ServoAlarms()
    # 61 C never holds for 2 s: each dip to 59 (between the lines) restarts the raise timer.
    flapping = [(t * 0.5, {"temperature_c": 61.0 if t % 3 else 59.0}) for t in range(40)]
    assert run(alarms, flapping) == []
    run(alarms, [(20.0, {"temperature_c": 61.0}), (22.0, {"temperature_c": 61.0})])
    assert state(alarms, AlarmKind.OVER_TEMPERATURE) is AlarmState.ACTIVE
    # Clearing needs 10 s at or below 55 in one stretch: 56 at 27 s restarts it.
    steps = [(23.0, 54.0), (27.0, 56.0), (28.0, 54.0), (37.9, 54.0)]
    assert run(alarms, [(t, {"temperature_c": c}) for t, c in steps]) == []
    assert run(alarms, [(38.0, {"temperature_c": 54.0})])[0][3] is AlarmState.LATCHED


def test_missing_readings_hold_the_state() -> None:
    alarms = ServoAlarms()
    run(alarms, [(0.0, {"temperature_c": 62.0}), (2.0, {"temperature_c": 62.0})])
    # The edge stops sending temp: nothing is known, so nothing clears, however long.
    assert run(alarms, [(t, {}) for t in (3.0, 100.0, 1000.0)]) == []
    assert state(alarms, AlarmKind.OVER_TEMPERATURE) is AlarmState.ACTIVE
    # A joint that never sent a value has no alarm record at all.
    assert alarms.get(alarm_id(DEV, "elbow_flex", AlarmKind.OVER_CURRENT)) is None


def test_critical_temperature_raises_both_levels() -> None:
    alarms = ServoAlarms()
    events = run(alarms, [(0.0, {"temperature_c": 66.0}), (2.0, {"temperature_c": 66.0})])
    assert sorted(k for _, _, k, _ in events) == [
        AlarmKind.OVER_TEMPERATURE,
        AlarmKind.OVER_TEMPERATURE_CRITICAL,
    ]
    assert alarms.present_by_severity() == {Severity.WARNING: 1, Severity.CRITICAL: 1}
    assert alarms.worst_by_joint(DEV) == {"elbow_flex": (Severity.CRITICAL, AlarmState.ACTIVE)}
    # Cooling to 62 C clears the critical level (at or below 60 C for 10 s) only once it gets there.
    run(alarms, [(3.0, {"temperature_c": 62.0}), (30.0, {"temperature_c": 62.0})])
    assert state(alarms, AlarmKind.OVER_TEMPERATURE_CRITICAL) is AlarmState.ACTIVE
    run(alarms, [(31.0, {"temperature_c": 60.0}), (41.0, {"temperature_c": 60.0})])
    assert state(alarms, AlarmKind.OVER_TEMPERATURE_CRITICAL) is AlarmState.LATCHED
    assert state(alarms, AlarmKind.OVER_TEMPERATURE) is AlarmState.ACTIVE  # 60 C is still at its line


# --- over-current -------------------------------------------------------------------------------------------


def test_over_current_raised_and_cleared() -> None:
    alarms = ServoAlarms()
    steps = [(0.0, 2.7), (0.99, 2.7), (1.0, 2.7), (2.0, 2.4), (10.0, 2.4), (11.0, 2.1), (13.0, 2.1)]
    events = run(alarms, [(t, {"current_a": a}) for t, a in steps])
    assert events == [
        (1.0, "raised", AlarmKind.OVER_CURRENT, AlarmState.ACTIVE),  # 2.7 A >= 2.6 A held 1 s
        (13.0, "cleared", AlarmKind.OVER_CURRENT, AlarmState.LATCHED),  # <= 2.1125 A held 2 s
    ]
    view = alarms.views()[0]
    assert (view.severity, view.unit) == (Severity.CRITICAL, "A")


def test_gripper_has_lerobots_lower_current_limit() -> None:
    alarms = ServoAlarms()
    events = run(alarms, [(0.0, {"current_a": 1.4}), (1.0, {"current_a": 1.4})], joint="gripper")
    assert events == [(1.0, "raised", AlarmKind.OVER_CURRENT, AlarmState.ACTIVE)]  # 1.4 A >= 1.3 A
    assert run(alarms, [(0.0, {"current_a": 1.4}), (1.0, {"current_a": 1.4})], joint="wrist_roll") == []


# --- sustained overload -------------------------------------------------------------------------------------


def test_sustained_overload_in_either_direction() -> None:
    alarms = ServoAlarms()
    # -85 %: the sign bit says which way; the magnitude is what overloads the servo.
    steps = [(0.0, -85.0), (0.5, -85.0), (1.0, -85.0), (1.5, -50.0), (3.5, -50.0)]
    events = run(alarms, [(t, {"load_percent": p}) for t, p in steps])
    assert events == [
        (1.0, "raised", AlarmKind.OVERLOAD, AlarmState.ACTIVE),
        (3.5, "cleared", AlarmKind.OVERLOAD, AlarmState.LATCHED),
    ]
    # A short peak is no sustained overload.
    alarms = ServoAlarms()
    assert run(alarms, [(0.0, {"load_percent": 95.0}), (0.9, {"load_percent": 95.0}), (1.0, {})]) == []


# --- the servo's own errors ---------------------------------------------------------------------------------


def test_a_servo_error_bit_raises_at_once_and_names_the_servo_and_the_bit() -> None:
    """A walk: the servo's status bits (its own protection acting) were shown and raised nothing."""
    alarms = ServoAlarms()
    # 32 = bit 5, overload; 34 also the sensor bit; 0 = no error, held 2 s to clear.
    steps = [(0.0, 0), (1.0, 32), (1.1, 34)]
    events = run(alarms, [(t, {"status": v}) for t, v in steps], joint="wrist_flex")
    assert events == [(1.0, "raised", AlarmKind.SERVO_ERROR, AlarmState.ACTIVE)]
    # Its value is the last message's error bits (a walk saw the model mismatch's figure there).
    assert alarms.views()[0].value == 34.0
    assert run(alarms, [(2.0, {"status": 0}), (3.9, {"status": 0})], joint="wrist_flex") == []
    (cleared,) = alarms.evaluate(DEV, readings("wrist_flex", status=0), {}, 4.0)
    assert (cleared.action, cleared.state) == ("cleared", AlarmState.LATCHED)
    assert cleared.message == (
        "wrist_flex servo (motor id 4) servo_error cleared: no error bit set for 2 s "
        "(latched until acknowledged)"
    )
    view = alarms.views()[0]
    assert (view.severity, view.unit) == (Severity.CRITICAL, "status")
    assert view.message == (
        "wrist_flex servo (motor id 4) reports an error of its own: overload (status bits 32); its "
        "protection acted and may have cut or limited its torque"
    )
    # Latched, its value holds no bit: /alarms advised on all six (voltage, calibrate...), not its overload.
    assert view.state is AlarmState.LATCHED and view.value == 0.0, view
    advice = alarm_info(view, 0.0, 0.0).advice
    assert advice.startswith(SERVO_ERROR_LEAD) and "Overload: reduce the payload" in advice, advice
    assert "Voltage" not in advice and "calibrate" not in advice, advice


def test_a_negative_status_names_no_error_bit() -> None:
    """A walk sent status -1: /state and the Arm page listed all six bits (Python's -1 has every bit)."""
    assert sts3215.status_names(-1) == () and sts3215.status_names(33) == ("voltage", "overload")


def test_servo_error_bits_chooses_the_bits_and_no_status_holds_the_state() -> None:
    alarms = ServoAlarms(AlarmThresholds(servo_error_bits=("voltage", "temperature")))
    assert alarms.thresholds.status_mask == 0b101
    # The overload bit and bits above the sixth are not errors here; a negative status is no register.
    assert run(alarms, [(0.0, {"status": 32}), (0.1, {"status": 128}), (0.2, {"status": -1})]) == []
    assert run(alarms, [(1.0, {"status": 4})]) == [(1.0, "raised", AlarmKind.SERVO_ERROR, AlarmState.ACTIVE)]
    # An edge that sends no status: nothing known, so the alarm holds, and clears only on a 0 held 2 s.
    assert run(alarms, [(2.0, {}), (5.0, {}), (6.0, {"status": 0})]) == []
    assert run(alarms, [(8.0, {"status": 0})]) == [
        (8.0, "cleared", AlarmKind.SERVO_ERROR, AlarmState.LATCHED)
    ]


# --- model mismatch -----------------------------------------------------------------------------------------

HOLD = {"shoulder_lift": 0.5}  # N m: 30.9 % of the 7.4 V servo's stall torque at 6 V


def test_load_matching_the_model_raises_nothing() -> None:
    alarms = ServoAlarms()
    steps = [(t, {"load_percent": 36.0}) for t in (0.0, 1.0, 5.0)]  # |36 - 30.9| = 5.1 < 15
    assert run(alarms, steps, joint="shoulder_lift", torques=HOLD) == []
    health = alarms.joint_health(DEV)["shoulder_lift"]
    assert health.model_load_percent == pytest.approx(30.900491, abs=1e-6)
    assert health.mismatch_percent == pytest.approx(5.099509, abs=1e-6)
    assert health.still is True


def test_contact_while_still_is_a_model_mismatch() -> None:
    alarms = ServoAlarms()
    # The pose holds (same holding torque) but the load jumps to 70 %: 39.1 points off the model, yet under
    # the 80 % overload line: only the model notices.
    steps = [(0.0, 30.0), (1.0, 70.0), (1.5, 70.0), (2.0, 70.0)]
    events = run(alarms, [(t, {"load_percent": p}) for t, p in steps], joint="shoulder_lift", torques=HOLD)
    assert events == [(2.0, "raised", AlarmKind.MODEL_MISMATCH, AlarmState.ACTIVE)]
    view = alarms.get(alarm_id(DEV, "shoulder_lift", AlarmKind.MODEL_MISMATCH))
    assert view is not None and view.value == pytest.approx(39.099509, abs=1e-6)
    assert "contact, a payload or a failing servo" in view.message and "30.9 %" in view.message
    assert view.message.startswith("shoulder_lift servo (motor id 2) load differs"), view.message
    ack = alarms.acknowledge(view.alarm_id, 3.0)
    assert ack.state is AlarmState.ACKNOWLEDGED
    # Contact released: the load falls back to the model's (|32 - 30.9| <= 10) for 2 s.
    events = run(
        alarms,
        [(4.0, {"load_percent": 32.0}), (6.0, {"load_percent": 32.0})],
        joint="shoulder_lift",
        torques=HOLD,
    )
    assert events == [(6.0, "cleared", AlarmKind.MODEL_MISMATCH, AlarmState.NORMAL)]


def test_the_model_is_only_checked_while_the_joint_is_still() -> None:
    alarms = ServoAlarms()
    moving = {"load_percent": 70.0, "velocity_rad_s": 0.8, "moving": True}
    assert run(alarms, [(t, moving) for t in (0.0, 1.0, 2.0, 3.0)], joint="shoulder_lift", torques=HOLD) == []
    assert alarms.joint_health(DEV)["shoulder_lift"].still is False
    # Slow drift under 0.05 rad/s counts as still; the Moving flag alone decides when velocity is absent.
    slow = {"load_percent": 70.0, "velocity_rad_s": 0.04, "moving": None}
    events = run(alarms, [(4.0, slow), (5.0, slow)], joint="shoulder_lift", torques=HOLD)
    assert [k for _, _, k, _ in events] == [AlarmKind.MODEL_MISMATCH]
    flag_only = ServoAlarms()
    steps = [(t, {"load_percent": 70.0, "velocity_rad_s": None, "moving": False}) for t in (0.0, 1.0)]
    assert len(run(flag_only, steps, joint="shoulder_lift", torques=HOLD)) == 1
    unknown = ServoAlarms()
    steps = [(t, {"load_percent": 70.0, "velocity_rad_s": None, "moving": None}) for t in (0.0, 1.0)]
    assert run(unknown, steps, joint="shoulder_lift", torques=HOLD) == []


def test_supply_voltage_scales_the_expected_load() -> None:
    alarms = ServoAlarms()
    # At 5 V the same 0.5 N m is 37.1 % of the (lower) stall torque: 50 % is 12.9 points off, no alarm;
    # at the quoted 6 V it would be 19.1 points off.
    at_5v = {"load_percent": 50.0, "voltage_v": 5.0}
    assert run(alarms, [(0.0, at_5v), (2.0, at_5v)], joint="shoulder_lift", torques=HOLD) == []
    at_6v = {"load_percent": 50.0, "voltage_v": 6.0}
    assert len(run(alarms, [(3.0, at_6v), (4.0, at_6v)], joint="shoulder_lift", torques=HOLD)) == 1


def test_the_gripper_is_not_checked_against_the_model() -> None:
    alarms = ServoAlarms()
    grasp = [(t, {"load_percent": 22.0}) for t in (0.0, 1.0, 2.0)]  # under its 25 % overload line
    assert run(alarms, grasp, joint="gripper", torques={"gripper": 0.0}) == []
    assert alarms.joint_health(DEV)["gripper"].mismatch_percent is None


# --- people and views ---------------------------------------------------------------------------------------


def test_acknowledging_an_unknown_alarm() -> None:
    with pytest.raises(AlarmNotFound):
        ServoAlarms().acknowledge("arm-001/elbow_flex/over_temperature", 0.0)


def test_views_sort_worst_first_and_hide_normal() -> None:
    alarms = ServoAlarms()
    run(alarms, [(0.0, {"temperature_c": 40.0}), (1.0, {"temperature_c": 40.0})], joint="wrist_flex")
    run(alarms, [(0.0, {"load_percent": 90.0}), (1.0, {"load_percent": 90.0})], joint="shoulder_pan")
    run(alarms, [(0.0, {"current_a": 3.0}), (1.0, {"current_a": 3.0})], joint="elbow_flex")
    assert [(v.joint, v.kind) for v in alarms.views()] == [
        ("elbow_flex", AlarmKind.OVER_CURRENT),
        ("shoulder_pan", AlarmKind.OVERLOAD),
    ]
    assert len(alarms.views(include_normal=True)) > 2
    assert alarms.views(device="arm-002") == []
    assert alarms.worst_by_joint(DEV) == {
        "elbow_flex": (Severity.CRITICAL, AlarmState.ACTIVE),
        "shoulder_pan": (Severity.WARNING, AlarmState.ACTIVE),
    }
    assert alarms.counters.raised[(AlarmKind.OVER_CURRENT, Severity.CRITICAL)] == 1


def test_disabled_alarms_evaluate_nothing() -> None:
    alarms = ServoAlarms(AlarmThresholds(enabled=False))
    assert run(alarms, [(0.0, {"temperature_c": 90.0}), (60.0, {"temperature_c": 90.0})]) == []
    assert alarms.views(include_normal=True) == []


def test_motion_seen_in_the_pose_overrides_a_velocity_field_that_says_still() -> None:
    # The edge's mock mode sends random velocities of a few steps/s while the pose sweeps: the pose decides.
    alarms = ServoAlarms()
    fields = {"load_percent": 70.0, "velocity_rad_s": 0.01, "moving": None}

    def feed(t: float, angle: float) -> list[Any]:
        return alarms.evaluate(
            DEV,
            readings("shoulder_lift", **fields),
            HOLD,
            t,
            angles_rad={"shoulder_lift": angle},
            timestamp_ms=TS0 + round(t * 1000),
        )

    # 0.03 rad per 100 ms is 0.3 rad/s: moving, however long the load stays off the model.
    assert [e for i in range(30) for e in feed(i * 0.1, i * 0.03)] == []
    assert alarms.joint_health(DEV)["shoulder_lift"].still is False
    # The pose holds (one encoder step of jitter, 0.015 rad/s, is still): raised after 1 s.
    events = [e for i in range(30, 42) for e in feed(i * 0.1, 0.9 + (i % 2) * 0.0015)]
    assert [(e.kind, e.state) for e in events] == [(AlarmKind.MODEL_MISMATCH, AlarmState.ACTIVE)]
    assert events[0].at == pytest.approx(4.1)  # still from the sample at 3.1 s (0.9 rad reached at 3.0 s)
    # A gap of over a second says nothing about speed: the velocity field (0.01 rad/s) decides again, so
    # the joint is still although the pose moved 1.1 rad since the last sample (0.19 rad/s over the gap).
    assert feed(10.0, 2.0) == []
    assert alarms.joint_health(DEV)["shoulder_lift"].still is True


TS0 = 1_764_000_000_000


# --- across restarts ----------------------------------------------------------------------------------------


def test_records_restore_acknowledged_and_latched_alarms_into_a_new_engine() -> None:
    old = ServoAlarms()
    # Over-temperature on the elbow, acknowledged; over-current on the wrist, cleared unacknowledged: LATCHED.
    run(old, [(0.0, {"temperature_c": 62.0}), (2.0, {"temperature_c": 62.0})])
    old.acknowledge(alarm_id(DEV, "elbow_flex", AlarmKind.OVER_TEMPERATURE), 3.0)
    run(old, [(4.0, {"current_a": 3.0}), (6.0, {"current_a": 3.0})], joint="wrist_flex")
    run(old, [(7.0, {"current_a": 0.1}), (9.5, {"current_a": 0.1})], joint="wrist_flex")
    records = old.records()
    assert {(r.alarm_id, r.state) for r in records} == {
        (alarm_id(DEV, "elbow_flex", AlarmKind.OVER_TEMPERATURE), AlarmState.ACKNOWLEDGED),
        (alarm_id(DEV, "wrist_flex", AlarmKind.OVER_CURRENT), AlarmState.LATCHED),
    }

    new = ServoAlarms()
    assert new.restore(records) == 2
    new.restore_counters(old.counters)
    assert state(new, AlarmKind.OVER_TEMPERATURE) is AlarmState.ACKNOWLEDGED
    assert state(new, AlarmKind.OVER_CURRENT, "wrist_flex") is AlarmState.LATCHED
    assert new.counters.acknowledged[AlarmKind.OVER_TEMPERATURE] == 1
    # The old engine saw the elbow cool (35 C, the idle reading) from 4.0 s on, but not what came between
    # its last reading and the restart: the clear timer starts again at the new engine's first cool reading.
    assert run(new, [(20.0, {"temperature_c": 40.0})]) == []
    events = run(new, [(30.0, {"temperature_c": 40.0})])
    assert events == [(30.0, "cleared", AlarmKind.OVER_TEMPERATURE, AlarmState.NORMAL)]
    # The latched alarm stays until a person acknowledges it, as before the restart.
    run(new, [(31.0, {"current_a": 0.1})], joint="wrist_flex")
    assert state(new, AlarmKind.OVER_CURRENT, "wrist_flex") is AlarmState.LATCHED
    new.acknowledge(alarm_id(DEV, "wrist_flex", AlarmKind.OVER_CURRENT), 32.0)
    assert state(new, AlarmKind.OVER_CURRENT, "wrist_flex") is AlarmState.NORMAL


def test_a_timer_pending_at_a_restart_starts_again_from_the_first_reading_after_it() -> None:
    """A worker's checkpoint holds the model check's raise timer, started by a still reading with contact
    load; the restarted worker takes up the messages since in catch-up mode, one reading of the arm, and
    never sees those in between (the joint moving, which resets the timer). The timer must start again
    from that reading, not complete on it: a walk saw model_mismatch raised on every arm of a restarted
    worker at once, and on no arm of the other."""
    contact, moving = {"load_percent": 70.0}, {"load_percent": 70.0, "velocity_rad_s": 0.8, "moving": True}
    old = ServoAlarms()
    assert run(old, [(0.0, contact)], joint="shoulder_lift", torques=HOLD) == []
    records = old.records()
    # The old engine, left running, sees the joint move: the timer restarts, nothing is raised.
    assert run(old, [(0.5, moving), (1.5, contact)], joint="shoulder_lift", torques=HOLD) == []

    new = ServoAlarms()
    new.restore(records)
    assert run(new, [(1.5, contact)], joint="shoulder_lift", torques=HOLD) == []
    # Held still for the rule's 1 s from there, it is raised, as on the engine that saw every reading.
    for engine in (old, new):
        events = run(engine, [(2.0, contact), (2.5, contact)], joint="shoulder_lift", torques=HOLD)
        assert events == [(2.5, "raised", AlarmKind.MODEL_MISMATCH, AlarmState.ACTIVE)]


def test_a_record_shows_as_the_engine_that_took_it_back_shows_the_alarm() -> None:
    """What /alarms lists of a worker being started again (record_view of its checkpoint's records) is what
    its new process lists once it has taken them back, before any message."""
    thresholds = AlarmThresholds(temperature_warning_c=58.0)
    old = ServoAlarms(thresholds)
    run(old, [(0.0, {"temperature_c": 62.0}), (2.0, {"temperature_c": 62.0})])
    old.acknowledge(alarm_id(DEV, "elbow_flex", AlarmKind.OVER_TEMPERATURE), 3.0)
    run(old, [(4.0, {"current_a": 3.0}), (6.0, {"current_a": 3.0})], joint="wrist_flex")
    run(old, [(7.0, {"current_a": 0.1}), (9.5, {"current_a": 0.1})], joint="wrist_flex")
    records = old.records()
    new = ServoAlarms(thresholds)
    new.restore(records)
    shown = sorted(
        (record_view(r, thresholds) for r in records),
        key=lambda v: worst_first(v.severity, v.state, v.alarm_id),
    )
    assert shown == new.views(include_normal=True)
    assert {(v.state, v.threshold) for v in shown} == {
        (AlarmState.ACKNOWLEDGED, 58.0),
        (AlarmState.LATCHED, thresholds.rule(AlarmKind.OVER_CURRENT, "wrist_flex").raise_at),
    }


# --- a round of messages at once ----------------------------------------------------------------------------


def _round_payload(device: str, step: int, rng: Any) -> dict[str, Any]:
    """An edge message whose servos wander across every line, in spells long enough for the timers: cool
    and hot, idle and overloaded, still and moving (the pose holds now and then), so alarms raise, hold and
    clear; a field left out or a Moving flag now and then sends a message down the one-by-one path."""
    from twin.edge.payload import make_payload

    spell = (step // 25 + sum(map(ord, device))) % 4
    held = (step // 13) % 3 == 0
    payload = make_payload(device, 0.0 if held else step * 0.1, "ticks", rng, timestamp_ms=TS0 + 100 * step)
    # The voltages from a generator of their own, so the other readings are those this stream always had.
    supply = random.Random(f"{device}/{step}")
    # The status register too (overload's bit in the hot, overloaded spell), now and then left out, a bit the
    # alarm ignores (128), a negative value or the voltage bit.
    flags = random.Random(f"status/{device}/{step}")
    for joint in payload["joints"].values():
        status = flags.choice([32 if spell == 2 else 0] * 30 + [None, 128, -1, 1])
        if status is not None:
            joint["status"] = status
        joint["temp"] = (35, 61, 67, 54)[spell] + rng.choice([0, 0, 0, -3])
        joint["current"] = (100, 210, 420, 160)[spell] + rng.choice([0, 0, 40, -40])
        joint["load"] = (10, 850, 1024 + 900, 620)[spell] + rng.choice([0, 0, 0, 30])
        if rng.random() < 0.05:
            del joint["current"]
        if rng.random() < 0.03:
            joint["moving"] = rng.random() < 0.5
        # The supply scales the model's expected load: the servo's 7.4 V, 12 V, none, and readings that are
        # no supply voltage (0 and 25 V: the stall torque as quoted).
        voltage = supply.choice([74, 74, 120, 0, 250, None])
        if voltage is None:
            joint.pop("voltage", None)
        else:
            joint["voltage"] = voltage
    return payload


def test_a_round_at_once_is_evaluate_one_by_one() -> None:
    """evaluate_batch (the mirror's path) against evaluate per message: the same events in the same order,
    the same alarms, states, values and joint health, on messages that raise, hold, clear and acknowledge."""
    import json
    import random

    from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units, diagnostic_columns

    rng = random.Random(11)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    devices = [f"arm-{i:02d}" for i in range(12)]
    one, many, together = ServoAlarms(), ServoAlarms(), ServoAlarms()

    def torques_of(pose: tuple[float, ...]) -> dict[str, float]:
        return {j: 0.6 * math.sin(a) for j, a in zip(so101.JOINT_NAMES, pose, strict=True)}

    asked: list[int] = []

    def all_at_once(sources: Sequence[Any]) -> list[Mapping[str, float]]:
        # The mirror's hook computes the batch's torques together; here it counts what it was asked for.
        asked.append(len(sources))
        return [source() for source in sources]

    def batch(engine: ServoAlarms, messages: list[Any], poses: list[Any], now: float, **hook: Any) -> Any:
        return engine.evaluate_batch(
            [m.device_id for m in messages],
            [m.diagnostics for m in messages],
            columns=diagnostic_columns(messages),
            angles=poses,
            timestamps_ms=[m.timestamp_ms for m in messages],
            now=[now] * len(messages),
            holding_torques_nm=[(lambda p=pose: torques_of(p)) for pose in poses],
            **hook,
        )

    raised: set[AlarmKind] = set()
    worst_states: set[AlarmState] = set()
    for step in range(160):
        now = step * 0.1
        messages = [decoder.decode(json.dumps(_round_payload(d, step, rng)).encode()) for d in devices]
        poses = [tuple(m.angles_rad.values()) for m in messages]
        expected = [
            one.evaluate(
                m.device_id,
                m.diagnostics,
                torques_of(pose),
                now,
                angles_rad=m.angles_rad,
                timestamp_ms=m.timestamp_ms,
            )
            for m, pose in zip(messages, poses, strict=True)
        ]
        got = batch(many, messages, poses, now)
        assert got == expected, step
        assert batch(together, messages, poses, now, torques_of=all_at_once) == expected, step
        raised |= {e.kind for events in got for e in events if e.action == "raised"}
        if step % 25 == 24:  # people acknowledge what is up, on both
            for view in one.views():
                if view.state in (AlarmState.ACTIVE, AlarmState.LATCHED):
                    assert one.acknowledge(view.alarm_id, now) == many.acknowledge(view.alarm_id, now)
                    together.acknowledge(view.alarm_id, now)
        assert many.views(include_normal=True) == one.views(include_normal=True)
        # Without NORMAL ones (picked out by the arrays): the same, less those, of the fleet and of each arm.
        every = many.views(include_normal=True)
        assert many.views() == [v for v in every if v.state is not AlarmState.NORMAL]
        for device in devices:
            assert many.views(device=device) == [
                v for v in every if v.device == device and v.state is not AlarmState.NORMAL
            ]
            a, b = one.joint_health(device), many.joint_health(device)
            assert {j: repr(h) for j, h in a.items()} == {j: repr(h) for j, h in b.items()}
            assert one.worst_by_joint(device) == many.worst_by_joint(device)
            assert {j: repr(h) for j, h in together.joint_health(device).items()} == {
                j: repr(h) for j, h in a.items()
            }
        # A report of the fleet reads every device's worst alarms in one pass.
        worst = {device: w for device in devices if (w := many.worst_by_joint(device))}
        assert many.worst_by_device() == worst
        worst_states |= {state for joints in worst.values() for _, state in joints.values()}
    assert raised == set(AlarmKind)  # every kind was raised, the model check's too
    assert worst_states >= {AlarmState.ACTIVE, AlarmState.ACKNOWLEDGED}
    # Asked once per round with still joints, for some of the round's rows only, never for none.
    assert asked and min(asked) > 0 and max(asked) <= len(devices) and min(asked) < len(devices)
    assert many.counts_by_state() == one.counts_by_state()
    assert many.present_by_severity() == one.present_by_severity()
    assert many.counters == one.counters


def test_small_rounds_row_by_row_are_the_array_rules() -> None:
    """The row-by-row path (small rounds, and `evaluate`) against the array path on one long random stream:
    rounds of 1 to 12 of the devices, each device skipped now and then (so its pose gaps exceed a second),
    acknowledgements in between. The same events in the same order, and every array of the engines' state
    the same, NaN for NaN."""
    import json
    import random

    import numpy as np
    from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units, diagnostic_columns

    rng = random.Random(23)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    devices = [f"arm-{i:02d}" for i in range(12)]
    arrays, rows = ServoAlarms(small_round=0), ServoAlarms(small_round=10**6)

    def torques_of(pose: tuple[float, ...]) -> dict[str, float | None]:
        torques: dict[str, float | None] = {
            j: 0.6 * math.sin(a) for j, a in zip(so101.JOINT_NAMES, pose, strict=True)
        }
        # Now and then a source that leaves a joint out or gives None for one: read as unknown on both paths.
        pick = int(abs(pose[0]) * 1e6) % 8
        if pick == 0:
            del torques[so101.JOINT_NAMES[1]]
        elif pick == 1:
            torques[so101.JOINT_NAMES[2]] = None
        return torques

    def same_state() -> None:
        a, b = arrays._arrays(), rows._arrays()
        for name, column in vars(a).items():
            if name != "capacity":
                assert np.array_equal(column, getattr(b, name), equal_nan=column.dtype.kind == "f"), name

    raised: set[AlarmKind] = set()
    events = 0
    for step in range(400):
        now = step * 0.1 + rng.choice([0.0, 0.0, 0.003])
        chosen = [d for d in devices if rng.random() < 0.6]
        rng.shuffle(chosen)
        chosen = chosen[: rng.randint(1, len(devices))]
        if not chosen:
            continue
        messages = [decoder.decode(json.dumps(_round_payload(d, step, rng)).encode()) for d in chosen]
        poses = [tuple(m.angles_rad.values()) for m in messages]
        args: dict[str, Any] = {
            "angles": poses,
            "timestamps_ms": [m.timestamp_ms for m in messages],
            "now": [now] * len(messages),
        }
        got = [
            engine.evaluate_batch(
                [m.device_id for m in messages],
                [m.diagnostics for m in messages],
                columns=lambda messages=messages: diagnostic_columns(messages),
                holding_torques_nm=[(lambda p=pose: torques_of(p)) for pose in poses],
                **args,
            )
            for engine in (arrays, rows)
        ]
        assert got[0] == got[1], step
        # Every round, not only at the end: a value a later round overwrites (a model load, say) counts too.
        same_state()
        events += sum(map(len, got[0]))
        raised |= {e.kind for found in got[0] for e in found if e.action == "raised"}
        if step % 40 == 39:
            for view in arrays.views():
                if view.state in (AlarmState.ACTIVE, AlarmState.LATCHED):
                    assert arrays.acknowledge(view.alarm_id, now) == rows.acknowledge(view.alarm_id, now)
    assert raised == set(AlarmKind)
    assert events > 50
    assert arrays._devices == rows._devices
    assert arrays._messages == rows._messages
    assert arrays.counters == rows.counters
    same_state()
    for device in devices:
        x, y = arrays.joint_health(device), rows.joint_health(device)
        assert {j: repr(h) for j, h in x.items()} == {j: repr(h) for j, h in y.items()}


def test_a_round_takes_the_row_path_up_to_small_round_and_makes_no_columns() -> None:
    """The mirror passes the columns as a function: a small round never calls it, a larger one once."""
    import json
    import random

    from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units, diagnostic_columns

    rng = random.Random(5)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    alarms = ServoAlarms(small_round=2)
    made = []

    def columns_of(messages: list[Any]) -> Any:
        made.append(len(messages))
        return diagnostic_columns(messages)

    for step, size in enumerate((1, 2, 3, 2, 5)):
        messages = [
            decoder.decode(json.dumps(_round_payload(f"arm-{k}", step, rng)).encode()) for k in range(size)
        ]
        alarms.evaluate_batch(
            [m.device_id for m in messages],
            [m.diagnostics for m in messages],
            columns=lambda messages=messages: columns_of(messages),
            angles=[tuple(m.angles_rad.values()) for m in messages],
            timestamps_ms=[m.timestamp_ms for m in messages],
            now=[step * 0.1] * size,
            holding_torques_nm=[{}] * size,
        )
    assert made == [3, 5]
