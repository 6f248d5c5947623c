"""Edge telemetry -> validated joint angles: the twin's data path, pure and I/O free.

One message is a JSON object `{"device_id", "timestamp", "joints": {<joint>: {"position", ...}}}`
published by the edge component (IgnacioSanchezAlvarado/lerobot-aws-iot-greengrass
component/lerobot_telemetry). Nothing in it says which units `position` uses, so units are a setting
(docs/telemetry.md explains every rule here):

- ticks: raw STS3215 encoder counts, JSON integers 0..4095;
- degrees: LeRobot DEGREES (0 = middle of the calibrated range), gripper 0..100 percent;
- range100: LeRobot RANGE_M100_100 for the arm, gripper 0..100 percent;
- auto: decided once per device from agreeing evidence, never flipped per message.

Every rejection raises TelemetryRejected with a RejectReason from a fixed set and a message naming the fix.

Two paths, one set of rules. The hot path parses and type-checks a message in one pass with msgspec against a
typed schema of the contract (`JointReading`, `_Message`), then applies the rules that depend on the decoder's
state (units, auto evidence) or need a sentence of their own (device-id characters). When the schema refuses a
message, msgspec's error would neither name the fix nor always be the first rule the documented order
reports, so `_explain` parses it again with the standard json module and walks the rules in that order: the
reason and message for a payload are the same whichever path saw it first. The schema refuses whatever the
rules refuse (tests/test_telemetry_properties.py compares both paths on generated payloads), so the hot path
never accepts a message the explanation would reject.
"""

from __future__ import annotations

import functools
import json
import logging
import math
from array import array
from collections.abc import Collection, ItemsView, Iterator, Mapping, ValuesView
from dataclasses import dataclass, field
from enum import StrEnum
from operator import attrgetter
from typing import TYPE_CHECKING, Annotated, Any, Final, NoReturn, Protocol, TypeVar, cast, overload

import msgspec
from msgspec import UNSET, Meta, UnsetType

from twin.core.topics import device_id_problem
from twin.core.units import MAX_PAYLOAD_BYTES, UNITS_CHOICES, Units
from twin.robot import so101, sts3215
from twin.robot.calibration import Calibration

if TYPE_CHECKING:
    from collections.abc import Sequence

    import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "MAX_PAYLOAD_BYTES",
    "UNITS_CHOICES",
    "DecoderConfig",
    "DiagnosticColumns",
    "JointDiagnostics",
    "JointReading",
    "RejectReason",
    "Telemetry",
    "TelemetryDecoder",
    "TelemetryRejected",
    "Units",
    "decode_load",
    "decode_velocity",
    "diagnostic_columns",
]


class RejectReason(StrEnum):
    """Why a message was rejected: a fixed set, documented in docs/telemetry.md; metrics label by it."""

    NOT_UTF8 = "not_utf8"
    NOT_JSON = "not_json"
    TOO_LARGE = "too_large"
    NOT_OBJECT = "not_object"
    MISSING_FIELD = "missing_field"
    BAD_DEVICE_ID = "bad_device_id"
    BAD_TIMESTAMP = "bad_timestamp"
    DEVICE_MISMATCH = "device_mismatch"
    MISSING_JOINT = "missing_joint"
    EXTRA_JOINT = "extra_joint"
    WRONG_TYPE = "wrong_type"
    NOT_FINITE = "not_finite"
    OUT_OF_RANGE = "out_of_range"
    UNITS_UNDECIDED = "units_undecided"
    CALIBRATION_REFUSED = "calibration_refused"


class TelemetryRejected(ValueError):  # noqa: N818 - a public name: callers catch it, docs/telemetry.md names it
    """A message the decoder refuses; `reason` is for counting, `str(exc)` for people. `servo_diagnostics`:
    the servo readings of a message refused for its arm's calibration alone (CALIBRATION_REFUSED), which
    need none, so that arm's servos are still watched; None for every other refusal."""

    servo_diagnostics: Mapping[str, JointDiagnostics] | None = None
    servo_timestamp_ms: int = 0  # the edge's stamp of those readings

    def __init__(self, reason: RejectReason, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _uses_calibration(units: Units, positions: list[int | float]) -> bool:
    """Whether a message in `units` is decoded with a calibration: degrees are not (already relative to the
    arm's calibrated middle), so a held arm that publishes them is not held. An arm units=auto has not decided
    yet is judged by its message's evidence; one that cannot tell may use one."""
    if units is Units.AUTO:
        units = _evidence(positions) or Units.TICKS
    return units is not Units.DEGREES


# What a held arm would decode with instead (`_held`): with no calibration in the config, it was told the
# config's was another arm's.
_FALLBACK = {
    True: "the config's, another arm's",
    False: "the nominal SO-101's zero and range, not this arm's",
}


def _held(device_id: str, why: str, store_option: str, restorable: bool, fallback: bool) -> TelemetryRejected:
    # `restore` only when the store keeps a valid calibration for the arm: else it exits 1, a dead end.
    restore = (
        f", put the one it replaced back (`twin calibration restore {device_id}{store_option}`)"
        if restorable
        else ""
    )
    return TelemetryRejected(
        RejectReason.CALIBRATION_REFUSED,
        f"the calibration of {device_id} in the store was refused ({why}); the twin holds still rather than "
        f"decode with {_FALLBACK[fallback]}: push a good file (`twin calibration push {device_id} "
        f"FILE{store_option}`){restore}, or remove it",
    )


class JointDiagnostics(msgspec.Struct, frozen=True, gc=False):
    """Per-joint servo readings, decoded to physical units; None where the edge did not send the field.

    A msgspec Struct, like Telemetry: the alarm engine reads all six joints of every applied message, and a
    Struct is built in about a third of a slotted dataclass's time."""

    velocity_steps_s: float | None = None
    velocity_rad_s: float | None = None
    load_percent: float | None = None
    temperature_c: float | None = None
    current_a: float | None = None
    voltage_v: float | None = None
    status: int | None = None
    moving: bool | None = None


# Servo registers are at most 16 bits; anything far beyond is not a reading.
DIAGNOSTIC_LIMIT = 1_000_000.0
_INT_LIMIT = int(DIAGNOSTIC_LIMIT)
# A diagnostic reading: a JSON number (never a bool) within DIAGNOSTIC_LIMIT.
_Reading = (
    Annotated[int, Meta(ge=-_INT_LIMIT, le=_INT_LIMIT)]
    | Annotated[float, Meta(ge=-DIAGNOSTIC_LIMIT, le=DIAGNOSTIC_LIMIT)]
)


class JointReading(msgspec.Struct, frozen=True, gc=False):
    """One joint's fields exactly as the edge sent them, before any conversion; `msgspec.UNSET` (falsy) where
    the edge left a field out. The schema of the hot path: the types and bounds here are the contract's."""

    position: int | float
    velocity: _Reading | UnsetType = UNSET
    load: _Reading | UnsetType = UNSET
    temp: _Reading | UnsetType = UNSET
    current: _Reading | UnsetType = UNSET
    voltage: _Reading | UnsetType = UNSET
    status: Annotated[int, Meta(ge=-_INT_LIMIT, le=_INT_LIMIT)] | UnsetType = UNSET
    moving: bool | Annotated[int, Meta(ge=0, le=1)] | UnsetType = UNSET


class Telemetry(msgspec.Struct, frozen=True, gc=False):
    """One decoded message. Immutable; built once per message, so a msgspec Struct (a tenth of the cost of a
    frozen dataclass) rather than a dataclass."""

    device_id: str
    timestamp_ms: int
    units: Units
    angles_rad: dict[str, float]
    gripper_percent: float | None
    # Computed on first access: most consumers (the twin, health) never read them.
    diagnostics: Mapping[str, JointDiagnostics]
    # Every field of each joint as sent, in JOINT_NAMES order (`readings_raw` and `positions_raw` name them):
    # the positions before any units conversion, so a wrong units setting can be corrected afterwards.
    readings: tuple[JointReading, ...] = ()

    @property
    def readings_raw(self) -> dict[str, JointReading]:
        """Each joint's reading as sent, by joint name (a fresh dict)."""
        return dict(zip(_JOINTS, self.readings, strict=True))

    @property
    def positions_raw(self) -> dict[str, int | float]:
        """Each joint's position as sent (before any units conversion), by joint name (a fresh dict)."""
        return {name: r.position for name, r in zip(_JOINTS, self.readings, strict=True)}


_T = TypeVar("_T")


class _LazyDiagnostics(Mapping[str, JointDiagnostics]):
    """JointDiagnostics by joint name, converted from schema-checked readings when first read (the
    conversion cannot fail: the schema already checked every type and bound), one joint at a time for a
    reader that asks for one (the alarm engine, for the few servos that are not quiet), all six for one
    that iterates."""

    __slots__ = ("_float_variant", "_one", "_readings", "_values")

    def __init__(self, readings: tuple[JointReading, ...], float_variant: bool) -> None:
        self._readings = readings
        self._float_variant = float_variant
        self._values: dict[str, JointDiagnostics] | None = None
        self._one: dict[str, JointDiagnostics] | None = None

    def _all(self) -> dict[str, JointDiagnostics]:
        values = self._values
        if values is None:
            # Idempotent: two threads racing here compute equal dicts and either may win.
            values = self._values = {
                name: _reading_diagnostics(r, self._float_variant)
                for name, r in zip(_JOINTS, self._readings, strict=True)
            }
        return values

    def __getitem__(self, joint: str) -> JointDiagnostics:
        values = self._values
        if values is not None:
            return values[joint]
        one = self._one
        if one is None:
            one = self._one = {}
        found = one.get(joint)
        if found is None:
            index = _JOINT_INDEX[joint]  # KeyError for a joint the SO-101 does not have
            found = one[joint] = _reading_diagnostics(self._readings[index], self._float_variant)
        return found

    def __iter__(self) -> Iterator[str]:
        return iter(_JOINTS)

    def __len__(self) -> int:
        return len(_JOINTS)

    # The Mapping mixins would go through __getitem__ once per joint; a reader of every joint (the views of
    # /state) goes straight to the dict.
    def items(self) -> ItemsView[str, JointDiagnostics]:
        return self._all().items()

    def values(self) -> ValuesView[JointDiagnostics]:
        return self._all().values()

    @overload
    def get(self, joint: str, /) -> JointDiagnostics | None: ...
    @overload
    def get(self, joint: str, default: JointDiagnostics | _T, /) -> JointDiagnostics | _T: ...
    def get(self, joint: str, default: object = None) -> object:
        if joint not in _JOINT_INDEX:
            return default
        return self[joint]

    def __repr__(self) -> str:
        return repr(self._all())


@dataclass(frozen=True)
class DecoderConfig:
    units: Units = Units.AUTO
    calibration: Calibration | None = None
    gripper_range_rad: tuple[float, float] = field(default=so101.JOINT_RANGES_RAD[so101.GRIPPER])
    max_payload_bytes: int = MAX_PAYLOAD_BYTES
    auto_evidence_messages: int = 3

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "units", Units(self.units))
        except ValueError:
            raise ValueError(
                f"units must be one of {', '.join(u.value for u in Units)}, got {self.units!r}"
            ) from None
        lo, hi = self.gripper_range_rad
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(
                f"gripper_range_rad must be two finite radians lo < hi, got {self.gripper_range_rad}"
            )
        if self.max_payload_bytes < 1:
            raise ValueError(f"max_payload_bytes must be positive, got {self.max_payload_bytes}")
        if self.auto_evidence_messages < 1:
            raise ValueError(f"auto_evidence_messages must be at least 1, got {self.auto_evidence_messages}")


# --- servo register decoding -------------------------------------------------------------------------------

STEPS_PER_TURN = so101.TICKS_PER_TURN
# LeRobot's DEGREES scale divides by the resolution minus one (4095), not 4096.
RAD_PER_TICK = 2.0 * math.pi / so101.TICK_MAX
# Diagnostic register scales: twin.robot.sts3215 holds them with their sources.
RAD_PER_STEP_S = sts3215.RAD_PER_STEP
CURRENT_MA_PER_UNIT = sts3215.CURRENT_MA_PER_UNIT
VOLTAGE_UNITS_PER_VOLT = sts3215.VOLTAGE_UNITS_PER_VOLT
LOAD_UNITS_PER_PERCENT = sts3215.LOAD_UNITS_PER_PERCENT

# Bounds a message must respect; docs/telemetry.md lists them (device ids: twin.core.topics).
TIMESTAMP_MIN_MS = 946_684_800_000  # 2000-01-01: an edge clock before this is unset, or it sends seconds
TIMESTAMP_MAX_MS = 4_102_444_800_000  # 2100-01-01
# DEGREES = (raw - mid) * 360/4095 with raw and mid both in 0..4095, so no real reading exceeds 360 in size.
DEGREES_LIMIT = 360.0
RANGE100_LIMIT = 100.0
PERCENT_MAX = 100.0
# Auto mode keeps an evidence streak per device until it decides; cap the undecided ones so a flood of
# made-up device ids cannot grow memory without bound.
MAX_PENDING_DEVICES = 4096
# units=auto's decisions are kept for at most this many devices (the agent's own limit on devices is lower:
# telemetry.max_devices, at most 10,000, and it forgets every device it refuses).
MAX_DECIDED_DEVICES = 10_000


def decode_velocity(raw: float) -> float:
    """Present_Velocity register -> signed steps/s (sign-magnitude, sign in bit 15).

    Negative input is already signed (the edge's mock mode sends -10..10) and passes through, as does anything
    outside the 16-bit register.
    """
    if 32768 <= raw <= 65535:
        return -(raw - 32768)
    return raw


def decode_load(raw: float) -> float:
    """Present_Load register -> signed 0.1 % units (magnitude 0..1000, sign in bit 10: >= 1024 is negative).

    Newer LeRobot already decodes the sign, so negative input passes through, as does anything above 11 bits.
    """
    if 1024 <= raw <= 2047:
        return -(raw - 1024)
    return raw


# --- parsing helpers ---------------------------------------------------------------------------------------


class _NonFiniteTokenError(ValueError):
    pass


def _reject_constant(token: str) -> NoReturn:
    raise _NonFiniteTokenError(token)


# A JSON object as the standard parser returns it, on the explaining path: its values are whatever the edge
# sent, and the rules below check them one by one before anything reads them as numbers.
_JsonObject = dict[str, Any]
# Built once: json.loads with a hook would build a decoder per call on the hot path.
_JSON = json.JSONDecoder(parse_constant=_reject_constant)
_MISSING: Final = object()
_EMPTY_DIAGNOSTICS = JointDiagnostics()
_JOINTS = so101.JOINT_NAMES
_JOINT_SET = frozenset(_JOINTS)
_JOINT_INDEX = {name: i for i, name in enumerate(_JOINTS)}
_ARM = so101.ARM_JOINTS
_N_ARM = len(_ARM)
_NUMERIC_DIAG_FIELDS = ("velocity", "load", "temp", "current", "voltage")
_DIAG_FIELDS = (*_NUMERIC_DIAG_FIELDS, "status", "moving")

# The hot path's schemas of a whole message: exactly the six joints, each a JointReading; unknown top-level
# and per-joint fields are ignored, as the contract allows newer edges to add some. One schema per units
# setting also carries that setting's position ranges, so a message it accepts only needs arithmetic; the
# generic one (units=auto before a device is decided) leaves positions to the checks in TelemetryDecoder.
_Timestamp = Annotated[int, Meta(ge=TIMESTAMP_MIN_MS, le=TIMESTAMP_MAX_MS)]


class _Message(Protocol):
    """What a `_message_schema` decoder returns: a Struct class made at import time with these fields, and
    `joints` holding one JointReading subclass per joint (read with `_readings_of`)."""

    @property
    def device_id(self) -> str: ...
    @property
    def timestamp(self) -> int: ...
    @property
    def joints(self) -> object: ...


# Type expressions (an Annotated union) handed to msgspec as field types; they are objects, not classes.
def _number_within(lo: int, hi: int) -> object:
    return Annotated[int, Meta(ge=lo, le=hi)] | Annotated[float, Meta(ge=float(lo), le=float(hi))]


def _message_schema(
    tag: str, arm_position: object, gripper_position: object
) -> msgspec.json.Decoder[_Message]:
    def reading(kind: str, position: object) -> type[msgspec.Struct]:
        return msgspec.defstruct(
            f"_{kind}Reading{tag}", [("position", position)], bases=(JointReading,), frozen=True, gc=False
        )

    arm, gripper = reading("Arm", arm_position), reading("Gripper", gripper_position)
    joints = msgspec.defstruct(
        f"_Joints{tag}",
        [(name, gripper if name == so101.GRIPPER else arm) for name in _JOINTS],
        forbid_unknown_fields=True,
        frozen=True,
        gc=False,
    )
    message = msgspec.defstruct(
        f"_Message{tag}",
        [("device_id", str), ("timestamp", _Timestamp), ("joints", joints)],
        frozen=True,
        gc=False,
    )
    # defstruct's classes are typed as plain Structs; _Message names the fields this one was given above.
    return cast("msgspec.json.Decoder[_Message]", msgspec.json.Decoder(message))


_PERCENT = _number_within(0, int(PERCENT_MAX))
_SCHEMAS: dict[Units, msgspec.json.Decoder[_Message]] = {
    Units.AUTO: _message_schema("Any", int | float, int | float),
    Units.TICKS: _message_schema(
        "Ticks", Annotated[int, Meta(ge=0, le=so101.TICK_MAX)], Annotated[int, Meta(ge=0, le=so101.TICK_MAX)]
    ),
    Units.DEGREES: _message_schema(
        "Degrees", _number_within(-int(DEGREES_LIMIT), int(DEGREES_LIMIT)), _PERCENT
    ),
    Units.RANGE100: _message_schema(
        "Range100", _number_within(-int(RANGE100_LIMIT), int(RANGE100_LIMIT)), _PERCENT
    ),
}
# msgspec raises RecursionError on nesting deeper than it parses; the explanation then names it.
_SCHEMA_ERRORS = (msgspec.ValidationError, msgspec.DecodeError, RecursionError)
_readings_of = attrgetter(*_JOINTS)
_READING_FIELDS = JointReading.__struct_fields__


def _rejected(reason: RejectReason, message: str) -> TelemetryRejected:
    return TelemetryRejected(reason, message)


def _fmt(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


# A payload may carry thousands of joint names; its rejection goes into an event, a log line and /state,
# so it names the first few and counts the rest rather than growing with the payload.
MAX_NAMES_LISTED = 8


def _fmt_names(names: list[str]) -> str:
    listed = ", ".join(map(_fmt, names[:MAX_NAMES_LISTED]))
    rest = len(names) - MAX_NAMES_LISTED
    return f"{listed} and {rest} more" if rest > 0 else listed


def _units_hint(value: int | float) -> str:
    """What a position that does not fit the configured units looks like instead."""
    if type(value) is int and 360 < value <= so101.TICK_MAX:
        return "the edge looks like it sends raw ticks: set units=ticks"
    if value < 0 or (type(value) is float and not value.is_integer()):
        return "the edge looks like it sends LeRobot degrees: set units=degrees (or range100 for -100..100)"
    if RANGE100_LIMIT < abs(value) <= DEGREES_LIMIT:
        return "the edge looks like it sends LeRobot degrees: set units=degrees"
    return "no units produce this value: check the edge's position source"


def _check_number(joint: str, name: str, value: object) -> float:
    if type(value) is int or type(value) is float:
        if type(value) is float and not math.isfinite(value):
            raise _rejected(
                RejectReason.NOT_FINITE,
                f"{name} {value} of {joint} is not a finite number; the edge must send real readings "
                "(omit a field it cannot read)",
            )
        if not -DIAGNOSTIC_LIMIT <= value <= DIAGNOSTIC_LIMIT:
            raise _rejected(
                RejectReason.OUT_OF_RANGE,
                f"{name} {_fmt(value)} of {joint} is beyond any servo register "
                f"(|x| <= {DIAGNOSTIC_LIMIT:g}); check the edge's field mapping",
            )
        return value
    raise _rejected(
        RejectReason.WRONG_TYPE,
        f"{name} of {joint} must be a JSON number, got {_fmt(value)}; omit the field when it is unknown",
    )


def _messages(count: int) -> str:
    return "message" if count == 1 else "messages"


def _check_device_id(device_id: object) -> str:
    """`device_id` if it passes the device-id rule of twin.core.topics, else a rejection saying why."""
    problem = device_id_problem(device_id)
    if problem is None and isinstance(device_id, str):  # the rule accepts only strings
        return device_id
    raise _rejected(
        RejectReason.BAD_DEVICE_ID,
        f"device_id {_fmt(device_id)} is not usable: {problem}; rename the device on the edge",
    )


def _mismatch(device_id: str, topic_device: str) -> TelemetryRejected:
    return _rejected(
        RejectReason.DEVICE_MISMATCH,
        f"device_id {_fmt(device_id)} does not match the topic's device {_fmt(topic_device)}; "
        "the edge's device id and its topic must agree (fix the edge config)",
    )


@dataclass(frozen=True, slots=True)
class _PositionMap:
    """How one arm's positions become angles: every units variant of an arm joint is an affine map
    angle = a + b * value, precomputed per joint; the gripper's tick range for its percent."""

    affine: Mapping[Units, tuple[tuple[float, float], ...]]
    ticks: tuple[tuple[float, float], ...]
    grip_min: float
    grip_max: float
    grip_inverted: bool

    @classmethod
    def of(cls, cal: Calibration | None, jaw_span: float) -> _PositionMap:
        ticks: list[tuple[float, float]] = []
        range100: list[tuple[float, float]] = []
        for name in _ARM:
            if cal is not None:
                m = cal[name]
                ticks.append((-m.mid * RAD_PER_TICK, RAD_PER_TICK))
                # Inverting RANGE_M100_100 gives raw - mid = v/200 * (max - min); drive_mode 1 negated v.
                sign = -1.0 if m.drive_mode else 1.0
                range100.append((0.0, sign * (m.range_max - m.range_min) / 200.0 * RAD_PER_TICK))
            else:
                # LeRobot's half-turn homing puts the calibration pose (the model's zero) at 2047.
                ticks.append((-so101.TICK_HOME * RAD_PER_TICK, RAD_PER_TICK))
                lo, hi = so101.JOINT_RANGES_RAD[name]
                range100.append(((lo + hi) / 2.0, (hi - lo) / 200.0))
        affine = {
            Units.TICKS: tuple(ticks),
            Units.DEGREES: tuple((0.0, so101.DEG) for _ in _ARM),
            Units.RANGE100: tuple(range100),
        }
        if cal is not None:
            g = cal[so101.GRIPPER]
            return cls(
                affine, affine[Units.TICKS], float(g.range_min), float(g.range_max), bool(g.drive_mode)
            )
        # Without a file the jaw's tick span maps 1:1 (RAD_PER_TICK) onto the model's jaw range, centred on
        # the homing pose; not rounded to whole ticks so the mapping stays exact.
        half = jaw_span / 2.0 / RAD_PER_TICK
        return cls(affine, affine[Units.TICKS], so101.TICK_HOME - half, so101.TICK_HOME + half, False)


# Decoders with the same default map share one set of tables, read only: a map's tables hold 1.1 MB
# (tracemalloc) and take about 0.5 ms to make, and a process may hold many decoders (the property tests make
# thousands, which spent most of their time here).
@functools.lru_cache(maxsize=4)
def _tick_tables_of(
    affine: tuple[tuple[float, float], ...], grip: tuple[float, float, bool], jaw: tuple[float, float]
) -> tuple[list[list[float]], list[tuple[float, float]]]:
    """Per arm joint (`affine`: its ticks map), the angle of every whole tick 0..TICK_MAX; for the gripper
    (`grip`: its tick range and whether it is inverted; `jaw`: the jaw's lowest angle and span), its
    (angle, percent): `_angles`' arithmetic done once per tick value, so a message's conversion is six
    lookups (a fleet's every message goes through it)."""
    import numpy as np  # noqa: PLC0415 - the mirror has it loaded (MuJoCo); this module stays light

    # The same arithmetic as `_angles`, element by element in IEEE double: the same values, in microseconds.
    ticks = np.arange(so101.TICK_MAX + 1, dtype=np.float64)
    arm = [(a + b * ticks).tolist() for a, b in affine]
    (lo, hi, grip_inverted), (jaw_lo, jaw_span) = grip, jaw
    # LeRobot RANGE_0_100: clamp into the calibrated range, then scale; drive_mode 1 inverts.
    percent = (np.where(ticks < lo, lo, np.where(ticks > hi, hi, ticks)) - lo) / (hi - lo) * PERCENT_MAX
    if grip_inverted:
        percent = PERCENT_MAX - percent
    angle = jaw_lo + percent / PERCENT_MAX * jaw_span
    gripper = list(zip(angle.tolist(), percent.tolist(), strict=True))
    return arm, gripper


class TelemetryDecoder:
    """Validates and decodes edge messages. Not thread-safe (auto-units state): one per consuming thread."""

    def __init__(self, config: DecoderConfig | None = None) -> None:
        self.config = config or DecoderConfig()
        cfg = self.config
        self._max_bytes = cfg.max_payload_bytes
        self._jaw_lo, jaw_hi = cfg.gripper_range_rad
        self._jaw_span = jaw_hi - self._jaw_lo
        # How positions map to angles: the config's calibration (or the nominal SO-101 without one) for every
        # arm, and per arm its own where one was set (set_calibrations). The hot path looks its arm up once.
        self._default = _PositionMap.of(cfg.calibration, self._jaw_span)
        self._per_device: dict[str, _PositionMap] = {}
        self._calibrations: dict[str, Calibration] = {}
        # Arms whose own calibration was refused, with no good one to keep: why, by device (set_calibrations).
        self._held: dict[str, str] = {}
        self._store_option = ""
        self._restorable: frozenset[str] = frozenset()  # arms the store keeps a valid calibration for
        # The default map's angle of every whole tick (_tick_tables), made on the first message in ticks. Only
        # the default's: an arm with its own calibration converts by arithmetic, since a table per arm would
        # cost about 1.1 MB each (2,000 calibrated arms: 2.2 GB).
        self._tables: tuple[list[list[float]], list[tuple[float, float]]] | None = None
        self._decided: dict[str, Units] = {}
        self._streaks: dict[str, tuple[Units, int]] = {}
        # Device ids that already passed the character rule, so the hot path checks each id once.
        self._known_ids: set[str] = set()

    # --- public -------------------------------------------------------------------------------------------

    def set_calibrations(
        self,
        calibrations: Mapping[str, Calibration],
        held: Mapping[str, str] | None = None,
        store_option: str = "",
        restorable: Collection[str] = (),
    ) -> None:
        """Each arm's own LeRobot calibration (device id -> file), replacing the previous set; an arm not in
        it decodes with the config's calibration. Safe to call from another thread than the decoding one: the
        table is built aside and swapped in whole, so a message decodes with the old set or the new one.

        `held`: arms whose own calibration exists but was refused (device -> why), with none to keep. Their
        messages are refused as `calibration_refused` (unless in degrees, which use none): the config's
        calibration is another arm's, and decoding with it would move the twin to a wrong pose.
        `store_option` (e.g. ` --store DIR`) goes into the commands their refusal names, so they reach the
        store this agent reads; `restorable`, the refused arms the store keeps a valid calibration for, the
        only ones a refusal offers `twin calibration restore`."""
        self._store_option = store_option
        self._restorable = frozenset(restorable)
        self._held = {d: why for d, why in (held or {}).items() if d not in calibrations}
        kept = {d: m for d, m in self._per_device.items() if self._calibrations.get(d) == calibrations.get(d)}
        fresh = {
            device: kept.get(device) or _PositionMap.of(cal, self._jaw_span)
            for device, cal in calibrations.items()
        }
        self._calibrations = dict(calibrations)
        self._per_device = fresh

    def calibration_for(self, device_id: str) -> Calibration | None:
        """The calibration a device decodes with: its own, else the config's, else None (nominal SO-101)."""
        return self._calibrations.get(device_id, self.config.calibration)

    def units_for(self, device_id: str) -> Units:
        """The units in force for a device: the explicit setting, auto's decision, or AUTO while undecided."""
        if self.config.units is not Units.AUTO:
            return self.config.units
        return self._decided.get(device_id, Units.AUTO)

    def decided_units(self) -> dict[str, Units]:
        """units=auto's decisions so far, by device (for a restarted mirror to take back)."""
        return dict(self._decided)

    def restore_units(self, decided: Mapping[str, Units]) -> None:
        """Take back decisions `decided_units` exported: those devices skip the evidence again."""
        for device, units in decided.items():
            if units is not Units.AUTO:
                self._remember(device, units)

    def forget(self, device_id: str) -> None:
        """Drop what auto knows of a device the agent does not mirror (refused by its device limit), so
        invented device ids cannot grow the table."""
        self._decided.pop(device_id, None)
        self._streaks.pop(device_id, None)

    def _remember(self, device_id: str, units: Units) -> None:
        decided = self._decided
        if device_id not in decided and len(decided) >= MAX_DECIDED_DEVICES:
            # A backstop: the agent forgets every device it refuses, so only a fleet larger than this (or a
            # decoder used without the agent) gets here. The oldest decision goes; that arm decides again.
            del decided[next(iter(decided))]
        decided[device_id] = units

    def decode(self, payload: bytes | str, *, topic_device: str | None = None) -> Telemetry:
        """Validate and decode one message; raises TelemetryRejected (and nothing else) on bad input."""
        data = self._envelope(payload)
        units = self.config.units
        if units is Units.AUTO and topic_device is not None:
            # The topic names the device before parsing; a payload naming another device is refused below.
            units = self._decided.get(topic_device, Units.AUTO)
        try:
            msg = _SCHEMAS[units].decode(data)
        except _SCHEMA_ERRORS:
            return self._explain(data, topic_device)
        device_id = msg.device_id
        if device_id not in self._known_ids:
            _check_device_id(device_id)
            if len(self._known_ids) >= MAX_PENDING_DEVICES:
                self._known_ids.clear()
            self._known_ids.add(device_id)
        if topic_device is not None and device_id != topic_device:
            raise _mismatch(device_id, topic_device)
        readings: tuple[JointReading, ...] = _readings_of(msg.joints)
        positions = [r.position for r in readings]
        if self._held and device_id in self._held and _uses_calibration(units, positions):
            held = _held(
                device_id,
                self._held[device_id],
                self._store_option,
                device_id in self._restorable,
                self.config.calibration is not None,
            )
            # Temperatures, loads and currents need no calibration: the servos are watched while the pose
            # waits for a good file. The variant as units=auto would judge this message.
            variant = units if units is not Units.AUTO else _evidence(positions) or Units.TICKS
            held.servo_diagnostics = _LazyDiagnostics(readings, variant is not Units.TICKS)
            held.servo_timestamp_ms = msg.timestamp
            raise held
        undecided = False
        if units is Units.AUTO:
            units, angles, percent, undecided = self._units_and_angles(device_id, positions)
        else:
            angles, percent = self._angles(units, positions, self._per_device.get(device_id, self._default))
        if undecided:
            self._count_evidence(device_id, units)
        return Telemetry(
            device_id,
            msg.timestamp,
            units,
            dict(zip(_JOINTS, angles, strict=True)),
            percent,
            _LazyDiagnostics(readings, units is not Units.TICKS),
            readings,
        )

    def _units_and_angles(
        self, device_id: str, positions: list[int | float]
    ) -> tuple[Units, list[float], float, bool]:
        """The units in force, the converted angles and gripper percent, and whether auto is still deciding
        (then the message only counts as evidence once everything else about it proved valid)."""
        units = self.config.units
        mapping = self._per_device.get(device_id, self._default)
        if units is not Units.AUTO:
            return (units, *self._convert(units, positions, mapping, auto=False), False)
        units = self._decided.get(device_id, Units.AUTO)
        if units is not Units.AUTO:
            return (units, *self._convert(units, positions, mapping, auto=True), False)
        units = self._evidence_or_reject(device_id, positions)
        # Evidence only counts when the message is valid in those units, so it is converted first.
        return (units, *self._convert(units, positions, mapping, auto=False), True)

    def _explain(self, data: bytes | str, topic_device: str | None) -> Telemetry:
        """The rules one by one in the documented order, on the standard json module's parse: for a message
        the schema refused, this finds the first broken rule and says how to fix it."""
        # The rules run in their documented order, which decides the reason a broken message is counted under:
        # the document, device id, timestamp, the joints object, each joint's position, then the units.
        text = data if isinstance(data, str) else data.decode("utf-8")
        doc = self._parse(text)
        if type(doc) is not dict:
            raise _rejected(
                RejectReason.NOT_OBJECT,
                f"message must be a JSON object, got {type(doc).__name__}; the edge publishes one object "
                "per message",
            )
        device_id = self._device_id(doc, topic_device)
        timestamp = self._timestamp(doc)
        entries, positions = self._joints(doc)
        units, angles, percent, undecided = self._units_and_angles(device_id, positions)
        float_variant = units is not Units.TICKS
        # A bare {"position": ...} (the common case without diagnostics) shares one empty record.
        diagnostics = {
            name: _EMPTY_DIAGNOSTICS if len(entry) == 1 else _joint_diagnostics(name, entry, float_variant)
            for name, entry in zip(_JOINTS, entries, strict=True)
        }
        if undecided:
            self._count_evidence(device_id, units)
        return Telemetry(
            device_id=device_id,
            timestamp_ms=timestamp,
            units=units,
            angles_rad=dict(zip(_JOINTS, angles, strict=True)),
            gripper_percent=percent,
            diagnostics=diagnostics,
            readings=tuple(
                JointReading(**{k: entry[k] for k in _READING_FIELDS if k in entry}) for entry in entries
            ),
        )

    def _joints(self, doc: _JsonObject) -> tuple[list[_JsonObject], list[int | float]]:
        """The six joints' objects and positions in JOINT_NAMES order: 'joints' present, an object, exactly
        the six; then joint by joint, an object with a number for its position."""
        joints = doc.get("joints", _MISSING)
        if joints is _MISSING:
            raise _rejected(
                RejectReason.MISSING_FIELD, "message has no 'joints' object; check the edge version"
            )
        if type(joints) is not dict:
            raise _rejected(
                RejectReason.WRONG_TYPE,
                f"'joints' must be an object keyed by joint name, got {type(joints).__name__}",
            )
        if len(joints) != len(_JOINTS) or not _JOINT_SET.issuperset(joints):
            self._joint_set_error(joints)
        entries: list[_JsonObject] = []
        positions: list[int | float] = []
        for name in _JOINTS:
            entry = joints[name]
            if type(entry) is not dict:
                raise _rejected(
                    RejectReason.WRONG_TYPE,
                    f"joint {name} must be an object with a 'position', got {_fmt(entry)}",
                )
            positions.append(_position(name, entry))
            entries.append(entry)
        return entries, positions

    # --- envelope -----------------------------------------------------------------------------------------

    def _envelope(self, payload: bytes | str) -> bytes | str:
        """Size and encoding checks before any parsing; returns what the parsers read (UTF-8 proven)."""
        limit = self._max_bytes
        if isinstance(payload, str):
            # Size first: UTF-8 never takes fewer bytes than characters, and ASCII exactly as many.
            if len(payload) > limit or (
                not payload.isascii() and len(payload.encode("utf-8", "surrogatepass")) > limit
            ):
                raise self._too_large(len(payload.encode("utf-8", "surrogatepass")))
            if not payload.isascii():
                try:
                    payload.encode("utf-8")
                except UnicodeEncodeError:
                    raise _rejected(
                        RejectReason.NOT_UTF8, "message text holds lone surrogates, which UTF-8 cannot carry"
                    ) from None
            return payload
        if isinstance(payload, bytes | bytearray | memoryview):
            size = len(payload) if not isinstance(payload, memoryview) else payload.nbytes
            if size > limit:
                raise self._too_large(size)
            data = payload if type(payload) is bytes else bytes(payload)
            # ASCII is valid UTF-8 (and the usual case, checked at C speed); msgspec does not check the UTF-8
            # of strings it skips, so anything else is proven here.
            if not data.isascii():
                try:
                    data.decode("utf-8")
                except UnicodeDecodeError as exc:
                    raise _rejected(
                        RejectReason.NOT_UTF8,
                        f"message is not UTF-8 ({exc.reason} at byte {exc.start}); "
                        "the edge must publish UTF-8 JSON",
                    ) from None
            return data
        raise _rejected(
            RejectReason.WRONG_TYPE, f"payload must be bytes or str, got {type(payload).__name__}"
        )

    @staticmethod
    def _parse(text: str) -> object:
        try:
            return _JSON.decode(text)
        except _NonFiniteTokenError as exc:
            raise _rejected(
                RejectReason.NOT_FINITE,
                f"message holds the non-standard JSON token {exc.args[0]}; NaN/Infinity are not readings: "
                "fix the edge to send numbers or omit the field",
            ) from None
        except RecursionError:
            raise _rejected(
                RejectReason.NOT_JSON, "message JSON is nested too deeply to be telemetry"
            ) from None
        except ValueError as exc:
            raise _rejected(
                RejectReason.NOT_JSON,
                f"message is not valid JSON ({exc}); the edge publishes one JSON object",
            ) from None

    def _too_large(self, size: int) -> TelemetryRejected:
        return _rejected(
            RejectReason.TOO_LARGE,
            f"message is {size} bytes, over the {self._max_bytes}-byte limit "
            f"(the IoT Core maximum is {MAX_PAYLOAD_BYTES}); check what the edge packs into it",
        )

    @staticmethod
    def _device_id(doc: _JsonObject, topic_device: str | None) -> str:
        sent = doc.get("device_id", _MISSING)
        if sent is _MISSING:
            raise _rejected(
                RejectReason.MISSING_FIELD, "message has no 'device_id'; set the edge component's device id"
            )
        device_id = _check_device_id(sent)
        if topic_device is not None and device_id != topic_device:
            raise _mismatch(device_id, topic_device)
        return device_id

    @staticmethod
    def _timestamp(doc: _JsonObject) -> int:
        ts = doc.get("timestamp", _MISSING)
        if ts is _MISSING:
            raise _rejected(
                RejectReason.MISSING_FIELD,
                "message has no 'timestamp' (epoch milliseconds); update or reconfigure the edge component",
            )
        if type(ts) is not int:
            raise _rejected(
                RejectReason.BAD_TIMESTAMP,
                f"timestamp must be a JSON integer of epoch milliseconds, got {_fmt(ts)}",
            )
        if not TIMESTAMP_MIN_MS <= ts <= TIMESTAMP_MAX_MS:
            hint = (
                "it looks like epoch seconds: the edge must send milliseconds"
                if TIMESTAMP_MIN_MS // 1000 <= ts <= TIMESTAMP_MAX_MS // 1000
                else "the edge clock is unset or broken: enable NTP on the edge"
            )
            raise _rejected(
                RejectReason.BAD_TIMESTAMP,
                f"timestamp {_fmt(ts)} is outside 2000..2100 in epoch milliseconds; {hint}",
            )
        return ts

    @staticmethod
    def _joint_set_error(joints: _JsonObject) -> NoReturn:
        missing = [n for n in _JOINTS if n not in joints]
        extra = sorted(str(k) for k in joints if k not in _JOINT_SET)
        if missing:
            also = f" (it sent unknown joints {_fmt_names(extra)})" if extra else ""
            raise _rejected(
                RejectReason.MISSING_JOINT,
                f"joints {', '.join(missing)} are missing{also}; the SO-101 edge sends exactly "
                f"{', '.join(_JOINTS)}",
            )
        raise _rejected(
            RejectReason.EXTRA_JOINT,
            f"unknown joints {_fmt_names(extra)}; this decoder handles the six SO-101 joints "
            f"{', '.join(_JOINTS)} only (is this another robot's telemetry?)",
        )

    # --- units --------------------------------------------------------------------------------------------

    def _convert(
        self, units: Units, positions: list[int | float], mapping: _PositionMap, *, auto: bool
    ) -> tuple[list[float], float]:
        if units is Units.TICKS:
            self._check_ticks(positions, auto)
        else:
            self._check_normalised(units, positions, auto)
        return self._angles(units, positions, mapping)

    def _tick_tables(self) -> tuple[list[list[float]], list[tuple[float, float]]]:
        """The default map's tick tables (`_tick_tables_of`), on the first message in ticks."""
        m = self._default
        # (functools' cache types its arguments as any hashables: the call is not checked against them.)
        tables = _tick_tables_of(
            m.ticks, (m.grip_min, m.grip_max, m.grip_inverted), (self._jaw_lo, self._jaw_span)
        )
        self._tables = tables
        return tables

    def _angles(
        self, units: Units, positions: list[int | float], mapping: _PositionMap
    ) -> tuple[list[float], float]:
        """Positions already checked against `units` -> joint angles and gripper percent (arithmetic only)."""
        if units is Units.TICKS and mapping is self._default:
            # Whole ticks in 0..TICK_MAX here: the ticks schema or _check_ticks proved it.
            arm, gripper = self._tables or self._tick_tables()
            p0, p1, p2, p3, p4, p5 = positions
            angles = [arm[0][p0], arm[1][p1], arm[2][p2], arm[3][p3], arm[4][p4]]  # type: ignore[index]
            angle, percent = gripper[p5]  # type: ignore[index]
            angles.append(angle)
            return angles, percent
        if units is Units.TICKS:
            angles = [a + b * v for (a, b), v in zip(mapping.ticks, positions, strict=False)]
            raw = positions[_N_ARM]
            lo, hi = mapping.grip_min, mapping.grip_max
            # LeRobot RANGE_0_100: clamp into the calibrated range, then scale; drive_mode 1 inverts.
            clamped = lo if raw < lo else hi if raw > hi else raw
            percent = (clamped - lo) / (hi - lo) * PERCENT_MAX
            if mapping.grip_inverted:
                percent = PERCENT_MAX - percent
        else:
            # float() only after the range checks: a huge JSON integer would overflow it.
            angles = [a + b * float(v) for (a, b), v in zip(mapping.affine[units], positions, strict=False)]
            percent = float(positions[_N_ARM])
        angles.append(self._jaw_lo + percent / PERCENT_MAX * self._jaw_span)
        return angles, percent

    def _check_ticks(self, positions: list[int | float], auto: bool) -> None:
        for name, value in zip(_JOINTS, positions, strict=True):
            if type(value) is not int:
                fix = (
                    "the edge looks like it sends LeRobot degrees: set units=degrees"
                    if not float(value).is_integer() or value < 0
                    else "ticks arrive as JSON integers: check the edge sends raw ticks, or set units=degrees"
                )
                raise _rejected(
                    RejectReason.WRONG_TYPE,
                    f"position {_fmt(value)} of {name} is not a whole tick count; "
                    f"{fix}{self._auto_note(auto)}",
                )
            if not 0 <= value <= so101.TICK_MAX:
                fix = (
                    "the edge looks like it sends LeRobot degrees: set units=degrees"
                    if value < 0
                    else "check the edge reads position mode"
                )
                raise _rejected(
                    RejectReason.OUT_OF_RANGE,
                    f"position {_fmt(value)} of {name} is outside the encoder's 0..{so101.TICK_MAX}; "
                    f"{fix}{self._auto_note(auto)}",
                )

    def _check_normalised(self, units: Units, positions: list[int | float], auto: bool) -> None:
        limit = DEGREES_LIMIT if units is Units.DEGREES else RANGE100_LIMIT
        for name, value in zip(_ARM, positions, strict=False):
            if not -limit <= value <= limit:
                raise _rejected(
                    RejectReason.OUT_OF_RANGE,
                    f"position {_fmt(value)} of {name} is outside {units.value}'s -{limit:g}..{limit:g}; "
                    f"{_units_hint(value)}{self._auto_note(auto)}",
                )
        percent = positions[_N_ARM]
        if not 0 <= percent <= PERCENT_MAX:
            hint = (
                "the edge looks like it sends raw ticks: set units=ticks"
                if type(percent) is int and percent > PERCENT_MAX
                else "LeRobot reports the gripper as 0 (closed)..100 (open) percent"
            )
            raise _rejected(
                RejectReason.OUT_OF_RANGE,
                f"gripper position {_fmt(percent)} is outside 0..100 percent; {hint}{self._auto_note(auto)}",
            )

    @staticmethod
    def _auto_note(auto: bool) -> str:
        return " (units=auto decided otherwise for this device and never changes its mind)" if auto else ""

    @staticmethod
    def _evidence_or_reject(device_id: str, positions: list[int | float]) -> Units:
        kind = _evidence(positions)
        if kind is None:
            _check_fits_some_units(positions)
            raise _rejected(
                RejectReason.UNITS_UNDECIDED,
                f"units=auto has not decided {device_id}'s units yet and this message cannot tell (whole, "
                "non-negative, small positions fit ticks, degrees and range100 alike); waiting for clearer "
                "messages, or set units explicitly",
            )
        return kind

    def _count_evidence(self, device_id: str, kind: Units) -> None:
        """Count one valid evidence message; rejects it as units_undecided until enough agree in a row."""
        previous = self._streaks.pop(device_id, None)
        count = previous[1] + 1 if previous is not None and previous[0] is kind else 1
        if previous is not None and previous[0] is not kind:
            log.debug(
                "device %s: units evidence switched from %s to %s; streak restarts",
                device_id,
                previous[0],
                kind,
            )
        needed = self.config.auto_evidence_messages
        if count < needed:
            if len(self._streaks) >= MAX_PENDING_DEVICES:
                self._streaks.clear()
            self._streaks[device_id] = (kind, count)
            raise _rejected(
                RejectReason.UNITS_UNDECIDED,
                f"units=auto is collecting evidence for {device_id} ({count} of {needed} messages agree on "
                f"{kind.value}); set units explicitly to skip this",
            )
        self._remember(device_id, kind)
        if kind is Units.TICKS:
            log.info(
                "device %s: units=auto decided ticks after %d agreeing %s (JSON integers 0..4095, some "
                "above 360); this stays fixed until restart",
                device_id,
                needed,
                _messages(needed),
            )
        else:
            log.warning(
                "device %s: units=auto decided degrees after %d agreeing %s (negative or fractional "
                "positions: LeRobot-normalised). LeRobot's range100 (-100..100) cannot be told from degrees "
                "by value: if this arm runs LeRobot without use_degrees (before 0.4.4), set units=range100 "
                "explicitly. This stays fixed until restart.",
                device_id,
                needed,
                _messages(needed),
            )


def _position(name: str, entry: _JsonObject) -> int | float:
    """A joint's 'position': present, a JSON number, finite (its range is the units' rule)."""
    pos: object = entry.get("position", _MISSING)
    if type(pos) is float:
        if not math.isfinite(pos):
            raise _rejected(
                RejectReason.NOT_FINITE,
                f"position {pos} of {name} is not a finite number; check the edge's servo read",
            )
        return pos
    if type(pos) is not int:
        if pos is _MISSING:
            raise _rejected(
                RejectReason.MISSING_FIELD,
                f"joint {name} has no 'position'; update or reconfigure the edge component",
            )
        raise _rejected(
            RejectReason.WRONG_TYPE,
            f"position of {name} must be a JSON number, got {_fmt(pos)}",
        )
    return pos


def _check_fits_some_units(positions: list[int | float]) -> None:
    """Rejects a position no units setting allows for its joint: waiting for clearer messages never helps it.
    Only for messages `_evidence` found ambiguous, so every position here is whole and non-negative."""
    for name, value in zip(_JOINTS, positions, strict=True):
        # A whole, non-negative JSON integer fits ticks up to TICK_MAX; a JSON float never fits ticks, and
        # the gripper is a 0..100 percent in both normalised settings.
        float_max = PERCENT_MAX if name == so101.GRIPPER else DEGREES_LIMIT
        if value <= so101.TICK_MAX and (type(value) is int or value <= float_max):
            continue
        ranges = (
            f"degrees and range100: 0..{PERCENT_MAX:g} percent"
            if name == so101.GRIPPER
            else f"degrees: -{DEGREES_LIMIT:g}..{DEGREES_LIMIT:g}, range100: -{RANGE100_LIMIT:g}.."
            f"{RANGE100_LIMIT:g}"
        )
        hint = (
            "if it is a tick count, ticks arrive as JSON integers: check the edge sends raw ticks; if not, "
            "check the edge's position source"
            if value <= so101.TICK_MAX
            else "no units produce this value: check the edge's position source"
        )
        raise _rejected(
            RejectReason.OUT_OF_RANGE,
            f"position {_fmt(value)} of {name} fits no units (ticks: JSON integers 0..{so101.TICK_MAX}, "
            f"{ranges}); {hint}",
        )


def _evidence(positions: list[int | float]) -> Units | None:
    """Which units one message proves, or None when it fits several (docs/telemetry.md, "auto")."""
    any_big = False
    all_ticks = True
    for v in positions:
        if v < 0 or (type(v) is float and not v.is_integer()):
            return Units.DEGREES
        if type(v) is not int or v > so101.TICK_MAX:
            all_ticks = False
        elif v > DEGREES_LIMIT:
            any_big = True
    return Units.TICKS if all_ticks and any_big else None


def _joint_diagnostics(joint: str, entry: _JsonObject, float_variant: bool) -> JointDiagnostics:
    get = entry.get
    velocity = get("velocity")
    load = get("load")
    temp = get("temp")
    current = get("current")
    voltage = get("voltage")
    status = get("status")
    moving = get("moving")
    # One cheap pass for the usual all-plain-numbers case; anything odd goes to the checks that explain it.
    # (NaN fails the chained comparison, so it takes the slow path too.)
    for value in (velocity, load, temp, current, voltage):
        if value is not None and not (
            (type(value) is int or type(value) is float) and -DIAGNOSTIC_LIMIT <= value <= DIAGNOSTIC_LIMIT
        ):
            for key in _NUMERIC_DIAG_FIELDS:
                if key in entry:
                    _check_number(joint, key, entry[key])
    if status is not None and type(status) is not int:
        raise _rejected(
            RejectReason.WRONG_TYPE, f"status of {joint} must be a JSON integer, got {_fmt(status)}"
        )
    if status is not None:
        _check_number(joint, "status", status)
    if moving is not None and not (
        moving is True or moving is False or (type(moving) is int and 0 <= moving <= 1)
    ):
        raise _rejected(
            RejectReason.WRONG_TYPE, f"moving of {joint} must be true/false or 0/1, got {_fmt(moving)}"
        )
    if None in (velocity, load, temp, current, voltage, status, moving):
        # get() returns None for an absent field and for an explicit null; only the null is an error.
        for key in _DIAG_FIELDS:
            if key in entry and entry[key] is None:
                raise _rejected(
                    RejectReason.WRONG_TYPE,
                    f"{key} of {joint} is null; omit a field the edge cannot read instead of sending null",
                )
    return _converted(
        float_variant,
        velocity=velocity,
        load=load,
        temp=temp,
        current=current,
        voltage=voltage,
        status=status,
        moving=moving,
    )


def _converted(
    float_variant: bool,
    *,
    velocity: float | None,
    load: float | None,
    temp: float | None,
    current: float | None,
    voltage: float | None,
    status: int | None,
    moving: bool | int | None,
) -> JointDiagnostics:
    """Register readings already checked (None where absent) -> physical units; both decode paths end here."""
    steps = rad_s = None
    if velocity is not None:
        # The float variant (LeRobot-normalised) already carries a signed speed; raw ticks do not.
        steps = float(velocity if float_variant else decode_velocity(velocity))
        rad_s = steps * RAD_PER_STEP_S
    return JointDiagnostics(
        steps,
        rad_s,
        None if load is None else decode_load(load) / LOAD_UNITS_PER_PERCENT,
        None if temp is None else float(temp),
        # Divided last so whole mA stay exact: 100 units -> 650 mA -> 0.65 A.
        None if current is None else current * CURRENT_MA_PER_UNIT / 1000.0,
        None if voltage is None else voltage / VOLTAGE_UNITS_PER_VOLT,
        status,
        None if moving is None else bool(moving),
    )


def _reading_diagnostics(r: JointReading, float_variant: bool) -> JointDiagnostics:
    """JointDiagnostics of a reading the schema already checked (types and bounds): conversion only."""
    velocity, load, temp, current, voltage, status, moving = (
        r.velocity,
        r.load,
        r.temp,
        r.current,
        r.voltage,
        r.status,
        r.moving,
    )
    if (
        velocity is UNSET
        and load is UNSET
        and temp is UNSET
        and current is UNSET
        and voltage is UNSET
        and status is UNSET
        and moving is UNSET
    ):
        return _EMPTY_DIAGNOSTICS
    return _converted(
        float_variant,
        velocity=None if velocity is UNSET else velocity,
        load=None if load is UNSET else load,
        temp=None if temp is UNSET else temp,
        current=None if current is UNSET else current,
        voltage=None if voltage is UNSET else voltage,
        status=None if status is UNSET else status,
        moving=None if moving is UNSET else moving,
    )


# --- the diagnostics of many messages at once --------------------------------------------------------------


@dataclass(frozen=True)
class DiagnosticColumns:
    """The diagnostics the servo alarms read, of K messages at once: arrays of shape (K, 6), joints in
    JOINT_NAMES order, each value what `JointDiagnostics` holds for it (`_converted`'s arithmetic on arrays,
    so value for value the same, but for the sign of a zero). `known[k]` is False for a message that left one
    of these fields out or sent `moving` on some joint: its row holds nothing, and whoever reads it takes
    the message's `JointDiagnostics` instead."""

    known: np.ndarray
    temperature_c: np.ndarray
    current_a: np.ndarray
    load_percent: np.ndarray
    velocity_rad_s: np.ndarray
    # The status register as sent (NaN where a joint sent none), `known` or not: the servo error alarm's.
    status: np.ndarray
    messages: Sequence[Telemetry]

    def voltage_v(self, rows: Sequence[int]) -> np.ndarray:
        """(len(rows), 6) the supply voltage of those rows' joints, `known` or not; NaN where the joint sent
        none (`JointDiagnostics.voltage_v` None). Read only for the rows that need it (the model check's): a
        field most rows never need is not worth a column."""
        import numpy as np  # noqa: PLC0415 - as diagnostic_columns

        nan = math.nan
        volts = array("d")
        for k in rows:
            volts.extend([nan if r.voltage is UNSET else r.voltage for r in self.messages[k].readings])
        registers = np.frombuffer(volts, dtype=np.float64).reshape(len(rows), len(_JOINTS))
        return registers / VOLTAGE_UNITS_PER_VOLT


def diagnostic_columns(messages: Sequence[Telemetry]) -> DiagnosticColumns:
    """The servo alarms' diagnostics of `messages` as columns (DiagnosticColumns). About a microsecond a
    message: the alarm engine checks a fleet's quiet servos on these instead of six JointDiagnostics each."""
    import numpy as np  # noqa: PLC0415 - the mirror has it loaded (MuJoCo); this module stays light

    count = len(messages)
    raw = array("d")
    known = np.ones(count, dtype=bool)
    nothing = [math.nan] * (4 * len(_JOINTS))
    for k, message in enumerate(messages):
        r0, r1, r2, r3, r4, r5 = message.readings
        # One list display and one call: this runs for every applied message of the fleet.
        row: list[Any] = [
            *(r0.temp, r0.current, r0.load, r0.velocity),
            *(r1.temp, r1.current, r1.load, r1.velocity),
            *(r2.temp, r2.current, r2.load, r2.velocity),
            *(r3.temp, r3.current, r3.load, r3.velocity),
            *(r4.temp, r4.current, r4.load, r4.velocity),
            *(r5.temp, r5.current, r5.load, r5.velocity),
        ]
        try:
            if not (
                r0.moving is UNSET
                and r1.moving is UNSET
                and r2.moving is UNSET
                and r3.moving is UNSET
                and r4.moving is UNSET
                and r5.moving is UNSET
            ):
                raise TypeError
            raw.fromlist(row)  # a field left out (UNSET) is no real number: TypeError, the array unchanged
        except TypeError:
            raw.fromlist(nothing)
            known[k] = False
    values = np.frombuffer(raw, dtype=np.float64).reshape(count, len(_JOINTS), 4)
    float_variant = np.fromiter((m.units is not Units.TICKS for m in messages), dtype=bool, count=count)
    load = values[..., 2]
    velocity = values[..., 3]
    # decode_load and decode_velocity (sign in bit 10 and bit 15), then the registers' scales, as _converted.
    load = np.where((load >= 1024) & (load <= 2047), -(load - 1024), load) / LOAD_UNITS_PER_PERCENT
    signed = np.where((velocity >= 32768) & (velocity <= 65535), -(velocity - 32768), velocity)
    steps = np.where(float_variant[:, None], velocity, signed)
    return DiagnosticColumns(
        known=known,
        temperature_c=values[..., 0].copy(),
        current_a=values[..., 1] * CURRENT_MA_PER_UNIT / 1000.0,
        load_percent=load,
        velocity_rad_s=steps * RAD_PER_STEP_S,
        status=_status_column(messages),
        messages=messages,
    )


def _status_column(messages: Sequence[Telemetry]) -> np.ndarray:
    """(K, 6) the status registers as sent, NaN where a joint sent none: few edges send `status`, so a row
    is filled only for a message that has one."""
    import numpy as np  # noqa: PLC0415 - as diagnostic_columns

    status = np.full((len(messages), len(_JOINTS)), math.nan)
    for k, message in enumerate(messages):
        r0, r1, r2, r3, r4, r5 = message.readings
        if (
            r0.status is UNSET
            and r1.status is UNSET
            and r2.status is UNSET
            and r3.status is UNSET
            and r4.status is UNSET
            and r5.status is UNSET
        ):
            continue
        status[k] = [math.nan if r.status is UNSET else r.status for r in message.readings]
    return status
