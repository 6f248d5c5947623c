"""Telemetry decoding, table-driven with the documented payloads (telemetry contract, docs/telemetry.md).

Expected angles are worked out by hand from the formulas and written as literals, so a wrong formula in the
decoder cannot agree with itself. K below is 2*pi/4095 = 0.00153435538636864 rad per tick (LeRobot DEGREES).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from twin.core.telemetry import (
    DecoderConfig,
    JointDiagnostics,
    JointReading,
    RejectReason,
    Telemetry,
    TelemetryDecoder,
    TelemetryRejected,
    Units,
    decode_load,
    decode_velocity,
    diagnostic_columns,
)
from twin.robot import so101
from twin.robot.calibration import Calibration, MotorCalibration, load_calibration

EXAMPLE_CALIBRATION = (
    Path(__file__).resolve().parents[1] / "robots" / "so101" / "calibration" / "so101_follower_example.json"
)
NAMES = so101.JOINT_NAMES
TS = 1706000000000
JAW_LO, JAW_HI = -0.174533, 1.7453292  # the model's gripper range (so101.JOINT_RANGES_RAD)

TICKS_EXAMPLE = (2048, 1800, 2200, 2100, 2048, 1500)  # contract, variant A
DEGREES_EXAMPLE = (2.01, -98.89, 97.27, 63.70, -3.44, 4.83)  # contract, variant B
ZERO_DEGREES = (0, 0, 0, 0, 0, 0)  # the arm at zero in degrees: whole, non-negative, JSON integers


def message(positions: tuple[Any, ...], *, device: Any = "arm-001", ts: Any = TS, **per_joint: Any) -> dict:
    return {
        "device_id": device,
        "timestamp": ts,
        "joints": {n: {"position": p, **per_joint} for n, p in zip(NAMES, positions, strict=True)},
    }


def payload(positions: tuple[Any, ...], **kw: Any) -> bytes:
    return json.dumps(message(positions, **kw)).encode()


def decoder(units: Units = Units.AUTO, **kw: Any) -> TelemetryDecoder:
    return TelemetryDecoder(DecoderConfig(units=units, **kw))


def assert_angles(t: Telemetry, expected: dict[str, float]) -> None:
    assert list(t.angles_rad) == list(NAMES)
    for name in NAMES:
        assert t.angles_rad[name] == pytest.approx(expected[name], abs=1e-9), name


# --- variant A: ticks ---------------------------------------------------------------------------------------

TICKS_NO_CALIBRATION = {
    "shoulder_pan": 0.0015343553863686413,  # (2048 - 2047) * K
    "shoulder_lift": -0.3789857804330544,  # (1800 - 2047) * K = -247 K
    "elbow_flex": 0.23475637411440212,  # (2200 - 2047) * K = 153 K
    "wrist_flex": 0.08132083547753799,  # (2100 - 2047) * K = 53 K
    "wrist_roll": 0.0015343553863686413,  # (2048 - 2047) * K
    # default jaw range 2047 -/+ 625.625 ticks (half of 1.9198622 rad / K): p = (1500 - 1421.375) / 1251.25
    # * 100 = 6.2837168 %, angle = -0.174533 + 0.062837168 * 1.9198622 (= pi/4 + (1500 - 2047) * K)
    "gripper": -0.05389429634364694,
}
TICKS_EXAMPLE_CALIBRATION = {
    "shoulder_pan": 0.018412264636423696,  # mid (762 + 3310) / 2 = 2036: (2048 - 2036) * K = 12 K
    "shoulder_lift": -0.34676431731931295,  # mid 2026: -226 K
    "elbow_flex": 0.32835205268288925,  # mid 1986: 214 K
    "wrist_flex": 0.1296530301481502,  # mid 2015.5: 84.5 K
    "wrist_roll": -0.02071379771597666,  # mid 2061.5: -13.5 K
    "gripper": JAW_LO,  # 1500 is below range_min 2024: clamped, p = 0 %, the closed (lower) jaw limit
}


@pytest.mark.parametrize(
    ("calibration", "expected", "percent"),
    [
        (None, TICKS_NO_CALIBRATION, 6.283716803026438),
        (EXAMPLE_CALIBRATION, TICKS_EXAMPLE_CALIBRATION, 0.0),
    ],
    ids=["defaults", "example-calibration"],
)
def test_ticks_example(calibration: Path | None, expected: dict[str, float], percent: float) -> None:
    cal = load_calibration(calibration) if calibration else None
    t = decoder(Units.TICKS, calibration=cal).decode(payload(TICKS_EXAMPLE))
    assert (t.device_id, t.timestamp_ms, t.units) == ("arm-001", TS, Units.TICKS)
    assert_angles(t, expected)
    assert t.gripper_percent == pytest.approx(percent, abs=1e-9)


def test_each_arm_decodes_with_its_own_calibration() -> None:
    """Two arms in one decoder: arm-001 with the example calibration, arm-002 with none (the nominal SO-101),
    from one identical payload; replacing the set moves arm-002 onto it and arm-001 back to the default."""
    cal = load_calibration(EXAMPLE_CALIBRATION)
    d = decoder(Units.TICKS)
    d.set_calibrations({"arm-001": cal})
    assert_angles(d.decode(payload(TICKS_EXAMPLE, device="arm-001")), TICKS_EXAMPLE_CALIBRATION)
    assert_angles(d.decode(payload(TICKS_EXAMPLE, device="arm-002")), TICKS_NO_CALIBRATION)
    assert d.calibration_for("arm-001") is cal and d.calibration_for("arm-002") is None
    d.set_calibrations({"arm-002": cal})
    assert_angles(d.decode(payload(TICKS_EXAMPLE, device="arm-001")), TICKS_NO_CALIBRATION)
    assert_angles(d.decode(payload(TICKS_EXAMPLE, device="arm-002")), TICKS_EXAMPLE_CALIBRATION)


def test_an_arm_without_its_own_uses_the_configs_calibration_on_both_paths() -> None:
    """The config's file stays the default for the arms without their own; units decided by auto take the
    arm's own table too."""
    cal = load_calibration(EXAMPLE_CALIBRATION)
    d = decoder(Units.TICKS, calibration=cal)
    d.set_calibrations({"arm-002": Calibration.from_dict(_shifted(cal.to_dict(), 100))})
    assert_angles(d.decode(payload(TICKS_EXAMPLE, device="arm-001")), TICKS_EXAMPLE_CALIBRATION)
    shifted = d.decode(payload(TICKS_EXAMPLE, device="arm-002"))
    rad_per_tick = 2 * math.pi / 4095
    assert shifted.angles_rad["shoulder_pan"] == pytest.approx(
        TICKS_EXAMPLE_CALIBRATION["shoulder_pan"] - 100 * rad_per_tick
    )
    auto = decoder(Units.AUTO, auto_evidence_messages=1)
    auto.set_calibrations({"arm-001": cal})
    assert_angles(auto.decode(payload(TICKS_EXAMPLE, device="arm-001")), TICKS_EXAMPLE_CALIBRATION)


def test_an_arms_own_calibration_gives_the_same_values_as_the_same_file_in_the_config() -> None:
    """The config's calibration converts ticks through tables made once, an arm's own by arithmetic (a table
    per arm would cost memory at fleet size): the two must agree exactly, on every tick of every joint, with
    the gripper's clamp at both ends and an inverted gripper."""
    data = _shifted(load_calibration(EXAMPLE_CALIBRATION).to_dict(), 0)
    data["gripper"] = {**data["gripper"], "drive_mode": 1}
    for cal in (load_calibration(EXAMPLE_CALIBRATION), Calibration.from_dict(data)):
        tables = decoder(Units.TICKS, calibration=cal)
        arithmetic = decoder(Units.TICKS)
        arithmetic.set_calibrations({"arm-001": cal})
        for tick in range(so101.TICK_MAX + 1):
            positions = tuple((tick + 683 * i) % (so101.TICK_MAX + 1) for i in range(len(NAMES)))
            a = tables.decode(payload(positions))
            b = arithmetic.decode(payload(positions))
            assert (a.angles_rad, a.gripper_percent) == (b.angles_rad, b.gripper_percent), positions


def _shifted(data: dict[str, dict[str, int]], ticks: int) -> dict[str, dict[str, int]]:
    """A calibration whose every range sits `ticks` higher (its middle moves by as much)."""
    return {
        name: {**m, "range_min": m["range_min"] + ticks, "range_max": m["range_max"] + ticks}
        for name, m in data.items()
    }


def test_ticks_gripper_inside_calibrated_range() -> None:
    t = decoder(Units.TICKS, calibration=load_calibration(EXAMPLE_CALIBRATION)).decode(
        payload((2048, 1800, 2200, 2100, 2048, 2500))
    )
    # p = (2500 - 2024) / (3432 - 2024) * 100 = 476 / 1408 * 100 = 33.806818 %
    assert t.gripper_percent == pytest.approx(33.80681818181818)
    # -0.174533 + 0.33806818 * 1.9198622
    assert t.angles_rad["gripper"] == pytest.approx(0.4745113232954546)


def test_drive_mode_inverts_the_gripper_percentage() -> None:
    data = json.loads(EXAMPLE_CALIBRATION.read_text())
    data["gripper"]["drive_mode"] = 1
    cal = Calibration.from_dict(data)
    t = decoder(Units.TICKS, calibration=cal).decode(payload((2048, 1800, 2200, 2100, 2048, 2500)))
    assert t.gripper_percent == pytest.approx(100 - 33.80681818181818)  # RANGE_0_100 with drive_mode 1


def test_ticks_extremes_stay_physical() -> None:
    t = decoder(Units.TICKS).decode(payload((0, 4095, 0, 4095, 0, 4095)))
    assert t.angles_rad["shoulder_pan"] == pytest.approx(-3.1408254758966088)  # -2047 K
    assert t.angles_rad["shoulder_lift"] == pytest.approx(3.1423598312829775)  # 2048 K
    assert t.angles_rad["gripper"] == pytest.approx(JAW_HI)  # clamped to the jaw's range_max: 100 %
    assert t.gripper_percent == 100.0


# --- variant B: LeRobot degrees / range100 ------------------------------------------------------------------

DEGREES_EXPECTED = {
    "shoulder_pan": 0.03508111796508602,  # 2.01 * pi / 180
    "shoulder_lift": -1.7259560972971923,  # -98.89 * pi / 180
    "elbow_flex": 1.6976817634148842,  # 97.27 * pi / 180
    "wrist_flex": 1.111774733520388,  # 63.70 * pi / 180
    "wrist_roll": -0.060039326268604934,  # -3.44 * pi / 180
    "gripper": -0.08180365573999998,  # 4.83 % of the jaw: -0.174533 + 0.0483 * 1.9198622
}


@pytest.mark.parametrize("calibration", [None, EXAMPLE_CALIBRATION], ids=["defaults", "example-calibration"])
def test_degrees_example(calibration: Path | None) -> None:
    # Degrees are already relative to the calibrated middle, so a calibration file changes nothing here.
    cal = load_calibration(calibration) if calibration else None
    t = decoder(Units.DEGREES, calibration=cal).decode(payload(DEGREES_EXAMPLE))
    assert t.units is Units.DEGREES
    assert_angles(t, DEGREES_EXPECTED)
    assert t.gripper_percent == pytest.approx(4.83)


def test_range100_without_calibration_uses_the_model_range() -> None:
    t = decoder(Units.RANGE100).decode(payload((-100, 100, 0, 50.0, -50.0, 100)))
    assert_angles(
        t,
        {
            "shoulder_pan": -1.91986,  # lo + 0/200 * (hi - lo)
            "shoulder_lift": 1.7453293,  # hi
            "elbow_flex": 0.0,  # middle of (-1.69, 1.69)
            "wrist_flex": 0.8290315,  # 0 + 150/200 * 3.316126 - 1.658063
            "wrist_roll": -1.3475839,  # -2.7438473 + 50/200 * 5.5850536
            "gripper": JAW_HI,  # 100 %
        },
    )


def test_range100_with_calibration_inverts_lerobot() -> None:
    cal = load_calibration(EXAMPLE_CALIBRATION)
    t = decoder(Units.RANGE100, calibration=cal).decode(payload((10.0, -100, 0, 100, 0, 0)))
    # raw - mid = v / 200 * (range_max - range_min), then * K
    assert t.angles_rad["shoulder_pan"] == pytest.approx(0.1954768762233649)  # 10/200 * 2548 = 127.4 K
    assert t.angles_rad["shoulder_lift"] == pytest.approx(-1.8320203313241579)  # -2388/2 = -1194 K
    assert t.angles_rad["elbow_flex"] == 0.0
    assert t.angles_rad["wrist_flex"] == pytest.approx(1.7959629797444947)  # 2341/2 = 1170.5 K


def test_zero_degrees_payload_is_zero_under_explicit_degrees() -> None:
    t = decoder(Units.DEGREES).decode(payload(ZERO_DEGREES))
    assert all(t.angles_rad[n] == 0.0 for n in so101.ARM_JOINTS)
    assert t.gripper_percent == 0.0
    assert t.angles_rad["gripper"] == pytest.approx(JAW_LO)  # 0 % = closed = the jaw's lower limit


# --- auto units ---------------------------------------------------------------------------------------------


def test_auto_decides_ticks_from_the_ticks_example(caplog: pytest.LogCaptureFixture) -> None:
    d = decoder()
    for i in range(2):
        with pytest.raises(TelemetryRejected) as info:
            d.decode(payload(TICKS_EXAMPLE))
        assert info.value.reason is RejectReason.UNITS_UNDECIDED
        assert f"{i + 1} of 3" in str(info.value)
        assert d.units_for("arm-001") is Units.AUTO
    with caplog.at_level(logging.INFO, logger="twin.core.telemetry"):
        t = d.decode(payload(TICKS_EXAMPLE))
    assert t.units is Units.TICKS
    assert_angles(t, TICKS_NO_CALIBRATION)
    assert d.units_for("arm-001") is Units.TICKS
    assert any("decided ticks" in r.getMessage() for r in caplog.records)


def test_auto_zero_degrees_is_undecided_never_ticks() -> None:
    d = decoder()
    for _ in range(10):
        with pytest.raises(TelemetryRejected) as info:
            d.decode(payload(ZERO_DEGREES))
        assert info.value.reason is RejectReason.UNITS_UNDECIDED
    assert d.units_for("arm-001") is Units.AUTO


# Positions no units allow for their joint, with the ranges and the hint the rejection names. Ticks are JSON
# integers 0..4095 on every joint; a JSON float fits degrees up to 360 on an arm joint, but the gripper is a
# 0..100 percent in both normalised settings. A whole float that could be a tick count keeps the ticks hint.
NO_UNITS = [
    ("gripper", 5000, "0..100 percent", "no units produce this value: check the edge's position source"),
    ("gripper", 10**400, "0..100 percent", "no units produce this value"),
    ("gripper", 150.0, "0..100 percent", "if it is a tick count, ticks arrive as JSON integers"),
    ("gripper", 1500.0, "0..100 percent", "if it is a tick count, ticks arrive as JSON integers"),
    ("gripper", 4096.0, "0..100 percent", "no units produce this value"),
    ("shoulder_pan", 4096, "degrees: -360..360", "no units produce this value"),
    ("elbow_flex", 361.0, "degrees: -360..360", "if it is a tick count, ticks arrive as JSON integers"),
]
NO_UNITS_IDS = [f"{joint}={position!r:.12}" for joint, position, *_ in NO_UNITS]


def with_joint(joint: str, position: int | float) -> tuple[int | float, ...]:
    """TICKS_EXAMPLE with one joint's position replaced."""
    return tuple(position if name == joint else p for name, p in zip(NAMES, TICKS_EXAMPLE, strict=True))


@pytest.mark.parametrize(("joint", "position", "ranges", "hint"), NO_UNITS, ids=NO_UNITS_IDS)
def test_auto_rejects_a_position_no_units_allow_as_out_of_range(
    joint: str, position: int | float, ranges: str, hint: str
) -> None:
    """Past every setting's range for its joint: no later message can make it fit, so waiting for evidence,
    the units_undecided answer, would be wrong advice; it is counted as out_of_range."""
    d = decoder()
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(with_joint(joint, position)))
    assert info.value.reason is RejectReason.OUT_OF_RANGE
    assert f"of {joint} fits no units (ticks: JSON integers 0..4095, " in str(info.value)
    assert ranges in str(info.value)
    assert hint in str(info.value)
    assert d.units_for("arm-001") is Units.AUTO


@pytest.mark.parametrize(("joint", "position", "ranges", "hint"), NO_UNITS, ids=NO_UNITS_IDS)
def test_a_position_no_units_allow_reads_the_same_on_both_paths(
    joint: str, position: int | float, ranges: str, hint: str
) -> None:
    """The msgspec hot path, the rule-by-rule path forced, and that path as a schema refusal reaches it (a
    bad velocity, which the rules check only after the units) give one reason and one message."""
    plain = payload(with_joint(joint, position))
    spoiled = payload(with_joint(joint, position), velocity="fast")
    answers = []
    for run in (
        lambda d: d.decode(plain),
        lambda d: d._explain(d._envelope(plain), None),
        lambda d: d.decode(spoiled),
    ):
        with pytest.raises(TelemetryRejected) as info:
            run(decoder())
        answers.append((info.value.reason, str(info.value)))
    assert answers[0][0] is RejectReason.OUT_OF_RANGE
    assert answers == [answers[0]] * 3


@pytest.mark.parametrize(("joint", "position"), [("gripper", 100.0), ("shoulder_pan", 360.0)])
def test_auto_still_waits_on_a_whole_float_some_units_allow(joint: str, position: float) -> None:
    """The last whole float each joint's degrees allow: ambiguous, so still units_undecided."""
    with pytest.raises(TelemetryRejected) as info:
        decoder().decode(payload(with_joint(joint, position)))
    assert info.value.reason is RejectReason.UNITS_UNDECIDED


def test_auto_decides_degrees_then_zero_payload_is_zero(caplog: pytest.LogCaptureFixture) -> None:
    d = decoder()
    with caplog.at_level(logging.INFO, logger="twin.core.telemetry"):
        for _ in range(2):
            with pytest.raises(TelemetryRejected):
                d.decode(payload(DEGREES_EXAMPLE))
        assert d.decode(payload(DEGREES_EXAMPLE)).units is Units.DEGREES
    decision = [r for r in caplog.records if "decided degrees" in r.getMessage()]
    assert decision and decision[0].levelno == logging.WARNING
    assert "units=range100" in decision[0].getMessage()  # the range100 ambiguity is spelled out
    t = d.decode(payload(ZERO_DEGREES))
    assert t.units is Units.DEGREES
    assert all(t.angles_rad[n] == 0.0 for n in so101.ARM_JOINTS)
    assert t.gripper_percent == 0.0


def test_auto_never_flips_after_deciding() -> None:
    d = decoder(auto_evidence_messages=1)
    assert d.decode(payload(DEGREES_EXAMPLE)).units is Units.DEGREES
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(TICKS_EXAMPLE))
    assert info.value.reason is RejectReason.OUT_OF_RANGE
    assert "set units=ticks" in str(info.value) and "never changes" in str(info.value)
    assert d.units_for("arm-001") is Units.DEGREES


def test_auto_is_per_device_and_needs_consecutive_agreement() -> None:
    d = decoder()
    with pytest.raises(TelemetryRejected):
        d.decode(payload(TICKS_EXAMPLE))
    with pytest.raises(TelemetryRejected):
        d.decode(payload(TICKS_EXAMPLE))
    # Disagreeing evidence restarts the streak: degrees now needs three in a row of its own.
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(DEGREES_EXAMPLE))
    assert "1 of 3" in str(info.value)
    # Ambiguous messages neither count nor break the streak.
    with pytest.raises(TelemetryRejected):
        d.decode(payload(ZERO_DEGREES))
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(DEGREES_EXAMPLE))
    assert "2 of 3" in str(info.value)
    assert d.decode(payload(DEGREES_EXAMPLE)).units is Units.DEGREES
    # Another device decides on its own evidence.
    assert d.units_for("arm-002") is Units.AUTO
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(TICKS_EXAMPLE, device="arm-002"))
    assert info.value.reason is RejectReason.UNITS_UNDECIDED


def test_auto_invalid_messages_are_not_evidence() -> None:
    d = decoder(auto_evidence_messages=2)
    bad = message(TICKS_EXAMPLE)
    bad["joints"]["gripper"]["temp"] = "hot"
    for _ in range(3):
        with pytest.raises(TelemetryRejected) as info:
            d.decode(json.dumps(bad))
        assert info.value.reason is RejectReason.WRONG_TYPE
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(TICKS_EXAMPLE))
    assert "1 of 2" in str(info.value)


@pytest.mark.parametrize(
    ("units", "positions", "reason", "hint"),
    [
        (Units.DEGREES, TICKS_EXAMPLE, RejectReason.OUT_OF_RANGE, "set units=ticks"),
        (Units.RANGE100, TICKS_EXAMPLE, RejectReason.OUT_OF_RANGE, "set units=ticks"),
        (Units.TICKS, DEGREES_EXAMPLE, RejectReason.WRONG_TYPE, "set units=degrees"),
    ],
)
def test_explicit_setting_wins(units: Units, positions: tuple, reason: RejectReason, hint: str) -> None:
    d = decoder(units)
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(positions))
    assert info.value.reason is reason
    assert hint in str(info.value)
    assert d.units_for("arm-001") is units


def test_explicit_ticks_decodes_the_ambiguous_zero_payload_as_ticks() -> None:
    t = decoder(Units.TICKS).decode(payload(ZERO_DEGREES))
    assert t.angles_rad["shoulder_pan"] == pytest.approx(-3.1408254758966088)  # -2047 K: the setting wins


def test_wrong_type_message_names_the_fix() -> None:
    with pytest.raises(TelemetryRejected) as info:
        decoder(Units.TICKS).decode(payload(DEGREES_EXAMPLE))
    assert str(info.value) == (
        "position 2.01 of shoulder_pan is not a whole tick count; the edge looks like it sends LeRobot "
        "degrees: set units=degrees"
    )


@pytest.mark.parametrize("keep_six", [False, True], ids=["missing_joint", "extra_joint"])
def test_unknown_joint_names_do_not_grow_the_message(keep_six: bool) -> None:
    """A payload under the size limit may carry a thousand joint names: its rejection, which goes into an
    event, a log line and /state, names a few and counts the rest (a walk: one was 42 KB)."""
    msg = message(TICKS_EXAMPLE)
    if not keep_six:
        msg["joints"] = {}
    msg["joints"].update({f"joint_{'x' * 60}_{i}": {"position": 1} for i in range(1000)})
    with pytest.raises(TelemetryRejected) as info:
        decoder(Units.TICKS).decode(json.dumps(msg).encode())
    text = str(info.value)
    assert len(text) < 1000, text
    assert "and 992 more" in text


# --- diagnostics --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("raw", "expected"),
    [(0, 0), (10, 10), (32768, 0), (32778, -10), (32768 + 3400, -3400), (-7, -7), (65535, -32767)],
)
def test_decode_velocity(raw: int, expected: int) -> None:
    assert decode_velocity(raw) == expected


@pytest.mark.parametrize(
    ("raw", "expected"),
    [(0, 0), (500, 500), (1000, 1000), (1024, 0), (1524, -500), (2024, -1000), (-30, -30), (1100.0, -76.0)],
)
def test_decode_load(raw: float, expected: float) -> None:
    assert decode_load(raw) == expected


def test_ticks_diagnostics_are_sign_decoded_and_scaled() -> None:
    d = decoder(Units.TICKS)
    t = d.decode(
        payload(
            TICKS_EXAMPLE, velocity=32778, load=1524, temp=41, current=100, voltage=121, status=0, moving=1
        )
    )
    assert t.diagnostics["elbow_flex"] == JointDiagnostics(
        velocity_steps_s=-10.0,
        velocity_rad_s=pytest.approx(-0.015339807878856412),  # -10 * 2 pi / 4096
        load_percent=-50.0,  # 1524 -> -500 units of 0.1 %
        temperature_c=41.0,
        current_a=0.65,  # 100 * 6.5 mA
        voltage_v=pytest.approx(12.1),  # 121 * 0.1 V
        status=0,
        moving=True,
    )


def test_tenth_unit_registers_read_as_the_decimal_they_stand_for() -> None:
    # 12 units of 0.1 % are 1.2 %, not 12 * 0.1 = 1.2000000000000002; the same for 0.1 V. The alarm engine's
    # columns agree with the per-message diagnostics.
    t = decoder(Units.TICKS).decode(
        payload(TICKS_EXAMPLE, velocity=0, load=1036, temp=41, current=100, voltage=121)
    )
    assert (t.diagnostics["elbow_flex"].load_percent, t.diagnostics["elbow_flex"].voltage_v) == (-1.2, 12.1)
    assert str(t.diagnostics["elbow_flex"].load_percent) == "-1.2"
    columns = diagnostic_columns([t])
    joint = list(so101.JOINT_NAMES).index("elbow_flex")
    assert columns.load_percent[0, joint] == -1.2 and columns.voltage_v([0])[0, joint] == 12.1


def test_float_variant_diagnostics_keep_the_signed_velocity() -> None:
    t = decoder(Units.DEGREES).decode(payload(DEGREES_EXAMPLE, velocity=-12.0, load=1100.0, temp=36.5))
    diag = t.diagnostics["gripper"]
    assert diag.velocity_steps_s == -12.0
    assert diag.velocity_rad_s == pytest.approx(-0.01840776945)  # -12 * 2 pi / 4096
    assert diag.load_percent == pytest.approx(-7.6)  # >= 1024 is negative here too: -(1100 - 1024) * 0.1
    assert diag.temperature_c == 36.5
    assert (diag.current_a, diag.voltage_v, diag.status, diag.moving) == (None, None, None, None)


# Each diagnostic in physical units, worked out by hand from the register facts (twin.robot.sts3215):
# velocity steps/s x 2 pi / 4096 rad/s (sign bit 15 in raw registers), load x 0.1 % of stall torque (sign bit
# 10), temperature as sent, current x 6.5 mA, voltage x 0.1 V.
DIAGNOSTIC_CASES = [
    # (variant, the joint's raw fields, expected decoded fields)
    (
        Units.TICKS,
        {"velocity": 3400, "load": 800, "temp": 58, "current": 400, "voltage": 74},
        {
            "velocity_steps_s": 3400.0,
            "velocity_rad_s": 5.215534678811180,  # 3400 x 0.0015339807878856412
            "load_percent": 80.0,
            "temperature_c": 58.0,
            "current_a": 2.6,  # 400 x 6.5 mA = 2600 mA
            "voltage_v": 7.4,
        },
    ),
    (
        Units.TICKS,
        # 32768 + 205: backwards at 205 steps/s; 1024 + 313: load of 31.3 % the other way.
        {"velocity": 32973, "load": 1337, "temp": 71, "current": 1, "voltage": 50},
        {
            "velocity_steps_s": -205.0,
            "velocity_rad_s": -0.314466061516560,  # -205 x 2 pi / 4096
            "load_percent": -31.3,
            "temperature_c": 71.0,
            "current_a": 0.0065,
            "voltage_v": 5.0,
        },
    ),
    (
        Units.DEGREES,
        # LeRobot-normalised: velocity already signed; newer LeRobot signs the load too.
        {"velocity": -205.0, "load": -313.0, "temp": 64.0, "current": 250.0, "voltage": 121.0},
        {
            "velocity_steps_s": -205.0,
            "velocity_rad_s": -0.314466061516560,
            "load_percent": -31.3,
            "temperature_c": 64.0,
            "current_a": 1.625,  # 250 x 6.5 mA, LeRobot's gripper protection current
            "voltage_v": 12.1,
        },
    ),
    (
        Units.DEGREES,
        # Older LeRobot leaves the load's bit 10 in the float: 1337.0 is -31.3 % as in ticks.
        {"velocity": 0.0, "load": 1337.0, "temp": 30.0, "current": 0.0, "voltage": 60.0},
        {
            "velocity_steps_s": 0.0,
            "velocity_rad_s": 0.0,
            "load_percent": -31.3,
            "temperature_c": 30.0,
            "current_a": 0.0,
            "voltage_v": 6.0,
        },
    ),
]


@pytest.mark.parametrize(("units", "raw", "expected"), DIAGNOSTIC_CASES)
def test_each_diagnostic_decodes_to_physical_units(
    units: Units, raw: dict[str, Any], expected: dict[str, float]
) -> None:
    positions = TICKS_EXAMPLE if units is Units.TICKS else DEGREES_EXAMPLE
    diag = decoder(units).decode(payload(positions, **raw)).diagnostics["shoulder_lift"]
    for name, value in expected.items():
        assert getattr(diag, name) == pytest.approx(value, abs=1e-12), name


def test_missing_diagnostics_are_none_and_unknown_fields_ignored() -> None:
    msg = message(TICKS_EXAMPLE)
    msg["joints"]["wrist_roll"]["torque_enabled"] = "yes"  # a field a newer edge might add
    msg["firmware"] = {"anything": [1, 2, 3]}
    t = decoder(Units.TICKS).decode(json.dumps(msg))
    assert t.diagnostics["wrist_roll"] == JointDiagnostics()
    assert set(t.diagnostics) == set(NAMES)


def test_moving_accepts_bool_and_zero_one() -> None:
    d = decoder(Units.TICKS)
    assert d.decode(payload(TICKS_EXAMPLE, moving=False)).diagnostics["gripper"].moving is False
    assert d.decode(payload(TICKS_EXAMPLE, moving=0)).diagnostics["gripper"].moving is False
    assert d.decode(payload(TICKS_EXAMPLE, moving=True)).diagnostics["gripper"].moving is True


def test_raw_values_are_kept_as_sent() -> None:
    t = decoder(Units.TICKS).decode(payload(TICKS_EXAMPLE, velocity=32778, moving=1))
    assert t.positions_raw == dict(zip(NAMES, TICKS_EXAMPLE, strict=True))
    assert all(type(v) is int for v in t.positions_raw.values())
    reading = t.readings_raw["elbow_flex"]
    assert isinstance(reading, JointReading)
    assert (reading.position, reading.velocity, reading.moving) == (2200, 32778, 1)  # undecoded
    assert reading.load is msgspec.UNSET and reading.temp is msgspec.UNSET  # not sent
    degrees = decoder(Units.DEGREES).decode(payload(DEGREES_EXAMPLE))
    assert degrees.positions_raw["shoulder_lift"] == -98.89


def test_diagnostics_read_as_a_mapping() -> None:
    t = decoder(Units.TICKS).decode(payload(TICKS_EXAMPLE, temp=41))
    assert list(t.diagnostics) == list(NAMES) and len(t.diagnostics) == 6
    assert dict(t.diagnostics)["gripper"] == JointDiagnostics(temperature_c=41.0)
    assert t.diagnostics.get("elbow_roll") is None


VALID_TICKS = json.dumps(message(TICKS_EXAMPLE))


@pytest.mark.parametrize(
    ("payload_", "reason"),
    [
        # Cases a fast parser could wave through where the rules refuse them, and the reverse.
        ((VALID_TICKS[:-1] + ', "note": "\xff"}').encode("latin-1"), RejectReason.NOT_UTF8),
        ((VALID_TICKS[:-1] + ', "note": NaN}').encode(), RejectReason.NOT_FINITE),
        ((VALID_TICKS[:-1] + ', "note": 1e999}').encode(), None),  # an ignored field may overflow
        ((VALID_TICKS[:-1] + ', "deep": ' + "[" * 5000 + "]" * 5000 + "}").encode(), RejectReason.NOT_JSON),
        (
            VALID_TICKS.replace('{"position": 1500}', '{"position": 1500, "position": 4096}'),
            RejectReason.OUT_OF_RANGE,
        ),
        (
            VALID_TICKS.replace('{"position": 1500}', '{"position": 4096, "position": 1500}'),
            None,
        ),  # last wins
        (
            VALID_TICKS.replace('{"position": 1500}', '{"position": 1500, "moving": 1.0}'),
            RejectReason.WRONG_TYPE,
        ),
        (
            VALID_TICKS.replace('{"position": 1500}', '{"position": 1500, "status": 1000001}'),
            RejectReason.OUT_OF_RANGE,
        ),
        (VALID_TICKS.replace("1706000000000", "4102444800001"), RejectReason.BAD_TIMESTAMP),
        (VALID_TICKS.replace("1706000000000", "4102444800000"), None),
        (VALID_TICKS.replace('"arm-001"', '"a\\u2028b"'), RejectReason.BAD_DEVICE_ID),
    ],
)
def test_edge_cases_of_the_fast_parser(payload_: bytes | str, reason: RejectReason | None) -> None:
    if reason is None:
        assert decoder(Units.TICKS).decode(payload_).device_id == "arm-001"
        return
    with pytest.raises(TelemetryRejected) as info:
        decoder(Units.TICKS).decode(payload_)
    assert info.value.reason is reason, str(info.value)


def test_auto_decided_device_keeps_its_hints() -> None:
    # Once auto has decided, the topic picks that units' ranges before parsing; the message still says auto.
    d = decoder(auto_evidence_messages=1)
    assert d.decode(payload(DEGREES_EXAMPLE), topic_device="arm-001").units is Units.DEGREES
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(TICKS_EXAMPLE), topic_device="arm-001")
    assert info.value.reason is RejectReason.OUT_OF_RANGE
    assert "never changes its mind" in str(info.value)
    with pytest.raises(TelemetryRejected) as info:
        d.decode(payload(DEGREES_EXAMPLE, device="arm-002"), topic_device="arm-001")
    assert info.value.reason is RejectReason.DEVICE_MISMATCH


def test_topic_device_match_is_accepted() -> None:
    assert decoder(Units.TICKS).decode(payload(TICKS_EXAMPLE), topic_device="arm-001").device_id == "arm-001"


def test_str_and_bytes_payloads_agree() -> None:
    d = decoder(Units.TICKS)
    text = json.dumps(message(TICKS_EXAMPLE))
    assert d.decode(text) == d.decode(text.encode()) == d.decode(bytearray(text.encode()))


# --- every rejection reason ---------------------------------------------------------------------------------


def _mutated(mutate: Any, positions: tuple = TICKS_EXAMPLE) -> bytes:
    msg = message(positions)
    mutate(msg)
    return json.dumps(msg).encode()


def _set_joint(name: str, key: str, value: Any) -> Any:
    return lambda m: m["joints"][name].__setitem__(key, value)


VALID = json.dumps(message(TICKS_EXAMPLE))
REJECTS: list[tuple[str, Any, Units, RejectReason]] = [
    ("not-utf8", b'{"device_id": "arm-\xff"}', Units.TICKS, RejectReason.NOT_UTF8),
    ("lone-surrogate-str", '{"device_id": "\ud800"}', Units.TICKS, RejectReason.NOT_UTF8),
    ("not-json", b"device_id=arm-001", Units.TICKS, RejectReason.NOT_JSON),
    ("truncated-json", VALID[:-3].encode(), Units.TICKS, RejectReason.NOT_JSON),
    ("deeply-nested", b"[" * 50_000 + b"]" * 50_000, Units.TICKS, RejectReason.NOT_JSON),
    ("empty", b"", Units.TICKS, RejectReason.NOT_JSON),
    ("not-bytes", 12345, Units.TICKS, RejectReason.WRONG_TYPE),
    ("too-large", b" " * 131_073, Units.TICKS, RejectReason.TOO_LARGE),
    (
        "too-large-valid-json",
        (VALID[:-1] + ', "pad": "' + "x" * 131_072 + '"}').encode(),
        Units.TICKS,
        RejectReason.TOO_LARGE,
    ),
    ("too-large-multibyte-str", '"' + "\u00e9" * 70_000 + '"', Units.TICKS, RejectReason.TOO_LARGE),
    ("array", b"[1, 2, 3]", Units.TICKS, RejectReason.NOT_OBJECT),
    ("null", b"null", Units.TICKS, RejectReason.NOT_OBJECT),
    ("no-device", _mutated(lambda m: m.pop("device_id")), Units.TICKS, RejectReason.MISSING_FIELD),
    ("no-timestamp", _mutated(lambda m: m.pop("timestamp")), Units.TICKS, RejectReason.MISSING_FIELD),
    ("no-joints", _mutated(lambda m: m.pop("joints")), Units.TICKS, RejectReason.MISSING_FIELD),
    (
        "no-position",
        _mutated(lambda m: m["joints"]["elbow_flex"].pop("position")),
        Units.TICKS,
        RejectReason.MISSING_FIELD,
    ),
    ("device-empty", payload(TICKS_EXAMPLE, device=""), Units.TICKS, RejectReason.BAD_DEVICE_ID),
    ("device-int", payload(TICKS_EXAMPLE, device=1), Units.TICKS, RejectReason.BAD_DEVICE_ID),
    ("device-slash", payload(TICKS_EXAMPLE, device="arm/1"), Units.TICKS, RejectReason.BAD_DEVICE_ID),
    ("device-plus", payload(TICKS_EXAMPLE, device="arm+"), Units.TICKS, RejectReason.BAD_DEVICE_ID),
    ("device-hash", payload(TICKS_EXAMPLE, device="#"), Units.TICKS, RejectReason.BAD_DEVICE_ID),
    ("device-long", payload(TICKS_EXAMPLE, device="a" * 129), Units.TICKS, RejectReason.BAD_DEVICE_ID),
    ("device-control", payload(TICKS_EXAMPLE, device="arm\n1"), Units.TICKS, RejectReason.BAD_DEVICE_ID),
    ("ts-float", payload(TICKS_EXAMPLE, ts=1706000000000.0), Units.TICKS, RejectReason.BAD_TIMESTAMP),
    ("ts-bool", payload(TICKS_EXAMPLE, ts=True), Units.TICKS, RejectReason.BAD_TIMESTAMP),
    ("ts-str", payload(TICKS_EXAMPLE, ts="1706000000000"), Units.TICKS, RejectReason.BAD_TIMESTAMP),
    ("ts-seconds", payload(TICKS_EXAMPLE, ts=1706000000), Units.TICKS, RejectReason.BAD_TIMESTAMP),
    ("ts-negative", payload(TICKS_EXAMPLE, ts=-1), Units.TICKS, RejectReason.BAD_TIMESTAMP),
    ("ts-far-future", payload(TICKS_EXAMPLE, ts=10**20), Units.TICKS, RejectReason.BAD_TIMESTAMP),
    (
        "missing-joint",
        _mutated(lambda m: m["joints"].pop("wrist_roll")),
        Units.TICKS,
        RejectReason.MISSING_JOINT,
    ),
    (
        "renamed-joint",
        _mutated(lambda m: m["joints"].__setitem__("wrist_rotate", m["joints"].pop("wrist_roll"))),
        Units.TICKS,
        RejectReason.MISSING_JOINT,
    ),
    (
        "extra-joint",
        _mutated(lambda m: m["joints"].__setitem__("elbow_roll", {"position": 2048})),
        Units.TICKS,
        RejectReason.EXTRA_JOINT,
    ),
    (
        "joints-list",
        _mutated(lambda m: m.__setitem__("joints", [2048] * 6)),
        Units.TICKS,
        RejectReason.WRONG_TYPE,
    ),
    (
        "joint-number",
        _mutated(lambda m: m["joints"].__setitem__("gripper", 1500)),
        Units.TICKS,
        RejectReason.WRONG_TYPE,
    ),
    (
        "position-bool",
        _mutated(_set_joint("gripper", "position", True)),
        Units.TICKS,
        RejectReason.WRONG_TYPE,
    ),
    (
        "position-str",
        _mutated(_set_joint("gripper", "position", "1500")),
        Units.TICKS,
        RejectReason.WRONG_TYPE,
    ),
    (
        "position-null",
        _mutated(_set_joint("gripper", "position", None)),
        Units.TICKS,
        RejectReason.WRONG_TYPE,
    ),
    (
        "ticks-float",
        _mutated(_set_joint("gripper", "position", 1500.0)),
        Units.TICKS,
        RejectReason.WRONG_TYPE,
    ),
    (
        "velocity-str",
        _mutated(_set_joint("gripper", "velocity", "fast")),
        Units.TICKS,
        RejectReason.WRONG_TYPE,
    ),
    ("load-bool", _mutated(_set_joint("gripper", "load", False)), Units.TICKS, RejectReason.WRONG_TYPE),
    ("temp-null", _mutated(_set_joint("gripper", "temp", None)), Units.TICKS, RejectReason.WRONG_TYPE),
    ("status-float", _mutated(_set_joint("gripper", "status", 1.0)), Units.TICKS, RejectReason.WRONG_TYPE),
    ("status-bool", _mutated(_set_joint("gripper", "status", True)), Units.TICKS, RejectReason.WRONG_TYPE),
    ("moving-2", _mutated(_set_joint("gripper", "moving", 2)), Units.TICKS, RejectReason.WRONG_TYPE),
    ("moving-str", _mutated(_set_joint("gripper", "moving", "true")), Units.TICKS, RejectReason.WRONG_TYPE),
    ("nan-token", VALID.replace("1500", "NaN").encode(), Units.TICKS, RejectReason.NOT_FINITE),
    ("infinity-token", VALID.replace("1800", "-Infinity").encode(), Units.TICKS, RejectReason.NOT_FINITE),
    ("nan-in-ignored-field", (VALID[:-1] + ', "extra": NaN}').encode(), Units.TICKS, RejectReason.NOT_FINITE),
    (
        "overflowing-float",
        payload(DEGREES_EXAMPLE).replace(b"2.01", b"1e400"),
        Units.DEGREES,
        RejectReason.NOT_FINITE,
    ),
    (
        "overflowing-current",
        _mutated(_set_joint("gripper", "current", 1.0)).replace(b"1.0", b"1e999"),
        Units.TICKS,
        RejectReason.NOT_FINITE,
    ),
    (
        "ticks-over-4095",
        _mutated(_set_joint("gripper", "position", 4096)),
        Units.TICKS,
        RejectReason.OUT_OF_RANGE,
    ),
    (
        "ticks-negative",
        _mutated(_set_joint("gripper", "position", -1)),
        Units.TICKS,
        RejectReason.OUT_OF_RANGE,
    ),
    ("degrees-over-360", payload((361.0, 0, 0, 0, 0, 0)), Units.DEGREES, RejectReason.OUT_OF_RANGE),
    ("degrees-huge-int", payload((10**400, 0, 0, 0, 0, 0)), Units.DEGREES, RejectReason.OUT_OF_RANGE),
    ("gripper-over-100", payload((0, 0, 0, 0, 0, 100.5)), Units.DEGREES, RejectReason.OUT_OF_RANGE),
    ("gripper-negative", payload((0, 0, 0, 0, 0, -0.5)), Units.RANGE100, RejectReason.OUT_OF_RANGE),
    ("range100-over", payload((0, 0, 100.01, 0, 0, 0)), Units.RANGE100, RejectReason.OUT_OF_RANGE),
    (
        "velocity-absurd",
        _mutated(_set_joint("gripper", "velocity", 10**12)),
        Units.TICKS,
        RejectReason.OUT_OF_RANGE,
    ),
    ("undecided", payload(ZERO_DEGREES), Units.AUTO, RejectReason.UNITS_UNDECIDED),
]


@pytest.mark.parametrize(
    ("payload_", "units", "reason"), [r[1:] for r in REJECTS], ids=[r[0] for r in REJECTS]
)
def test_rejects(payload_: Any, units: Units, reason: RejectReason) -> None:
    with pytest.raises(TelemetryRejected) as info:
        decoder(units).decode(payload_)
    assert info.value.reason is reason, str(info.value)
    assert isinstance(info.value, ValueError)
    assert len(str(info.value)) > 20  # a sentence a person can act on, not a bare code


def test_device_mismatch() -> None:
    with pytest.raises(TelemetryRejected) as info:
        decoder(Units.TICKS).decode(payload(TICKS_EXAMPLE), topic_device="arm-002")
    assert info.value.reason is RejectReason.DEVICE_MISMATCH
    assert "'arm-001'" in str(info.value) and "'arm-002'" in str(info.value)


def test_an_arm_whose_own_calibration_was_refused_is_held_not_decoded_with_another() -> None:
    dec = decoder(Units.TICKS, calibration=load_calibration(EXAMPLE_CALIBRATION))
    dec.set_calibrations({}, held={"arm-001": "entry 'wrist_roll' is missing"})
    with pytest.raises(TelemetryRejected) as info:
        dec.decode(payload(TICKS_EXAMPLE))
    assert info.value.reason is RejectReason.CALIBRATION_REFUSED
    text = str(info.value)
    assert "arm-001" in text and "wrist_roll" in text and "twin calibration push arm-001" in text
    # Nothing kept for it: a restore would only exit 1, so none is offered.
    assert "restore" not in text, text
    assert "rather than decode with the config's, another arm's:" in text, text
    assert dec.decode(payload(TICKS_EXAMPLE, device="arm-002")).device_id == "arm-002"  # others decode
    # With no calibration in the config, the refusal named "the config's, another arm's", which is none.
    bare = decoder(Units.TICKS)
    bare.set_calibrations({}, held={"arm-001": "entry 'wrist_roll' is missing"})
    with pytest.raises(TelemetryRejected) as info:
        bare.decode(payload(TICKS_EXAMPLE))
    said = str(info.value)
    assert "rather than decode with the nominal SO-101's zero and range, not this arm's:" in said, said
    # The agent's own store goes into each command, so they reach the store it reads; a restore is offered
    # once the store keeps a calibration for the arm.
    dec.set_calibrations(
        {}, held={"arm-001": "a problem"}, store_option=" --store /srv/cal", restorable=["arm-001"]
    )
    commands = r"push arm-001 FILE --store /srv/cal`.*restore arm-001 --store /srv/cal`"
    with pytest.raises(TelemetryRejected, match=commands):
        dec.decode(payload(TICKS_EXAMPLE))
    # A good file of its own, and the arm is held no longer (a held arm with one is not held at all).
    own = load_calibration(EXAMPLE_CALIBRATION)
    dec.set_calibrations({"arm-001": own}, held={"arm-001": "an older problem"})
    assert dec.decode(payload(TICKS_EXAMPLE)).device_id == "arm-001"
    dec.set_calibrations({})
    assert dec.decode(payload(TICKS_EXAMPLE)).device_id == "arm-001"


def test_an_arm_publishing_degrees_is_not_held_for_a_calibration_it_does_not_use() -> None:
    """Degrees ignore every calibration (they are already relative to the arm's calibrated middle), yet a
    degrees arm whose own file was refused had each message refused as calibration_refused: its twin held
    still for a file it would never read. Under units=auto the message's own evidence says so."""
    for units in (Units.DEGREES, Units.AUTO):
        dec = decoder(units, auto_evidence_messages=1)
        dec.set_calibrations({}, held={"arm-001": "not valid JSON"})
        assert dec.decode(payload(DEGREES_EXAMPLE)).units is Units.DEGREES, units
    # Ticks under auto, or an auto message that cannot tell yet: the arm is held as before.
    for positions in (TICKS_EXAMPLE, (0, 0, 0, 0, 0, 0)):
        dec = decoder(Units.AUTO, auto_evidence_messages=1)
        dec.set_calibrations({}, held={"arm-001": "not valid JSON"})
        with pytest.raises(TelemetryRejected) as info:
            dec.decode(payload(positions))
        assert info.value.reason is RejectReason.CALIBRATION_REFUSED, positions


def test_every_reason_is_exercised() -> None:
    exercised = {r[3] for r in REJECTS} | {RejectReason.DEVICE_MISMATCH, RejectReason.CALIBRATION_REFUSED}
    assert exercised == set(RejectReason)


def test_size_is_checked_before_parsing() -> None:
    # Valid JSON just over a small limit is refused for its size, not parsed.
    small = decoder(Units.TICKS, max_payload_bytes=100)
    with pytest.raises(TelemetryRejected) as info:
        small.decode(payload(TICKS_EXAMPLE))
    assert info.value.reason is RejectReason.TOO_LARGE
    assert "100-byte limit" in str(info.value)


def test_seconds_timestamp_hint() -> None:
    with pytest.raises(TelemetryRejected) as info:
        decoder(Units.TICKS).decode(payload(TICKS_EXAMPLE, ts=1706000000))
    assert "epoch seconds" in str(info.value)


# --- config and calibration ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        {"units": "furlongs"},
        {"auto_evidence_messages": 0},
        {"max_payload_bytes": 0},
        {"gripper_range_rad": (1.0, 0.0)},
    ],
)
def test_bad_config_is_refused(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        DecoderConfig(**kwargs)


def test_config_accepts_units_strings() -> None:
    assert DecoderConfig(units="range100").units is Units.RANGE100  # type: ignore[arg-type]


def test_example_calibration_loads() -> None:
    cal = load_calibration(EXAMPLE_CALIBRATION)
    assert list(cal) == list(NAMES)
    assert cal["shoulder_pan"] == MotorCalibration(
        id=1, drive_mode=0, homing_offset=128, range_min=762, range_max=3310
    )
    assert cal["wrist_flex"].mid == 2015.5
    assert Calibration.from_dict(cal.to_dict()) == cal


def _write(tmp_path: Path, data: Any) -> Path:
    path = tmp_path / "cal.json"
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return path


def _example_without(joint: str) -> dict:
    data = json.loads(EXAMPLE_CALIBRATION.read_text())
    del data[joint]
    return data


def _example_with(joint: str, key: str, value: Any) -> dict:
    data = json.loads(EXAMPLE_CALIBRATION.read_text())
    data[joint][key] = value
    return data


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        ("{not json", "not valid JSON"),
        ([1, 2], "JSON object keyed by motor name"),
        ({"shoulder_pan": {"id": 1}}, "lacks"),
        (_example_with("gripper", "range_min", True), "must be a JSON integer"),
        (_example_with("gripper", "range_min", 3500), "range_min < range_max"),
        (_example_with("elbow_flex", "range_max", 4096), "range_min < range_max"),
        (_example_with("elbow_flex", "drive_mode", 2), "drive_mode must be 0 or 1"),
        (
            _example_with("elbow_flex", "homing_offset", 3000),
            r"homing_offset 3000 is outside the servo's \+-2047 .*; re-run the calibration",
        ),
        # Six motors and one key more: that key is named, not taken for a motor lacking its fields.
        ({**json.loads(EXAMPLE_CALIBRATION.read_text()), "elbow_roll": 5}, r"\(unknown elbow_roll\)"),
        ({**json.loads(EXAMPLE_CALIBRATION.read_text()), "meta": {"note": "x"}}, r"\(unknown meta\)"),
        # ... and five with it: the missing motor and the key are named, not "motor 'meta' lacks id".
        (
            {**_example_without("wrist_roll"), "meta": {"note": "x"}},
            r"\(missing wrist_roll; unknown meta\)",
        ),
        # A walk: these two were taken, or refused without saying why.
        (
            _example_with("wrist_flex", "id", 17),
            "has id 17, where an SO-101 follower's wrist_flex is motor 4",
        ),
        (
            {
                "homing_offset": [0] * 6,
                "drive_mode": [0] * 6,
                "start_pos": [0] * 6,
                "end_pos": [4095] * 6,
                "calib_mode": ["DEGREE"] * 6,
                "motor_names": list(NAMES),
            },
            "LeRobot's old calibration layout",
        ),
    ],
)
def test_bad_calibration_files(tmp_path: Path, data: Any, needle: str) -> None:
    with pytest.raises(ValueError, match=needle):
        load_calibration(_write(tmp_path, data))


def test_calibration_for_another_robot(tmp_path: Path) -> None:
    data = json.loads(EXAMPLE_CALIBRATION.read_text())
    data["wrist_rotate"] = data.pop("wrist_roll")
    with pytest.raises(ValueError, match="missing wrist_roll; unknown wrist_rotate"):
        load_calibration(_write(tmp_path, data))


def test_missing_calibration_file_names_lerobot_location(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="so_follower"):
        load_calibration(tmp_path / "nope.json")


# --- exact messages -----------------------------------------------------------------------------------------

# Reason and message of every case above under every units setting, as the decoder produced them before
# it moved its parsing to msgspec (tests/data/telemetry_rejections.json, written once by that decoder), but
# for changes made on purpose since: under auto, a position no units allow is out_of_range, not undecided, and
# a missing timestamp or position says who fixes it.
# People and runbooks match on these sentences, so a rewrite of the parsing must keep them word for word.
GOLDEN = json.loads((Path(__file__).parent / "data" / "telemetry_rejections.json").read_text())


@pytest.mark.parametrize(
    ("case_id", "payload_"), [(r[0], r[1]) for r in REJECTS], ids=[r[0] for r in REJECTS]
)
def test_rejection_messages_are_unchanged(case_id: str, payload_: Any) -> None:
    got = {}
    for units in ("ticks", "degrees", "range100", "auto"):
        try:
            decoder(Units(units)).decode(payload_)
            got[f"{units}/-"] = "accepted"
        except TelemetryRejected as exc:
            got[f"{units}/-"] = [str(exc.reason), str(exc)]
    assert got == GOLDEN[case_id]


def test_diagnostic_columns_hold_what_joint_diagnostics_hold() -> None:
    """The alarm engine's columns of many messages: value for value what each JointDiagnostics holds (sign
    bits, both variants' velocity), and a message that leaves a field out or sends `moving` is not known."""
    import random

    from twin.core.telemetry import diagnostic_columns

    rng = random.Random(21)
    decoders = {units: TelemetryDecoder(DecoderConfig(units=units)) for units in (Units.TICKS, Units.DEGREES)}
    messages = []
    for k in range(400):
        units = Units.TICKS if k % 3 else Units.DEGREES
        joints = {}
        for name in so101.JOINT_NAMES:
            joints[name] = {
                "position": rng.randint(0, 4095) if units is Units.TICKS else rng.uniform(-90, 90),
                "velocity": rng.choice([0, 5, 32768, 32768 + 40, 65535, -7, 900]),
                "load": rng.choice([0, 12, 1023, 1024, 1024 + 300, 2047, 2048, -50]),
                "temp": rng.choice([30, 45.5, 70]),
                "current": rng.choice([0, 100, 499, 12.5]),
                "voltage": rng.choice([0, 74, 120, 121.5, 250]),
            }
        if k % 5 == 0:
            del joints["wrist_roll"]["voltage"]  # left out: the joint's voltage unknown, the row still known
        if k % 17 == 0:
            del joints["wrist_flex"]["temp"]
        if k % 19 == 0:
            joints["gripper"]["moving"] = True
        if units is Units.DEGREES:
            joints["gripper"]["position"] = rng.uniform(0, 100)
        payload = {"device_id": "arm-001", "timestamp": 1_706_000_000_000 + k, "joints": joints}
        messages.append(decoders[units].decode(json.dumps(payload).encode()))
    columns = diagnostic_columns(messages)
    rows = [3, 0, 5, 5]
    every = columns.voltage_v(range(len(messages)))
    assert np.array_equal(columns.voltage_v(rows), every[rows], equal_nan=True)
    fields = {
        "temperature_c": columns.temperature_c,
        "current_a": columns.current_a,
        "load_percent": columns.load_percent,
        "velocity_rad_s": columns.velocity_rad_s,
    }
    for k, message in enumerate(messages):
        assert bool(columns.known[k]) == (k % 17 != 0 and k % 19 != 0), k
        # The supply voltage in every row, known or not; NaN where it was not sent.
        volts = [message.diagnostics[name].voltage_v for name in so101.JOINT_NAMES]
        assert [None if math.isnan(v) else v for v in columns.voltage_v([k])[0].tolist()] == volts, k
        assert (volts[4] is None) == (k % 5 == 0), k
        if not columns.known[k]:
            continue
        for j, name in enumerate(so101.JOINT_NAMES):
            diag = message.diagnostics[name]
            for field, column in fields.items():
                assert float(column[k, j]) == getattr(diag, field), (k, name, field)


def test_a_servos_status_bits_are_named() -> None:
    from twin.robot.sts3215 import STATUS_BITS, status_names

    assert STATUS_BITS == ("voltage", "sensor", "temperature", "current", "angle", "overload")
    assert status_names(0) == ()
    assert status_names(32) == ("overload",)
    assert status_names(1 | 8) == ("voltage", "current")
    assert status_names(0b111111) == STATUS_BITS
    assert status_names(64 | 2) == ("sensor",)  # bits above the sixth name nothing
