"""`twin edge-sim` servo faults: what each writes into the payload, decoded back, and the alarms it raises.

The last tests run a fault's whole timeline through the real decoder, MuJoCo twin (inverse dynamics) and
alarm engine, without a broker; tests/test_servo_alarms_e2e.py does the same through mosquitto and the agent.
"""

from __future__ import annotations

import json
import random
from typing import Any

import pytest
from twin.core.alarms import AlarmKind, AlarmState, AlarmThresholds, ServoAlarms
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.core.twin import DeviceTwin
from twin.edge.payload import make_payload, mock_ticks, ticks_to_degrees
from twin.edge.servo_faults import (
    CONTACT_JUMP_PERCENT,
    HEAT_PEAK_C,
    ModelLoads,
    ServoFault,
    current_register,
    load_register,
    overrides_at,
    parse_fault,
)
from twin.robot import so101
from twin.robot.model import RobotModel

TS0 = 1_764_000_000_000


def test_parse_fault() -> None:
    assert parse_fault("heat:elbow_flex") == ServoFault("heat", "elbow_flex", 5.0, 20.0)
    assert parse_fault("contact:wrist_flex:2.5:8") == ServoFault("contact", "wrist_flex", 2.5, 8.0)
    for text, match in [
        ("heat", "KIND:JOINT"),
        ("melt:elbow_flex", "not one of heat, overload, contact"),
        ("heat:elbow", "joint 'elbow'"),
        ("heat:elbow_flex:soon", "numbers of seconds"),
        ("heat:elbow_flex:1:0", "duration"),
    ]:
        with pytest.raises(ValueError, match=match):
            parse_fault(text)


def test_registers() -> None:
    assert load_register(90.0) == 900
    assert load_register(-31.3) == 1024 + 313  # direction in bit 10
    assert load_register(150.0) == 1000  # the register's full scale
    assert current_register(2.925) == 450  # 2925 mA / 6.5 mA


@pytest.mark.parametrize(
    ("t", "expected_c"),
    [(5.0, 35.0), (7.5, 51.5), (10.0, 68.0), (15.0, 68.0), (22.5, 51.5), (24.9, 35.66)],
)
def test_heat_ramps_to_the_peak_and_back(t: float, expected_c: float) -> None:
    # 20 s from 5 s: up over 5 s (35 + 33 x (t - 5) / 5), 10 s at 68 C, down over the last 5 s.
    override = overrides_at((ServoFault("heat", "elbow_flex", 5.0, 20.0),), t)["elbow_flex"]
    assert override.temperature_c == pytest.approx(expected_c)
    assert override.hold_at_s is None
    assert overrides_at((ServoFault("heat", "elbow_flex", 5.0, 20.0),), 25.0) == {}


def test_overload_in_ticks_decodes_to_the_fault_figures() -> None:
    fault = ServoFault("overload", "shoulder_lift", 5.0, 10.0)
    msg = make_payload("arm-001", 7.0, "ticks", random.Random(1), timestamp_ms=TS0, servo_faults=(fault,))
    joint = msg["joints"]["shoulder_lift"]
    assert joint["position"] == mock_ticks(5.0)[1]  # stalled where it was when the fault began
    assert (joint["velocity"], joint["load"], joint["current"]) == (0, 900, 450)
    diag = TelemetryDecoder(DecoderConfig(units=Units.TICKS)).decode(json.dumps(msg)).diagnostics
    assert (diag["shoulder_lift"].load_percent, diag["shoulder_lift"].current_a) == (90.0, 2.925)
    assert diag["shoulder_lift"].velocity_rad_s == 0.0
    assert diag["elbow_flex"].load_percent is not None and diag["elbow_flex"].load_percent <= 5.0


def test_contact_in_degrees_holds_the_pose_and_releases() -> None:
    fault = ServoFault("contact", "wrist_flex", 2.0, 10.0)
    rng = random.Random(2)
    held = [make_payload("a", t, "degrees", rng, servo_faults=(fault,))["joints"] for t in (2.0, 4.0, 7.9)]
    positions = {j["wrist_flex"]["position"] for j in held}
    assert positions == {round(ticks_to_degrees(mock_ticks(2.0)[3]), 4)}
    # The mock's load (5..50 raw, 0.5..5 %) plus 45 points: 455..500 raw.
    assert all(455.0 <= j["wrist_flex"]["load"] <= 500.0 for j in held)
    assert len({j["elbow_flex"]["position"] for j in held}) == 3  # the other joints keep moving
    # Released after 60 % of the duration (8 s): still held, load back to the mock's.
    released = make_payload("a", 8.0, "degrees", rng, servo_faults=(fault,))["joints"]["wrist_flex"]
    assert released["position"] in positions and released["load"] <= 50.0 and released["velocity"] == 0.0
    after = make_payload("a", 12.0, "degrees", rng, servo_faults=(fault,))["joints"]["wrist_flex"]
    assert after["position"] not in positions


def test_model_loads_agree_with_the_agents_holding_torque(robot: RobotModel) -> None:
    loads = ModelLoads()
    msg = make_payload("arm-001", 3.0, "ticks", random.Random(3), timestamp_ms=TS0, model_loads=loads)
    telemetry = TelemetryDecoder(DecoderConfig(units=Units.TICKS)).decode(json.dumps(msg))
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(telemetry.angles_rad, TS0)
    alarms = ServoAlarms()
    alarms.evaluate("arm-001", telemetry.diagnostics, twin.joint_torques, 0.0)
    for joint, health in alarms.joint_health("arm-001").items():
        measured = abs(telemetry.diagnostics[joint].load_percent or 0.0)
        # Equal to the register's 0.1 % resolution; the supply (5 V) travels in the message.
        assert measured == pytest.approx(health.model_load_percent, abs=0.051), joint
        assert telemetry.diagnostics[joint].voltage_v == 5.0
    # A contact on top adds 45 points away from zero.
    fault = ServoFault("contact", "elbow_flex", 3.0, 10.0)  # held where it is at 3 s
    base = make_payload("a", 3.0, "ticks", random.Random(3), model_loads=loads)["joints"]["elbow_flex"][
        "load"
    ]
    jumped = make_payload("a", 3.0, "ticks", random.Random(3), model_loads=loads, servo_faults=(fault,))
    assert abs(load_percent(jumped["joints"]["elbow_flex"]["load"])) == pytest.approx(
        abs(load_percent(base)) + CONTACT_JUMP_PERCENT, abs=0.051
    )


def load_percent(raw: int) -> float:
    return -(raw - 1024) / 10 if raw >= 1024 else raw / 10


# --- each fault's timeline through decoder, twin and alarm engine -------------------------------------------


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


def timeline(robot: RobotModel, variant: str, fault: ServoFault, seconds: float) -> ServoAlarms:
    """Run the simulated edge at 10 Hz (model-consistent loads) through the real data path; returns the
    alarm engine at the end, with the fault joint's events in `seen`."""
    units = Units.TICKS if variant == "ticks" else Units.DEGREES
    decoder = TelemetryDecoder(DecoderConfig(units=units))
    twin = DeviceTwin(robot, "arm-001")
    alarms = ServoAlarms(AlarmThresholds(temperature_clear_after_s=3.0))
    rng = random.Random(7)
    loads = ModelLoads()
    seen: list[tuple[AlarmKind, AlarmState]] = []
    for k in range(round(seconds * 10)):
        t = k / 10
        ts = TS0 + k * 100
        telemetry = decoder.decode(
            json.dumps(
                make_payload(
                    "arm-001", t, variant, rng, timestamp_ms=ts, servo_faults=(fault,), model_loads=loads
                )
            )
        )
        assert twin.apply(telemetry.angles_rad, ts)
        events = alarms.evaluate(
            "arm-001",
            telemetry.diagnostics,
            twin.joint_torques,
            t,
            angles_rad=twin.joint_angles,
            timestamp_ms=ts,
        )
        seen.extend((e.kind, e.state) for e in events if e.joint == fault.joint)
        assert all(e.joint == fault.joint for e in events), events
    alarms.seen = seen  # type: ignore[attr-defined]
    return alarms


@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_heat_raises_and_clears_both_temperature_alarms(robot: RobotModel, variant: str) -> None:
    alarms = timeline(robot, variant, ServoFault("heat", "elbow_flex", 1.0, 12.0), 20.0)
    assert alarms.seen == [  # type: ignore[attr-defined]
        (AlarmKind.OVER_TEMPERATURE, AlarmState.ACTIVE),
        (AlarmKind.OVER_TEMPERATURE_CRITICAL, AlarmState.ACTIVE),
        (AlarmKind.OVER_TEMPERATURE_CRITICAL, AlarmState.LATCHED),
        (AlarmKind.OVER_TEMPERATURE, AlarmState.LATCHED),
    ]
    assert HEAT_PEAK_C < 70.0


@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_overload_raises_overload_current_mismatch_and_the_servo_error(
    robot: RobotModel, variant: str
) -> None:
    alarms = timeline(robot, variant, ServoFault("overload", "shoulder_lift", 1.0, 8.0), 12.0)
    raised = {k for k, s in alarms.seen if s is AlarmState.ACTIVE}  # type: ignore[attr-defined]
    cleared = {k for k, s in alarms.seen if s is AlarmState.LATCHED}  # type: ignore[attr-defined]
    assert (
        raised
        == cleared
        == {AlarmKind.OVERLOAD, AlarmKind.OVER_CURRENT, AlarmKind.MODEL_MISMATCH, AlarmKind.SERVO_ERROR}
    )


def test_an_overloaded_servo_reports_its_overload_bit_after_its_protection_time() -> None:
    """The overload fault's status: 0 until the servo's 2 s protection time has passed, the overload bit until
    the release, 0 after; on every joint of the arm, and on no arm without an overload fault."""
    fault = ServoFault("overload", "shoulder_lift", 1.0, 8.0)  # released at 1 + 0.6 x 8 = 5.8 s

    def statuses(t: float, faults: tuple[ServoFault, ...] = (fault,)) -> dict[str, Any]:
        joints = make_payload("arm-001", t, "ticks", random.Random(3), servo_faults=faults)["joints"]
        return {name: fields.get("status") for name, fields in joints.items()}

    assert statuses(2.9) == dict.fromkeys(so101.JOINT_NAMES, 0)
    assert statuses(3.0) == {**dict.fromkeys(so101.JOINT_NAMES, 0), "shoulder_lift": 32}
    assert statuses(5.7)["shoulder_lift"] == 32 and statuses(5.8)["shoulder_lift"] == 0
    heat = ServoFault("heat", "elbow_flex", 1.0, 8.0)
    assert statuses(3.0, (heat,)) == dict.fromkeys(so101.JOINT_NAMES)


@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_contact_raises_only_the_model_mismatch(robot: RobotModel, variant: str) -> None:
    alarms = timeline(robot, variant, ServoFault("contact", "elbow_flex", 1.0, 6.0), 10.0)
    assert alarms.seen == [  # type: ignore[attr-defined]
        (AlarmKind.MODEL_MISMATCH, AlarmState.ACTIVE),
        (AlarmKind.MODEL_MISMATCH, AlarmState.LATCHED),
    ]


def unfaulted_alarms(robot: RobotModel, variant: str, seconds: float, loads: ModelLoads | None) -> list[Any]:
    """The alarm events of one simulated arm with no fault, `seconds` at 10 Hz (seed 3)."""
    units = Units.TICKS if variant == "ticks" else Units.DEGREES
    decoder = TelemetryDecoder(DecoderConfig(units=units))
    twin = DeviceTwin(robot, "arm-001")
    alarms = ServoAlarms(AlarmThresholds())
    rng = random.Random(3)
    events: list[Any] = []
    for k in range(round(seconds * 10)):
        t, ts = k / 10, TS0 + k * 100
        message = make_payload("arm-001", t, variant, rng, timestamp_ms=ts, model_loads=loads)
        telemetry = decoder.decode(json.dumps(message))
        assert twin.apply(telemetry.angles_rad, ts)
        events += alarms.evaluate(
            "arm-001",
            telemetry.diagnostics,
            twin.joint_torques,
            t,
            angles_rad=twin.joint_angles,
            timestamp_ms=ts,
        )
    return events


def test_model_loads_without_a_fault_raise_no_alarm(robot: RobotModel) -> None:
    # The mock's random currents (0.52-1.95 A) cross the gripper's 1.3 A over-current line now and then, and
    # once raised it never clears: this seed's arm raises it after 324 s. With model loads each servo draws
    # the current its holding load does, so the same arm raises nothing.
    mock = unfaulted_alarms(robot, "ticks", 400.0, None)
    assert [(e.joint, e.kind, e.action) for e in mock] == [("gripper", AlarmKind.OVER_CURRENT, "raised")]
    loads = ModelLoads()
    for variant in ("ticks", "degrees"):
        assert unfaulted_alarms(robot, variant, 400.0, loads) == [], variant
