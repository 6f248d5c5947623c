"""What the SO-101 edge publishes: its mock-mode motion and the telemetry payloads built from it, plus the
malformed variants a consumer must reject. Pure (no MQTT): the edge simulator publishes these, the fidelity
benchmark and the tests use them directly.

Variant "ticks" sends raw STS3215 registers as the serial/mock modes do; variant "degrees" sends what the
LeRobot (ROS 2) mode sends for the same motion under a default calibration (docs/telemetry.md, "The edge's
telemetry contract").
"""

from __future__ import annotations

import json
import math
import random
import time
from typing import TYPE_CHECKING, Any

from twin.core.telemetry import MAX_PAYLOAD_BYTES
from twin.edge.servo_faults import (
    ModelLoads,
    ServoFault,
    current_register,
    load_register,
    overrides_at,
)
from twin.robot import so101, sts3215

if TYPE_CHECKING:
    # Only the physical mode loads MuJoCo: the payloads of the mock mode need none of it.
    from twin.edge.servo_physics import PhysicalArm, ServoReading

VARIANTS: tuple[str, ...] = ("ticks", "degrees")
# Each kind breaks one rule of the contract a consumer must check; all must be rejected, none may crash it.
MALFORMED_KINDS: tuple[str, ...] = (
    "not_json",
    "not_utf8",
    "not_object",
    "missing_field",
    "missing_joint",
    "not_finite",
    "too_large",
    "wrong_type",
    "bad_timestamp",
    "device_mismatch",
)
# STS3215 registers: velocity is sign-magnitude with the sign in bit 15, load has its sign in bit 10.
VELOCITY_SIGN_BIT = sts3215.VELOCITY_SIGN_BIT
LOAD_SIGN_BIT = sts3215.LOAD_SIGN_BIT
VOLTAGE_UNITS_PER_VOLT = sts3215.VOLTAGE_UNITS_PER_VOLT
# Default calibration for the "degrees" variant: arm joints centred on the LeRobot home tick; the gripper's
# calibrated range is the mock motion's span, so it sweeps 0..100 % (closed..open).
DEGREES_PER_TICK = 360.0 / so101.TICK_MAX
GRIPPER_RANGE_TICKS = (1548, 2548)


# The edge's mock mode (docs/telemetry.md, the contract): joint i (JOINT_NAMES order) at t s after start is
# int(2048 + 500 sin(t (0.5 + 0.1 i) + i pi/3)) ticks. The one definition of that motion in the project: the
# edge simulator publishes it, the fidelity benchmark measures against it, tests check both.
MOCK_CENTRE_TICKS = 2048.0
MOCK_AMPLITUDE_TICKS = 500.0
MOCK_BASE_RAD_S = 0.5  # angular frequency of joint 0 ...
MOCK_STEP_RAD_S = 0.1  # ... plus this much per joint index
MOCK_PHASE_STEP_RAD = math.pi / 3


def mock_motion_ticks(t: float) -> list[float]:
    """The mock motion itself (continuous ticks, JOINT_NAMES order) at edge time `t`: what servos following
    it would really read, before the edge truncates to whole ticks."""
    return [
        MOCK_CENTRE_TICKS
        + MOCK_AMPLITUDE_TICKS
        * math.sin(t * (MOCK_BASE_RAD_S + MOCK_STEP_RAD_S * i) + i * MOCK_PHASE_STEP_RAD)
        for i in range(len(so101.JOINT_NAMES))
    ]


def mock_motion_rates(t: float) -> tuple[list[float], list[float]]:
    """The mock motion's speed (ticks/s) and acceleration (ticks/s²) at edge time `t`, JOINT_NAMES order:
    the derivatives of `mock_motion_ticks`, which the physical servos turn into torques."""
    rates: list[float] = []
    accelerations: list[float] = []
    for i in range(len(so101.JOINT_NAMES)):
        omega = MOCK_BASE_RAD_S + MOCK_STEP_RAD_S * i
        phase = t * omega + i * MOCK_PHASE_STEP_RAD
        rates.append(MOCK_AMPLITUDE_TICKS * omega * math.cos(phase))
        accelerations.append(-MOCK_AMPLITUDE_TICKS * omega * omega * math.sin(phase))
    return rates, accelerations


def mock_ticks(t: float) -> list[int]:
    """The edge mock mode's published joint positions (whole ticks, truncated like the edge's int())."""
    return [int(ticks) for ticks in mock_motion_ticks(t)]


def sign_magnitude(value: int, sign_bit: int) -> int:
    """Encode like the servo register: |value|, plus `sign_bit` when negative (the edge passes it on raw)."""
    return sign_bit + abs(value) if value < 0 else value


def ticks_to_degrees(ticks: int) -> float:
    """LeRobot DEGREES mode with the default calibration (mid = TICK_HOME)."""
    return (ticks - so101.TICK_HOME) * DEGREES_PER_TICK


def ticks_to_gripper_percent(ticks: int) -> float:
    """LeRobot RANGE_0_100 for the gripper with the default calibration (0 closed, 100 open)."""
    lo, hi = GRIPPER_RANGE_TICKS
    return (min(max(ticks, lo), hi) - lo) / (hi - lo) * 100.0


def make_payload(
    device_id: str,
    t: float,
    variant: str,
    rng: random.Random,
    *,
    timestamp_ms: int | None = None,
    load_sign: bool = False,
    servo_faults: tuple[ServoFault, ...] = (),
    model_loads: ModelLoads | None = None,
    physical: PhysicalArm | None = None,
) -> dict[str, Any]:
    """One telemetry message as the edge builds it (before JSON encoding).

    `timestamp_ms` defaults to the wall clock now; `load_sign` sets bit 10 on about half the raw loads
    (variant ticks) or makes them negative (variant degrees, where newer LeRobot decodes the sign);
    `servo_faults` rewrite the readings of their joints while they last, and `model_loads` replaces the
    mock's random loads and currents with the load each servo reports holding the pose and the current it
    draws (twin.edge.servo_faults).
    `physical` replaces all the mock's random readings with what servos following the motion report
    (twin.edge.servo_physics); it keeps the arm's temperatures, so call it in time order.
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant {variant!r} is not one of {VARIANTS}")
    if physical is not None:
        if model_loads is not None:
            raise ValueError("physical servos already report the model's loads: give model_loads or physical")
        joints = _physical_joints(t, variant, physical, servo_faults)
    else:
        joints = _mock_joints(t, variant, rng, load_sign)
    if model_loads is not None or servo_faults:
        _apply_servo_faults(joints, t, variant, faults=servo_faults, model_loads=model_loads)
    return {
        "device_id": device_id,
        "timestamp": int(time.time() * 1000) if timestamp_ms is None else int(timestamp_ms),
        "joints": joints,
    }


def _mock_joints(t: float, variant: str, rng: random.Random, load_sign: bool) -> dict[str, dict[str, Any]]:
    """Every joint as the edge's mock mode sends it: the motion's position, uniform noise for the rest."""
    ticks = mock_ticks(t)
    joints: dict[str, dict[str, Any]] = {}
    for name, position in zip(so101.JOINT_NAMES, ticks, strict=True):
        velocity = rng.randint(-10, 10)
        load = rng.randint(5, 50)
        negative_load = load_sign and rng.random() < 0.5
        temp = rng.randint(30, 40)
        current = rng.randint(80, 300)
        if variant == "ticks":
            joints[name] = {
                "position": position,
                "velocity": sign_magnitude(velocity, VELOCITY_SIGN_BIT),
                "load": load + LOAD_SIGN_BIT if negative_load else load,
                "temp": temp,
                "current": current,
            }
        else:
            degrees = (
                ticks_to_gripper_percent(position) if name == so101.GRIPPER else ticks_to_degrees(position)
            )
            joints[name] = {
                "position": round(degrees, 4),
                "velocity": float(velocity),
                "load": float(-load if negative_load else load),
                "temp": float(temp),
                "voltage": float(rng.randint(118, 122)),
                "current": float(current),
            }
    return joints


def physical_readings(
    t: float, physical: PhysicalArm, faults: tuple[ServoFault, ...] = ()
) -> tuple[list[int], dict[str, ServoReading]]:
    """The mock motion's positions at edge time `t` (ticks, JOINT_NAMES order) and what `physical`'s servos
    read there, their temperatures integrated up to `t`. A joint a fault holds still is computed still, where
    the fault holds it. The edge simulator also calls it for ticks it skips without publishing."""
    ticks = mock_ticks(t)
    rates, accelerations = mock_motion_rates(t)
    overrides = overrides_at(faults, t)
    for i, name in enumerate(so101.JOINT_NAMES):
        o = overrides.get(name)
        if o is not None and o.hold_at_s is not None:
            ticks[i] = mock_ticks(o.hold_at_s)[i]
            rates[i] = accelerations[i] = 0.0
    return ticks, physical.readings(t, ticks, rates, accelerations)


def _physical_joints(
    t: float, variant: str, physical: PhysicalArm, faults: tuple[ServoFault, ...]
) -> dict[str, dict[str, Any]]:
    """Every joint's readings from the physical servos (`physical_readings`), encoded as the variant's
    registers."""
    ticks, readings = physical_readings(t, physical, faults)
    joints: dict[str, dict[str, Any]] = {}
    for name, position in zip(so101.JOINT_NAMES, ticks, strict=True):
        r = readings[name]
        steps = round(r.velocity_steps_s)
        # Present_Temperature reads whole degrees, whichever way the edge forwards it.
        temperature = round(r.temperature_c)
        volts = r.voltage_v * VOLTAGE_UNITS_PER_VOLT
        if variant == "ticks":
            joints[name] = {
                "position": position,
                "velocity": sign_magnitude(steps, VELOCITY_SIGN_BIT),
                "load": load_register(r.load_percent),
                "temp": temperature,
                "current": current_register(r.current_a),
                "voltage": round(volts),
            }
        else:
            degrees = (
                ticks_to_gripper_percent(position) if name == so101.GRIPPER else ticks_to_degrees(position)
            )
            joints[name] = {
                "position": round(degrees, 4),
                "velocity": float(steps),
                # LeRobot passes the register on in its 0.1 % units, the sign decoded.
                "load": round(r.load_percent * 10.0, 1),
                "temp": float(temperature),
                "voltage": round(volts, 1),
                "current": float(current_register(r.current_a)),
            }
    return joints


def _apply_servo_faults(
    joints: dict[str, dict[str, Any]],
    t: float,
    variant: str,
    *,
    faults: tuple[ServoFault, ...],
    model_loads: ModelLoads | None,
) -> None:
    """Rewrite loads (model-consistent, when asked) and the faulted joints' readings, encoded as the
    variant's registers."""
    ticks_variant = variant == "ticks"
    overrides = overrides_at(faults, t)
    positions = mock_ticks(t)
    for i, name in enumerate(so101.JOINT_NAMES):
        o = overrides.get(name)
        if o is not None and o.hold_at_s is not None:
            positions[i] = mock_ticks(o.hold_at_s)[i]
    loads = None
    # An edge that forwards the status register sends it on every joint: so does an arm whose faults trip one.
    with_status = any(fault.kind == "overload" for fault in faults)
    if model_loads is not None:
        loads = model_loads.percent(positions)
        volts = model_loads.supply_v * VOLTAGE_UNITS_PER_VOLT
        for fields in joints.values():
            fields["voltage"] = round(volts) if ticks_variant else round(volts, 1)
    for i, (name, fields) in enumerate(joints.items()):
        o = overrides.get(name)
        load = None if loads is None else loads[name]
        if o is not None and o.hold_at_s is not None:
            if ticks_variant:
                fields["position"] = positions[i]
            elif name == so101.GRIPPER:
                fields["position"] = round(ticks_to_gripper_percent(positions[i]), 4)
            else:
                fields["position"] = round(ticks_to_degrees(positions[i]), 4)
            fields["velocity"] = 0 if ticks_variant else 0.0
        if with_status:
            fields["status"] = (o.status or 0) if o is not None else 0
        if o is not None and o.temperature_c is not None:
            fields["temp"] = round(o.temperature_c) if ticks_variant else round(o.temperature_c, 1)
        if o is not None and o.load_percent is not None:
            load = o.load_percent
        elif o is not None and o.load_add_percent is not None:
            base = load if load is not None else _decoded_load(fields["load"])
            load = base + (o.load_add_percent if base >= 0 else -o.load_add_percent)
        if load is not None:
            # The LeRobot variant carries the sign as a sign (newer LeRobot decodes bit 10).
            fields["load"] = load_register(load) if ticks_variant else round(load * 10.0, 1)
        current = o.current_a if o is not None else None
        if current is None and loads is not None and model_loads is not None:
            # The current holding the pose draws, not the mock's random 0.52-1.95 A: those cross the
            # gripper's 1.3 A over-current line within minutes and never clear, so every simulated arm
            # would show a critical alarm nobody asked for.
            current = model_loads.current_a(loads[name])
        if current is not None:
            raw_current = current_register(current)
            fields["current"] = raw_current if ticks_variant else float(raw_current)


def _decoded_load(raw: float) -> float:
    """A load field as this module wrote it (bit 10 set, or a signed float) -> signed percent."""
    if raw >= LOAD_SIGN_BIT:
        return -(raw - LOAD_SIGN_BIT) * 0.1
    return raw * 0.1


def encode(payload: Any) -> bytes:
    return json.dumps(payload, separators=(",", ":")).encode()


def make_malformed(kind: str, payload: dict[str, Any], rng: random.Random) -> bytes:
    """`payload` broken in one documented way (MALFORMED_KINDS)."""
    broken = json.loads(json.dumps(payload))  # deep copy of plain JSON data
    joints: dict[str, dict[str, Any]] = broken["joints"]
    joint = rng.choice(list(joints))
    if kind == "not_json":
        return encode(payload)[: rng.randint(1, 40)]
    if kind == "not_utf8":
        return b"\xff\xfe" + encode(payload)
    if kind == "not_object":
        return encode([payload])
    if kind == "missing_field":
        del broken[rng.choice(["timestamp", "joints", "device_id"])]
    elif kind == "missing_joint":
        del joints[joint]
    elif kind == "not_finite":
        joints[joint]["position"] = rng.choice([math.nan, math.inf, -math.inf])
        # allow_nan: Python's json writes the NaN/Infinity tokens a sloppy C or JS producer might emit.
        return json.dumps(broken, separators=(",", ":"), allow_nan=True).encode()
    elif kind == "too_large":
        broken["padding"] = "x" * (MAX_PAYLOAD_BYTES + 4096)
    elif kind == "wrong_type":
        joints[joint]["position"] = rng.choice([str(joints[joint]["position"]), None, [1, 2], True])
    elif kind == "bad_timestamp":
        broken["timestamp"] = rng.choice(["2024-01-23T10:00:00Z", -5, 1.5e30, None])
    elif kind == "device_mismatch":
        broken["device_id"] = broken["device_id"] + "-other"
    else:
        raise ValueError(f"malformed kind {kind!r} is not one of {MALFORMED_KINDS}")
    return encode(broken)


def device_ids(count: int) -> list[str]:
    """arm-001 .. arm-NNN, the fleet naming of the edge."""
    if count < 1:
        raise ValueError(f"--devices {count} must be at least 1")
    return [f"arm-{i:03d}" for i in range(1, count + 1)]
