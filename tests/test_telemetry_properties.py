"""Property tests: whatever arrives, the decoder rejects it with a documented reason or returns sane angles.

About 10,500 generated payloads over five strategies (random bytes, random JSON values, near-valid messages
with mutated fields, valid messages, huge payloads), each fed to decoders in every units setting.
derandomize=True keeps CI reproducible; deadline=None because this 2-core machine is shared.

Accepted angles: the gripper always lies within the model's jaw range and range100 arm angles within the
model's joint ranges, by construction. Ticks and degrees arm angles are what the servo measured and are only
bounded physically (a 12-bit turn around the calibrated middle): a reading past a model joint limit is real
data, which DeviceTwin clamps and counts (docs/telemetry.md, "Accepted values").
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from twin.core.telemetry import (
    DecoderConfig,
    RejectReason,
    Telemetry,
    TelemetryDecoder,
    TelemetryRejected,
    Units,
)
from twin.robot import so101

NAMES = so101.JOINT_NAMES
K = 2 * math.pi / 4095
JAW_LO, JAW_HI = so101.JOINT_RANGES_RAD[so101.GRIPPER]
EPS = 1e-9
REASONS = set(RejectReason)
FIELDS = (
    "device_id",
    "timestamp",
    "joints",
    "position",
    "velocity",
    "load",
    "temp",
    "current",
    "voltage",
    "status",
    "moving",
    *NAMES,
)

EXPLICIT = {u: TelemetryDecoder(DecoderConfig(units=u)) for u in (Units.TICKS, Units.DEGREES, Units.RANGE100)}


def fast(n: int) -> settings:
    return settings(
        max_examples=n,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    )


def check_accepted(t: Telemetry) -> None:
    assert t.units in (Units.TICKS, Units.DEGREES, Units.RANGE100)
    assert list(t.angles_rad) == list(NAMES)
    assert list(t.diagnostics) == list(NAMES)
    assert all(type(a) is float and math.isfinite(a) for a in t.angles_rad.values())
    assert t.gripper_percent is not None and 0.0 <= t.gripper_percent <= 100.0
    assert JAW_LO - EPS <= t.angles_rad[so101.GRIPPER] <= JAW_HI + EPS
    for name in so101.ARM_JOINTS:
        angle = t.angles_rad[name]
        if t.units is Units.TICKS:
            # Default homing: raw 0..4095 around 2047.
            assert -2047 * K - EPS <= angle <= 2048 * K + EPS, (name, angle)
        elif t.units is Units.DEGREES:
            assert abs(angle) <= 2 * math.pi + EPS, (name, angle)
        else:
            lo, hi = so101.JOINT_RANGES_RAD[name]
            assert lo - EPS <= angle <= hi + EPS, (name, angle)
    for diag in t.diagnostics.values():
        for value in (
            diag.velocity_steps_s,
            diag.velocity_rad_s,
            diag.load_percent,
            diag.temperature_c,
            diag.current_a,
            diag.voltage_v,
        ):
            assert value is None or math.isfinite(value)


# A message that decides units=auto for arm-001 at once (auto_evidence_messages=1), per units.
DECIDING = {
    Units.TICKS: json.dumps(
        {"device_id": "arm-001", "timestamp": 1706000000000, "joints": {n: {"position": 3000} for n in NAMES}}
    ),
    Units.DEGREES: json.dumps(
        {
            "device_id": "arm-001",
            "timestamp": 1706000000000,
            "joints": {n: {"position": 1.5 if n == so101.GRIPPER else -1.5} for n in NAMES},
        }
    ),
}


def auto_decided(kind: Units | None) -> TelemetryDecoder:
    """A fresh units=auto decoder, with arm-001 already decided as `kind` (None: undecided)."""
    decoder = TelemetryDecoder(DecoderConfig(auto_evidence_messages=1))
    if kind is not None:
        assert decoder.decode(DECIDING[kind]).units is kind
    return decoder


def outcome(decode: Callable[[], Telemetry]) -> tuple[Any, ...]:
    """Everything a caller can observe of one decode: the telemetry's values, or the reason and message."""
    try:
        t = decode()
    except TelemetryRejected as exc:
        return ("rejected", exc.reason, str(exc))
    readings = {name: msgspec.structs.astuple(r) for name, r in t.readings_raw.items()}
    return (
        t.device_id,
        t.timestamp_ms,
        t.units,
        t.angles_rad,
        t.gripper_percent,
        dict(t.diagnostics),
        t.positions_raw,
        readings,
    )


def explained(decoder: TelemetryDecoder, payload: bytes | str, topic_device: str | None) -> Telemetry:
    """The rule-by-rule path the decoder takes when its msgspec schema refuses a message, forced."""
    return decoder._explain(decoder._envelope(payload), topic_device)


def feed(payload: bytes | str, topic_device: str | None = None) -> int:
    """Decode with every setting; returns how many accepted. Any exception but TelemetryRejected fails.

    Each payload also goes through the rule-by-rule explanation path on a decoder in the same state: the
    msgspec hot path must never accept what the rules refuse, and must give the same values, reasons and
    messages (docs/telemetry.md's sentences are the explanation path's).
    """
    accepted = 0
    # Explicit units; auto undecided; auto already decided for arm-001 (which picks a units schema by topic).
    makers = [*(lambda u=u: EXPLICIT[u] for u in EXPLICIT), lambda: auto_decided(None)]
    makers += [lambda k=kind: auto_decided(k) for kind in DECIDING]
    for make in makers:
        decoder = make()
        fast = outcome(lambda d=decoder: d.decode(payload, topic_device=topic_device))
        twin = decoder if decoder in EXPLICIT.values() else make()
        assert outcome(lambda d=twin: explained(d, payload, topic_device)) == fast, payload
        if fast[0] == "rejected":
            assert fast[1] in REASONS
            assert fast[2]
            continue
        check_accepted(decoder.decode(payload, topic_device=topic_device))
        accepted += 1
    return accepted


# --- strategies ---------------------------------------------------------------------------------------------

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.integers(min_value=-10, max_value=5000),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-400, max_value=400),
    st.text(max_size=8),
)
json_values = st.recursive(
    scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=6),
        st.dictionaries(st.one_of(st.sampled_from(FIELDS), st.text(max_size=6)), children, max_size=8),
    ),
    max_leaves=30,
)

# Cheaper values for mutating a near-valid message: hypothesis' drawing, not decoding, dominates the run time.
small_json = st.recursive(
    scalars,
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=4), c, max_size=3),
    max_leaves=6,
)
tick = st.integers(min_value=0, max_value=4095)
degree = st.one_of(st.floats(min_value=-360, max_value=360), st.integers(min_value=-360, max_value=360))
r100 = st.one_of(st.floats(min_value=-100, max_value=100), st.integers(min_value=-100, max_value=100))
percent = st.one_of(st.floats(min_value=0, max_value=100), st.integers(min_value=0, max_value=100))
device_ids = st.sampled_from(["arm-001", "arm-002", "a", "so101 lab 2", "\u00e4rm-\u00fc", "a" * 128])
timestamps = st.integers(min_value=946_684_800_000, max_value=4_102_444_800_000)
diag_fields = st.fixed_dictionaries(
    {},
    optional={
        "velocity": st.one_of(st.integers(min_value=0, max_value=65535), st.floats(-3400, 3400)),
        "load": st.one_of(st.integers(min_value=0, max_value=2047), st.floats(-1000, 2047)),
        "temp": st.integers(min_value=20, max_value=80),
        "current": st.integers(min_value=0, max_value=500),
        "voltage": st.integers(min_value=60, max_value=130),
        "status": st.integers(min_value=0, max_value=63),
        "moving": st.one_of(st.booleans(), st.integers(min_value=0, max_value=1)),
        "firmware_extra": st.sampled_from(["v2", 1, None, [1, 2], {"x": 1.5}]),
    },
)
MUTATIONS = (
    "set_top",
    "del_top",
    "set_joint",
    "del_joint_field",
    "del_joint",
    "add_joint",
    "set_field",
    "rename",
)


@st.composite
def valid_messages(draw: st.DrawFn) -> dict[str, Any]:
    kind = draw(st.sampled_from(["ticks", "degrees", "range100"]))
    arm = {"ticks": tick, "degrees": degree, "range100": r100}[kind]
    positions = [*draw(st.lists(arm, min_size=5, max_size=5)), draw(tick if kind == "ticks" else percent)]
    # One diagnostics draw shared by the joints that carry it keeps generation cheap.
    diag = draw(diag_fields)
    with_diag = draw(st.integers(min_value=0, max_value=63))
    joints = {
        n: {"position": p, **(diag if with_diag >> i & 1 else {})}
        for i, (n, p) in enumerate(zip(NAMES, positions, strict=True))
    }
    return {"device_id": draw(device_ids), "timestamp": draw(timestamps), "joints": joints}


@st.composite
def mutated_messages(draw: st.DrawFn) -> str:
    msg = draw(valid_messages())
    msg["joints"] = {n: dict(j) for n, j in msg["joints"].items()}  # the shared diag dict must not leak
    for _ in range(draw(st.integers(min_value=1, max_value=2))):
        op = draw(st.sampled_from(MUTATIONS))
        joints = msg.get("joints")
        if op == "set_top":
            msg[draw(st.sampled_from(["device_id", "timestamp", "joints", "extra"]))] = draw(small_json)
        elif op == "del_top" and msg:
            msg.pop(draw(st.sampled_from(sorted(msg))))
        elif isinstance(joints, dict) and joints:
            name = draw(st.sampled_from(sorted(joints)))
            if op == "set_joint":
                joints[name] = draw(small_json)
            elif op == "del_joint":
                del joints[name]
            elif op == "add_joint":
                joints[draw(st.text(max_size=12))] = {"position": draw(tick)}
            elif op == "rename":
                joints[name + draw(st.sampled_from(["_x", "", "2"]))] = joints.pop(name)
            elif isinstance(joints[name], dict):
                key = draw(st.sampled_from(FIELDS[3:11]))
                if op == "set_field":
                    joints[name][key] = draw(scalars)
                else:
                    joints[name].pop(key, None)
    text = json.dumps(msg)  # allow_nan: float('nan') becomes the NaN token the edge must not send
    if draw(st.integers(min_value=0, max_value=3)) == 0:
        cut = draw(st.integers(min_value=0, max_value=len(text)))
        text = text[:cut] + draw(st.sampled_from(["", "NaN", "Infinity", "-Infinity", "}", "\x00", "1e999"]))
    return text


# --- properties ---------------------------------------------------------------------------------------------


@pytest.mark.slow  # thousands of generated messages: tens of seconds on the dev machine
@fast(2500)
@given(st.binary(max_size=600))
def test_random_bytes(payload: bytes) -> None:
    feed(payload)


@pytest.mark.slow  # thousands of generated messages: tens of seconds on the dev machine
@fast(2500)
@given(json_values)
def test_random_json_values(value: Any) -> None:
    feed(json.dumps(value))
    feed(json.dumps(value).encode())


@pytest.mark.slow  # thousands of generated messages: tens of seconds on the dev machine
@fast(4500)
@given(mutated_messages(), st.sampled_from([None, "arm-001"]))
def test_near_valid_mutated_messages(payload: str, topic_device: str | None) -> None:
    feed(payload.encode("utf-8", "surrogatepass"), topic_device)


@pytest.mark.slow  # thousands of generated messages: tens of seconds on the dev machine
@fast(1000)
@given(valid_messages())
def test_valid_messages_are_accepted_in_their_own_units(msg: dict[str, Any]) -> None:
    positions = [msg["joints"][n]["position"] for n in NAMES]
    payload = json.dumps(msg).encode("utf-8", "surrogatepass")
    if not all(type(p) is int and 0 <= p <= 4095 for p in positions):
        units = Units.RANGE100 if all(-100 <= p <= 100 for p in positions[:5]) else Units.DEGREES
    else:
        units = Units.TICKS
    check_accepted(EXPLICIT[units].decode(payload))
    assert feed(payload) >= 1


@fast(60)
@given(st.integers(min_value=1, max_value=400_000), st.sampled_from(["bytes", "str", "multibyte", "json"]))
def test_huge_payloads(extra: int, shape: str) -> None:
    base = {
        "device_id": "arm-001",
        "timestamp": 1706000000000,
        "joints": {n: {"position": 2048} for n in NAMES},
    }
    if shape == "json":
        payload: bytes | str = json.dumps({**base, "pad": "x" * (131_072 + extra)}).encode()
    elif shape == "multibyte":
        # Under the limit in characters, over it in UTF-8 bytes: the size check must count bytes.
        payload = json.dumps({**base, "pad": "\u20ac" * (43_700 + extra // 10)}, ensure_ascii=False)
    elif shape == "str":
        payload = " " * (131_072 + extra)
    else:
        payload = b"{" * (131_072 + extra)
    for decoder in EXPLICIT.values():
        try:
            decoder.decode(payload)
        except TelemetryRejected as exc:
            assert exc.reason is RejectReason.TOO_LARGE
        else:
            raise AssertionError("a payload over 128 KB was accepted")
