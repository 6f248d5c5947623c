"""Servo alarms: over-temperature, over-current, sustained overload and model mismatch, per joint of each arm.

Pure and I/O free, with the time passed in (the agent's monotonic receive time), so every rule is tested
without sleeping. The worker calls `ServoAlarms.evaluate_batch` for each round of applied messages (one per
device); people acknowledge through the HTTP API (`acknowledge`).

States follow AWS IoT SiteWise / IoT Events alarms (iotevents-data API `AlarmState`):

- NORMAL: the condition is absent;
- ACTIVE: the condition is present and nobody has acknowledged it;
- ACKNOWLEDGED: the condition is present and a person has acknowledged it;
- LATCHED: the condition has gone but nobody acknowledged it: it stays visible until acknowledged, so a
  servo that overheated at night is still on the board in the morning.

    NORMAL --raise--> ACTIVE --ack--> ACKNOWLEDGED --clear--> NORMAL
                        |  ^                                    ^
                   clear|  |raise                               |
                        v  |                                    |
                      LATCHED ---------------ack----------------+

Each condition has hysteresis and minimum durations: it is raised once the value has stayed at or beyond
`raise_at` for `raise_after_s`, and cleared once it has stayed at or below `clear_at` for `clear_after_s`. A
value in between, or no value at all (the field was not sent, the joint is moving for the model check), holds
the condition as it is and restarts both timers: a noisy reading never flaps the alarm.

The thresholds' defaults come from the servo's factory settings (twin.robot.sts3215); docs/servo-health.md
explains each and what to do when it fires.
"""

from __future__ import annotations

import dataclasses
import math
import re
from array import array
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from operator import itemgetter
from typing import TYPE_CHECKING, Any, Final

from twin.robot import so101, sts3215

if TYPE_CHECKING:
    # Annotations only: the config loads the alarm thresholds from here, and `twin --help` must not need the
    # decoder's msgspec (tests/infra/test_userdata.py installs the package without its dependencies); nor
    # may the agent's receiving process, which imports this module, load numpy (evaluate_batch does, in the
    # mirrors, which have it loaded for MuJoCo).

    from twin.core.telemetry import DiagnosticColumns, JointDiagnostics


class AlarmState(StrEnum):
    NORMAL = "NORMAL"
    ACTIVE = "ACTIVE"
    ACKNOWLEDGED = "ACKNOWLEDGED"
    LATCHED = "LATCHED"


class Severity(StrEnum):
    WARNING = "warning"
    CRITICAL = "critical"

    @property
    def rank(self) -> int:
        return 2 if self is Severity.CRITICAL else 1


class AlarmKind(StrEnum):
    OVER_TEMPERATURE = "over_temperature"
    OVER_TEMPERATURE_CRITICAL = "over_temperature_critical"
    OVER_CURRENT = "over_current"
    OVERLOAD = "overload"
    MODEL_MISMATCH = "model_mismatch"
    SERVO_ERROR = "servo_error"


SEVERITY: dict[AlarmKind, Severity] = {
    AlarmKind.OVER_TEMPERATURE: Severity.WARNING,
    AlarmKind.OVER_TEMPERATURE_CRITICAL: Severity.CRITICAL,
    AlarmKind.OVER_CURRENT: Severity.CRITICAL,
    AlarmKind.OVERLOAD: Severity.WARNING,
    AlarmKind.MODEL_MISMATCH: Severity.WARNING,
    # The servo's own protection acted (it cuts or limits its torque): the arm may no longer hold its pose.
    AlarmKind.SERVO_ERROR: Severity.CRITICAL,
}

# What a person does at the arm about each kind: docs/servo-health.md's "What to do" table, shortened. An
# alarm's e-mail (output.alerts) and its row on the console's Arm page carry it: either may be all they see
# (a phone at night), so neither may send them to a page before they can act.
WHAT_TO_DO: dict[str, str] = {
    AlarmKind.OVER_TEMPERATURE: (
        "lower the arm to a rest pose or let it rest; check the joint moves freely. A servo much hotter than "
        "its neighbours on similar work is wearing."
    ),
    AlarmKind.OVER_TEMPERATURE_CRITICAL: (
        "stop the task now and park the arm supported: at 70 C the servo cuts its torque and the arm drops. "
        "Let it cool below 55 C before resuming."
    ),
    AlarmKind.OVER_CURRENT: (
        "stop the motion; check for a collision or a trapped cable. If it recurs in free motion, replace "
        "the servo."
    ),
    AlarmKind.OVERLOAD: (
        "reduce the payload or bring it closer to the base (after 2 s at this load the servo drops to 20 % "
        "torque)."
    ),
    AlarmKind.MODEL_MISMATCH: (
        "look at the arm: clear anything touching it; a payload it carries is expected (acknowledge). "
        "Otherwise compare with the joint's history (wear) and check [alarms] servo_version."
    ),
    AlarmKind.SERVO_ERROR: (
        "the arm may not hold its pose: stop the motion and support it, then let the servo rest. Voltage: "
        "check the supply and its cable; angle: calibrate again; sensor: power-cycle, replace if it recurs."
    ),
}
# A servo error's advice, per status bit set: the person at the arm reads the bits the servo set, not a
# list of all six (a voltage error sent them to calibrate as well). Lead: what every servo error needs.
SERVO_ERROR_LEAD = "the arm may not hold its pose: stop the motion and support it."
SERVO_ERROR_BIT_ADVICE: dict[str, str] = {
    "voltage": "Voltage: check the supply and its cable under load.",
    "sensor": "Sensor: power-cycle the arm; if it recurs, replace the servo.",
    "temperature": "Temperature: the servo cut its torque at 70 C; let it cool below 55 C before resuming.",
    "current": "Current: check for a collision or a trapped cable, then let the servo rest.",
    "angle": (
        "Angle: a goal position outside the servo's limits (from the leader or the policy): calibrate again."
    ),
    "overload": "Overload: reduce the payload or bring it closer to the base, then let the servo rest.",
}
# As WHAT_TO_DO_AT, for a bit: the gripper's overload is its jaw, not a payload.
SERVO_ERROR_BIT_ADVICE_AT: dict[tuple[str, str], str] = {
    ("gripper", "overload"): "Overload: the jaw is squeezing something hard: open it, grip with less force.",
}
# Where a joint's own servo calls for other advice than the kind's: an alarm names one servo, and the person
# at the arm reads only its advice (the gripper's jaw on an elbow's overload sent them to the wrong joint).
WHAT_TO_DO_AT: dict[tuple[str, str], str] = {
    ("gripper", AlarmKind.OVERLOAD): (
        "the jaw is squeezing something hard: open it, and grip with less force (after 2 s at this load the "
        "servo drops to 20 % torque)."
    ),
}


def what_to_do(kind: str, joint: str, value: float | None = None, message: str = "") -> str:
    """What a person does at the arm about an alarm of `kind` on `joint`'s servo; "" for a kind this agent
    has no advice for. A servo error's `value` (its set status bits) narrows the advice to those bits; with
    none set (its condition gone: LATCHED, or waiting to clear), the bits its raise `message` names do."""
    if kind == AlarmKind.SERVO_ERROR:
        names = _error_names(value) or _error_names(_raised_bits(message))
        if names:
            advice = (SERVO_ERROR_BIT_ADVICE_AT.get((joint, n)) or SERVO_ERROR_BIT_ADVICE[n] for n in names)
            return " ".join([SERVO_ERROR_LEAD, *advice])
    return WHAT_TO_DO_AT.get((joint, kind)) or WHAT_TO_DO.get(kind, "")


def _error_names(value: float | None) -> tuple[str, ...]:
    if value is None or not math.isfinite(value):
        return ()
    return sts3215.status_names(int(value))


# A servo error's raise message gives its bits as "(status bits N)" (`_describe`): a LATCHED error's value
# is the register's now, no bit set, and whoever acknowledges it got the advice for all six bits.
_RAISED_BITS = re.compile(r"\(status bits (\d+)\)")


def _raised_bits(message: str) -> float | None:
    found = _RAISED_BITS.search(message)
    return float(found.group(1)) if found else None


UNITS: dict[AlarmKind, str] = {
    AlarmKind.OVER_TEMPERATURE: "C",
    AlarmKind.OVER_TEMPERATURE_CRITICAL: "C",
    AlarmKind.OVER_CURRENT: "A",
    AlarmKind.OVERLOAD: "%",
    AlarmKind.MODEL_MISMATCH: "% points",
    AlarmKind.SERVO_ERROR: "status",
}
# The order evaluate() feeds values in: temperature (twice), current, |load|, model mismatch, status bits.
_KINDS: tuple[AlarmKind, ...] = (
    AlarmKind.OVER_TEMPERATURE,
    AlarmKind.OVER_TEMPERATURE_CRITICAL,
    AlarmKind.OVER_CURRENT,
    AlarmKind.OVERLOAD,
    AlarmKind.MODEL_MISMATCH,
    AlarmKind.SERVO_ERROR,
)
_JOINT_SET = frozenset(so101.JOINT_NAMES)
_JOINT_INDEX = {joint: i for i, joint in enumerate(so101.JOINT_NAMES)}
# What follows the device in an alarm id (`alarm_id`), per joint and kind.
_ID_SUFFIX = {(joint, kind): f"/{joint}/{kind.value}" for joint in so101.JOINT_NAMES for kind in AlarmKind}
# Poses further apart than this (edge clock) say nothing about the speed between them.
MAX_POSE_GAP_S = 1.0
# States in which the condition is present; LATCHED is remembered, not present.
CONDITION_PRESENT = frozenset({AlarmState.ACTIVE, AlarmState.ACKNOWLEDGED})
# States that wait for a person: an acknowledgement is for them (the Fleet page's "unacknowledged"), and
# the agent forgets an arm holding one only after telemetry.forget_unseen_after_s.
WAITING_STATES = frozenset({AlarmState.ACTIVE, AlarmState.LATCHED})


@dataclass(frozen=True, slots=True)
class Hysteresis:
    """One condition's numbers: raised at or above `raise_at` held `raise_after_s`, cleared at or below
    `clear_at` held `clear_after_s`."""

    raise_at: float
    clear_at: float
    raise_after_s: float
    clear_after_s: float


@dataclass(frozen=True)
class AlarmThresholds:
    """The [alarms] section of the agent config. Defaults from the STS3215's factory settings (see below and
    docs/servo-health.md); every `*_clear_*` value must lie below its raise value."""

    enabled: bool = True
    # SiteWise's latching: an alarm whose condition went away unacknowledged stays LATCHED until acknowledged.
    latch: bool = True
    # Which STS3215 version the arm has ("7.4v" or "12v"): its stall torque converts the model's holding
    # torque into the load percent the servo should report.
    servo_version: str = sts3215.DEFAULT_SERVO_VERSION

    # Temperature: the servo's own protection cuts torque at 70 C (factory Maximum temperature). The warning
    # sits at the top of the datasheet's operating range (60 C), the critical level 5 C before the cut-out.
    temperature_warning_c: float = 60.0
    temperature_warning_clear_c: float = 55.0
    temperature_critical_c: float = sts3215.MAX_TEMPERATURE_C - 5.0
    temperature_critical_clear_c: float = 60.0
    # The register reads whole degrees and moves slowly: a short raise delay filters a one-sample glitch,
    # a long clear delay keeps a servo hovering at the line from flapping.
    temperature_raise_after_s: float = 2.0
    temperature_clear_after_s: float = 10.0

    # Current: the servo trips at 3.25 A (factory Protection current) held 2 s; raise at 80 % of that for
    # half the trip time, so the alarm comes before the servo cuts out.
    # Rounded (to the microampere): a share's float tail (2.1125000000000003) is what `twin config` and the
    # config reference would print as the default.
    current_a: float = round(0.8 * sts3215.PROTECTION_CURRENT_A, 6)
    current_clear_a: float = round(0.65 * sts3215.PROTECTION_CURRENT_A, 6)
    # LeRobot limits the gripper to 1.625 A; same 80 % / 65 % shares.
    gripper_current_a: float = round(0.8 * sts3215.GRIPPER_PROTECTION_CURRENT_A, 6)
    gripper_current_clear_a: float = round(0.65 * sts3215.GRIPPER_PROTECTION_CURRENT_A, 6)
    current_raise_after_s: float = sts3215.OVERCURRENT_PROTECTION_TIME_S / 2.0
    current_clear_after_s: float = 2.0

    # Overload: the servo starts its overload countdown at 80 % load (factory Overload torque) and drops to
    # 20 % torque after 2 s; raise at that load held half the countdown. LeRobot sets the gripper's to 25 %.
    overload_percent: float = sts3215.OVERLOAD_TORQUE_PERCENT
    overload_clear_percent: float = 60.0
    gripper_overload_percent: float = sts3215.GRIPPER_OVERLOAD_TORQUE_PERCENT
    gripper_overload_clear_percent: float = 20.0
    overload_raise_after_s: float = sts3215.OVERLOAD_PROTECTION_TIME_S / 2.0
    overload_clear_after_s: float = 2.0

    # Model mismatch: |measured load| vs |inverse-dynamics holding torque as load| while the joint is still,
    # in percentage points of stall torque. Magnitudes, because the direction bit's sense relative to the
    # model's joint axis depends on how each servo is mounted.
    mismatch_percent: float = 15.0
    mismatch_clear_percent: float = 10.0
    mismatch_raise_after_s: float = 1.0
    mismatch_clear_after_s: float = 2.0
    # Still = the reported velocity and the pose's own rate of change (successive applied angles) both at
    # most this (0.05 rad/s is 33 steps/s, or 3 encoder steps between two messages at 10 Hz), and the
    # servo's Moving flag not set.
    still_velocity_rad_s: float = 0.05
    # The jaw holds no weight worth modelling and grasps by design: it is not checked against the model.
    mismatch_joints: tuple[str, ...] = so101.ARM_JOINTS

    # Servo error: an error bit of the servo's status register (edges that send `status`) among these. The
    # servo sets one only once its own protection acted (after its protection time, e.g. 2 s of overload),
    # so the first reading raises; a clear waits a little, as a bit may blink while the servo recovers.
    servo_error_bits: tuple[str, ...] = sts3215.STATUS_BITS
    servo_error_raise_after_s: float = 0.0
    servo_error_clear_after_s: float = 2.0

    def __post_init__(self) -> None:
        sts3215.servo_version(self.servo_version)  # raises with the choices
        for kind in AlarmKind:
            for joint in (so101.ARM_JOINTS[0], so101.GRIPPER):
                rule = self.rule(kind, joint)
                if not all(math.isfinite(v) for v in dataclasses.astuple(rule)):
                    raise ValueError(f"alarms: the {kind} thresholds must be finite numbers, got {rule}")
                if rule.clear_at >= rule.raise_at:
                    raised, cleared = _rule_keys(kind, joint)
                    raise ValueError(
                        f"alarms: {kind} clears at {rule.clear_at:g} ({cleared}), which is not below where "
                        f"it is raised ({rule.raise_at:g}, {raised}); set {cleared} below {raised} too, so "
                        "the alarm has hysteresis"
                    )
                if rule.raise_after_s < 0 or rule.clear_after_s < 0:
                    name = _DURATION_KEYS[kind]
                    raise ValueError(
                        f"alarms: {name}_raise_after_s ({rule.raise_after_s:g}) and {name}_clear_after_s "
                        f"({rule.clear_after_s:g}) are seconds a value must be held: set each to 0 or more"
                    )
        if self.temperature_warning_c >= self.temperature_critical_c:
            raise ValueError(
                f"alarms: temperature_warning_c ({self.temperature_warning_c:g}) is not below "
                f"temperature_critical_c ({self.temperature_critical_c:g}); the warning must come first, so "
                "set it lower (or the critical level higher, below the servo's own 70 C cut-out)"
            )
        if not self.still_velocity_rad_s >= 0:
            raise ValueError(f"alarms.still_velocity_rad_s must be >= 0, got {self.still_velocity_rad_s}")
        unknown = [j for j in self.mismatch_joints if j not in so101.JOINT_NAMES]
        if unknown:
            raise ValueError(
                f"alarms.mismatch_joints names unknown joints {unknown}; "
                f"choose from {list(so101.JOINT_NAMES)}"
            )
        unknown = [b for b in self.servo_error_bits if b not in sts3215.STATUS_BITS]
        if unknown:
            raise ValueError(
                f"alarms.servo_error_bits names unknown status bits {unknown}; "
                f"choose from {list(sts3215.STATUS_BITS)}"
            )

    @property
    def status_mask(self) -> int:
        """The status register's bits that raise a servo error (servo_error_bits)."""
        return sum(1 << sts3215.STATUS_BITS.index(name) for name in set(self.servo_error_bits))

    @property
    def servo(self) -> sts3215.ServoVersion:
        return sts3215.servo_version(self.servo_version)

    def rule(self, kind: AlarmKind, joint: str) -> Hysteresis:
        """The numbers of one condition for one joint (the gripper has its own current and overload)."""
        grip = joint == so101.GRIPPER
        if kind is AlarmKind.OVER_TEMPERATURE:
            return Hysteresis(
                self.temperature_warning_c,
                self.temperature_warning_clear_c,
                self.temperature_raise_after_s,
                self.temperature_clear_after_s,
            )
        if kind is AlarmKind.OVER_TEMPERATURE_CRITICAL:
            return Hysteresis(
                self.temperature_critical_c,
                self.temperature_critical_clear_c,
                self.temperature_raise_after_s,
                self.temperature_clear_after_s,
            )
        if kind is AlarmKind.OVER_CURRENT:
            return Hysteresis(
                self.gripper_current_a if grip else self.current_a,
                self.gripper_current_clear_a if grip else self.current_clear_a,
                self.current_raise_after_s,
                self.current_clear_after_s,
            )
        if kind is AlarmKind.OVERLOAD:
            return Hysteresis(
                self.gripper_overload_percent if grip else self.overload_percent,
                self.gripper_overload_clear_percent if grip else self.overload_clear_percent,
                self.overload_raise_after_s,
                self.overload_clear_after_s,
            )
        if kind is AlarmKind.SERVO_ERROR:
            # The value is the status's error bits as a number: any set one raises, none clears. Fixed
            # levels, so no key of theirs can undo the hysteresis (_RULE_KEYS has none).
            return Hysteresis(1.0, 0.0, self.servo_error_raise_after_s, self.servo_error_clear_after_s)
        return Hysteresis(
            self.mismatch_percent,
            self.mismatch_clear_percent,
            self.mismatch_raise_after_s,
            self.mismatch_clear_after_s,
        )


class AlarmNotFound(KeyError):  # noqa: N818 - reads as the HTTP answer it becomes (404)
    """No alarm has this id."""


class NothingToAcknowledge(ValueError):  # noqa: N818 - reads as the HTTP answer it becomes (409)
    """The alarm is NORMAL (cleared) or already ACKNOWLEDGED; `state` says which (the 409 carries it)."""

    def __init__(self, message: str, state: str = "") -> None:
        super().__init__(message)
        self.state = state


def alarm_id(device: str, joint: str, kind: AlarmKind | str) -> str:
    """`device/joint/kind`: device ids never hold '/', joint and kind names never do, so it splits back."""
    return f"{device}/{joint}/{kind}"


@dataclass(frozen=True, slots=True)
class AlarmEvent:
    """One state change, for the JSON log line and the counters."""

    alarm_id: str
    device: str
    joint: str
    kind: AlarmKind
    severity: Severity
    previous: AlarmState
    state: AlarmState
    # raised | cleared | acknowledged | reset (LATCHED acknowledged back to NORMAL)
    action: str
    value: float | None
    threshold: float
    at: float
    message: str


@dataclass(frozen=True, slots=True)
class AlarmView:
    """An alarm as /alarms shows it (times are the engine's clock: the agent's monotonic seconds)."""

    alarm_id: str
    device: str
    joint: str
    kind: AlarmKind
    severity: Severity
    state: AlarmState
    value: float | None
    threshold: float
    unit: str
    since: float
    raised: int
    message: str


@dataclass(frozen=True, slots=True)
class AlarmRecord:
    """What an alarm must carry across a restart: its state and whether its condition is present, the times on
    the engine's clock (monotonic seconds). `ServoAlarms.records` exports them, `ServoAlarms.restore` takes
    them back; the agent keeps them over a worker's restart and, for the states a person must see, in its
    state file over its own (service.persist). Not a raise or clear being timed: see `ServoAlarms.restore`."""

    device: str
    joint: str
    kind: AlarmKind
    state: AlarmState
    since: float
    present: bool
    raised: int
    value: float | None = None
    message: str = ""

    @property
    def alarm_id(self) -> str:
        return alarm_id(self.device, self.joint, self.kind)


TorqueSource = Mapping[str, float] | Callable[[], Mapping[str, float]]
# The holding torques of many sources at once, in their order: how a caller that can compute them together
# (the mirror, service.mirror) hands the model check a batch's torques.
TorquesOf = Callable[[Sequence[TorqueSource]], Sequence[Mapping[str, float]]]


# One device's idle alarms (`ServoAlarms.idle`): its id, a mask with the bit of each alarm's cell (joint *
# kinds + kind), and for those raised before, (cell, times raised, when it went NORMAL, its raise message).
IdleRow = tuple[str, int, tuple[tuple[int, int, float, str], ...]]


class _Torques:
    """One pose's holding torques, asked for at most once: the agent passes a function that runs inverse
    dynamics (about 30 us per arm), which only a still joint's model check and a reader of
    `model_load_percent` need; a fleet of moving arms should not pay it per message."""

    __slots__ = ("_source", "_torques")

    def __init__(self, source: TorqueSource) -> None:
        self._source = source
        self._torques: Mapping[str, float] | None = None if callable(source) else source

    def get(self, joint: str) -> float | None:
        torques = self._torques
        if torques is None:
            source = self._source
            torques = self._torques = source() if callable(source) else source
        return torques.get(joint)


class _Unknown(Enum):
    """Not computed yet: a sentinel that, unlike None, is a valid value of no reading."""

    UNKNOWN = 0


_UNKNOWN: Final = _Unknown.UNKNOWN


class JointHealth:
    """What the alarm rules saw for one joint in the last evaluation (for /state, /metrics and the viewer).

    `model_load_percent` (the holding torque as the load the servo should report) is computed when first read,
    unless the model check already needed it. Safe to read from any thread: a race computes the same value."""

    __slots__ = ("_model", "_servo", "_torques", "_voltage", "joint", "mismatch_percent", "still")

    def __init__(
        self,
        *,
        mismatch_percent: float | None,
        still: bool | None,
        model_load_percent: float | _Unknown | None = _UNKNOWN,
        joint: str = "",
        torques: _Torques | None = None,
        servo: sts3215.ServoVersion | None = None,
        voltage_v: float | None = None,
    ) -> None:
        self.mismatch_percent = mismatch_percent  # | |load| - |model load| |, only while the joint is still
        self.still = still
        self.joint = joint
        self._model = model_load_percent
        self._torques = torques
        self._servo = servo
        self._voltage = voltage_v

    @property
    def model_load_percent(self) -> float | None:
        model = self._model
        if model is _UNKNOWN:
            model = self._model = _model_load(self._torques, self._servo, self.joint, self._voltage)
        return model

    def __repr__(self) -> str:
        return (
            f"JointHealth(model_load_percent={self.model_load_percent!r}, "
            f"mismatch_percent={self.mismatch_percent!r}, still={self.still!r})"
        )


def _still(diag: JointDiagnostics, pose_speed: float | None, limit: float) -> bool | None:
    """False on any sign of motion, True on some sign of rest and none of motion, None when nothing is known
    (no velocity, no Moving flag, no previous pose). `limit` is the still speed in rad/s."""
    velocity = diag.velocity_rad_s
    if (
        diag.moving is True
        or (velocity is not None and abs(velocity) > limit)
        or (pose_speed is not None and pose_speed > limit)
    ):
        return False
    if velocity is None and pose_speed is None and diag.moving is None:
        return None
    return True


# One joint's readings for the rules: temperature, current, load, velocity, moving, the status's error bits
# (NaN: not given).
_Reading = tuple[float, float, float, float, float, float]


def _row_readings(
    diagnostics: Mapping[str, JointDiagnostics], status_mask: int
) -> tuple[list[bool], list[_Reading]]:
    """`_fill` for one row, as lists: which joints were given, and their readings (the status as the servo
    error's value, `_error_bits`)."""
    nan = math.nan
    given = [False] * _JOINTS
    readings: list[_Reading] = [(nan, nan, nan, nan, nan, nan)] * _JOINTS
    for joint, diag in diagnostics.items():
        j = _JOINT_INDEX.get(joint)
        if j is not None:
            given[j] = True
            readings[j] = (
                _float(diag.temperature_c),
                _float(diag.current_a),
                _float(diag.load_percent),
                _float(diag.velocity_rad_s),
                nan if diag.moving is None else float(bool(diag.moving)),
                _error_bits(_float(diag.status), status_mask),
            )
    return given, readings


def _model_load(
    torques: _Torques | None, servo: sts3215.ServoVersion | None, joint: str, voltage_v: float | None
) -> float | None:
    torque = None if torques is None else torques.get(joint)
    if torque is None or servo is None:
        return None
    return servo.load_percent(abs(torque), voltage_v)


@dataclass
class AlarmCounters:
    raised: Counter[tuple[AlarmKind, Severity]] = field(default_factory=Counter)
    cleared: Counter[AlarmKind] = field(default_factory=Counter)
    acknowledged: Counter[AlarmKind] = field(default_factory=Counter)


# --- the engine's state: one flat array per field, a row per device ----------------------------------------

# The alarm states as the arrays hold them.
_NORMAL, _ACTIVE, _ACKNOWLEDGED, _LATCHED = 0, 1, 2, 3
_STATES = (AlarmState.NORMAL, AlarmState.ACTIVE, AlarmState.ACKNOWLEDGED, AlarmState.LATCHED)
_CODE = {state: code for code, state in enumerate(_STATES)}
_JOINTS = len(so101.JOINT_NAMES)
_N_KINDS = len(_KINDS)
_KIND_INDEX = {kind: k for k, kind in enumerate(_KINDS)}
# An alarm's cell in a device's row, joint * _N_KINDS + kind: its bit in an IdleRow's mask.
_CELLS = _JOINTS * _N_KINDS
if _CELLS > 64:  # the mask is built in a uint64: a 65th cell would wrap onto the first, silently
    raise RuntimeError(f"{_CELLS} alarm cells per arm do not fit an IdleRow's 64-bit mask")
# A fleet's arrays start with room for this many devices and double when full.
_FIRST_CAPACITY = 64
# Rounds of at most this many messages are evaluated row by row in plain Python (ServoAlarms._evaluate_one):
# the array rules cost a few dozen numpy calls whatever the round's size (about 140 us, and some 6 us a
# message more), which a small fleet's rounds of one or two messages would pay in full. Timed on the mirror
# with 100 arms in rounds of 1 to 16 (docs/performance.md): row by row is cheaper up to 8, arrays at 16.
SMALL_ROUND = 8


def _np() -> Any:
    """numpy, imported on first use (TYPE_CHECKING above says why)."""
    import numpy as np  # noqa: PLC0415

    return np


class _Fleet:
    """Every device's alarms and last evaluation, as arrays with a row per device (ServoAlarms' slots):
    per joint and kind (_KINDS order) whether the alarm exists (its kind has had a value), its state, whether
    its condition is present, its raise and clear timers (NaN: not running), when it last changed, its value
    at the last evaluation and how often it was raised; per joint the last pose (NaN: not given) with its
    edge time, and what the last evaluation saw (speeds, model checks)."""

    def __init__(self, capacity: int) -> None:
        np = _np()
        shape = (capacity, _JOINTS, _N_KINDS)
        self.capacity = capacity
        self.exists = np.zeros(shape, dtype=bool)
        self.state = np.zeros(shape, dtype=np.int8)
        self.present = np.zeros(shape, dtype=bool)
        self.raise_since = np.full(shape, np.nan)
        self.clear_since = np.full(shape, np.nan)
        self.since = np.zeros(shape)
        self.value = np.full(shape, np.nan)
        self.raised = np.zeros(shape, dtype=np.int64)
        self.pose = np.full((capacity, _JOINTS), np.nan)
        self.pose_ms = np.zeros(capacity, dtype=np.int64)
        self.has_pose = np.zeros(capacity, dtype=bool)
        self.speeds = np.full((capacity, _JOINTS), np.nan)
        self.checked = np.zeros((capacity, _JOINTS), dtype=bool)
        self.model = np.full((capacity, _JOINTS), np.nan)
        self.mismatch = np.full((capacity, _JOINTS), np.nan)

    def grown(self) -> _Fleet:
        bigger = _Fleet(self.capacity * 2)
        n = self.capacity
        for name, column in vars(self).items():
            if name != "capacity":
                getattr(bigger, name)[:n] = column
        return bigger


@dataclass
class _Rows:
    """K evaluations at once, each of another device, as arrays (joints in JOINT_NAMES order; NaN: the field
    was not sent, or the joint not given)."""

    slots: Any  # (K,) int64
    diagnostics: Sequence[Mapping[str, JointDiagnostics]]
    torques: list[TorqueSource | _Torques]  # the model check replaces the sources it reads by their torques
    torques_of: TorquesOf | None  # None: each source by itself
    now: Any  # (K,)
    given: Any  # (K, 6) bool: the joint is in the message's diagnostics
    temperature: Any
    current: Any
    load: Any  # signed
    velocity: Any
    voltages: Callable[[list[int]], Any]  # rows -> (len(rows), 6) supply volts, NaN where not sent
    moving: Any  # 1.0 True, 0.0 False, NaN None
    status: Any  # the status register, NaN where not sent
    angles: Any  # (K, 6), NaN where not given
    posed: Any  # (K,) bool: the evaluation came with a pose and its edge time
    stamps: Any  # (K,) int64


def _matrix(rows: Sequence[Sequence[float]], count: int) -> Any:
    """(count, 6) float64 from rows of six floats (through array('d'): numpy reads nested Python sequences
    element by element, several times slower)."""
    flat = array("d")
    for row in rows:
        flat.extend(row)
    return _np().frombuffer(flat, dtype=_np().float64).reshape(count, _JOINTS).copy()


# A mapping's values of every SO-101 joint in JOINT_NAMES order, in one call (KeyError if one is missing).
_EVERY_JOINT = itemgetter(*so101.JOINT_NAMES)


def _float(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _error_bits(status: float, mask: int) -> float:
    """The servo error alarm's value: the status register's bits within `mask` (NaN: no status, or a
    negative one, which no register holds)."""
    return float(int(status) & mask) if status >= 0.0 else math.nan


def _optional(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


class ServoAlarms:
    """Every alarm of every device. Not thread-safe: the agent's worker evaluates, and the HTTP thread's
    acknowledgements go through the service lock like every other read of worker state.

    The state lives in flat arrays with a row per device (`_Fleet`), so `evaluate_batch` runs the rules for
    a round of messages (one per device) in a few array operations instead of a loop per joint and kind in
    Python: a fleet's every applied message is evaluated. Only what is rare runs per item in Python: a model
    check (inverse dynamics), a state change and its event. Those array operations cost the same whatever
    the round's size, so a small round (`small_round`, and `evaluate`) runs the same rules row by row in
    plain Python on the same arrays (`_evaluate_one`); the tests hold the two paths to the same events and
    state."""

    def __init__(self, thresholds: AlarmThresholds | None = None, *, small_round: int = SMALL_ROUND) -> None:
        self.thresholds = thresholds or AlarmThresholds()
        # Rounds up to this size go row by row (SMALL_ROUND); the tests set it to compare the two paths.
        self.small_round = small_round
        self._servo = self.thresholds.servo
        self.counters = AlarmCounters()
        self._rules = {
            joint: {kind: self.thresholds.rule(kind, joint) for kind in AlarmKind}
            for joint in so101.JOINT_NAMES
        }
        self._mismatch_joints = frozenset(self.thresholds.mismatch_joints)
        # The device of each row, and the row of each device.
        self._devices: list[str] = []
        self._slot: dict[str, int] = {}
        self._fleet: _Fleet | None = None  # made on the first evaluation (numpy: see TYPE_CHECKING)
        # A raised alarm's message, by (row, joint, kind).
        self._messages: dict[tuple[int, int, int], str] = {}
        # The last evaluation's diagnostics and holding torques, by row (JointHealth reads them).
        self._last_diagnostics: list[Mapping[str, JointDiagnostics] | None] = []
        self._last_torques: list[TorqueSource | _Torques | None] = []
        self._rule_arrays: tuple[Any, Any, Any, Any, Any] | None = None
        # The same rules as flat lists (joint * kinds + kind) for the row path (floats compare as numpy's).
        self._rule_lists = tuple(
            [getattr(self._rules[joint][kind], name) for joint in so101.JOINT_NAMES for kind in _KINDS]
            for name in ("raise_at", "clear_at", "raise_after_s", "clear_after_s")
        )
        self._check_joints = [joint in self._mismatch_joints for joint in so101.JOINT_NAMES]
        self._status_mask = self.thresholds.status_mask

    # -- rows -----------------------------------------------------------------------------------------------

    def _arrays(self) -> _Fleet:
        fleet = self._fleet
        if fleet is None:
            fleet = self._fleet = _Fleet(_FIRST_CAPACITY)
        return fleet

    def _row(self, device: str) -> int:
        """The device's row, made on its first evaluation."""
        slot = self._slot.get(device)
        if slot is None:
            slot = self._slot[device] = len(self._devices)
            self._devices.append(device)
            self._last_diagnostics.append(None)
            self._last_torques.append(None)
            fleet = self._arrays()
            if slot >= fleet.capacity:
                self._fleet = fleet.grown()
        return slot

    def _rules_as_arrays(self) -> tuple[Any, Any, Any, Any, Any]:
        """(raise_at, clear_at, raise_after_s, clear_after_s) per joint and kind, and the joints the model
        check looks at."""
        arrays = self._rule_arrays
        if arrays is None:
            # The row path's flat lists (joint * kinds + kind), shaped per joint and kind.
            np = _np()
            raise_at, clear_at, raise_after, clear_after = (
                np.array(values).reshape(_JOINTS, _N_KINDS) for values in self._rule_lists
            )
            arrays = self._rule_arrays = (
                raise_at,
                clear_at,
                raise_after,
                clear_after,
                np.array(self._check_joints),
            )
        return arrays

    # -- evaluation -------------------------------------------------------------------------------------

    def evaluate(
        self,
        device: str,
        diagnostics: Mapping[str, JointDiagnostics],
        holding_torques_nm: TorqueSource,
        now: float,
        *,
        angles_rad: Mapping[str, float] | None = None,
        timestamp_ms: int | None = None,
    ) -> list[AlarmEvent]:
        """Feed one applied message; returns the state changes it caused (usually none).

        `angles_rad` and `timestamp_ms` (the applied pose and its edge time) let the model check see motion
        from the pose itself: the edge's mock mode, for one, sends random velocities whatever the arm does.
        `holding_torques_nm` may be a function returning them: it is called only if some joint needs them.
        """
        if not self.thresholds.enabled:
            return []
        pose = None if angles_rad is None else [_float(angles_rad.get(j)) for j in so101.JOINT_NAMES]
        return self._evaluate_one(
            self._row(device),
            diagnostics,
            angles=pose,
            timestamp_ms=timestamp_ms,
            now=now,
            holding_torques_nm=holding_torques_nm,
        )

    def evaluate_batch(
        self,
        devices: Sequence[str],
        diagnostics: Sequence[Mapping[str, JointDiagnostics]],
        *,
        columns: DiagnosticColumns | Callable[[], DiagnosticColumns],
        angles: Sequence[Sequence[float]],
        timestamps_ms: Sequence[int],
        now: Sequence[float],
        holding_torques_nm: Sequence[TorqueSource],
        torques_of: TorquesOf | None = None,
    ) -> list[list[AlarmEvent]]:
        """`evaluate` for many applied messages, each of another device: row k is `devices[k]`, its
        diagnostics (as `columns` row k holds them, where it knows them), its applied pose in JOINT_NAMES
        order with its edge time, its receive time and its holding torques. Returns each message's events,
        as `evaluate` one by one would. `columns` may be a function that makes them: a small round (up to
        `small_round` messages) goes row by row and does not need them. `torques_of`, if given, computes
        the torques of the sources the model check needs all at once (values equal to the sources' own)."""
        count = len(devices)
        if not self.thresholds.enabled:
            return [[] for _ in range(count)]
        if count <= self.small_round:
            return [
                self._evaluate_one(
                    self._row(devices[k]),
                    diagnostics[k],
                    angles=angles[k],
                    timestamp_ms=timestamps_ms[k],
                    now=now[k],
                    holding_torques_nm=holding_torques_nm[k],
                )
                for k in range(count)
            ]
        if callable(columns):
            columns = columns()
        rows = self._rows_of(
            devices,
            diagnostics,
            columns=columns,
            angles=angles,
            timestamps_ms=timestamps_ms,
            now=now,
            holding_torques_nm=holding_torques_nm,
            torques_of=torques_of,
        )
        return self._evaluate(rows)

    def _rows_of(
        self,
        devices: Sequence[str],
        diagnostics: Sequence[Mapping[str, JointDiagnostics]],
        *,
        columns: DiagnosticColumns,
        angles: Sequence[Sequence[float]],
        timestamps_ms: Sequence[int],
        now: Sequence[float],
        holding_torques_nm: Sequence[TorqueSource],
        torques_of: TorquesOf | None,
    ) -> _Rows:
        """`evaluate_batch`'s messages as arrays: the columns, and each row the columns do not know filled
        from its diagnostics."""
        np = _np()
        count = len(devices)
        slots = np.fromiter((self._row(d) for d in devices), dtype=np.int64, count=count)
        known = columns.known
        nan = np.full((count, _JOINTS), np.nan)
        rows = _Rows(
            slots=slots,
            diagnostics=diagnostics,
            torques=list(holding_torques_nm),
            torques_of=torques_of,
            now=np.asarray(now, dtype=np.float64),
            given=np.ones((count, _JOINTS), dtype=bool),
            temperature=columns.temperature_c,
            current=columns.current_a,
            load=columns.load_percent,
            velocity=columns.velocity_rad_s,
            voltages=columns.voltage_v,
            moving=nan,
            status=columns.status,
            angles=_matrix(angles, count),
            posed=np.ones(count, dtype=bool),
            stamps=np.asarray(timestamps_ms, dtype=np.int64),
        )
        if not known.all():
            # What the columns do not hold (a field left out, a Moving flag), from the diagnostics themselves.
            rows.moving = nan.copy()
            for k in np.flatnonzero(~known).tolist():
                rows.given[k] = False
                self._fill(rows, k, diagnostics[k])
        return rows

    @staticmethod
    def _fill(rows: _Rows, k: int, diagnostics: Mapping[str, JointDiagnostics]) -> None:
        """Row k's readings, from its JointDiagnostics (joints the SO-101 does not have are left out)."""
        for joint, diag in diagnostics.items():
            j = _JOINT_INDEX.get(joint)
            if j is None:
                continue
            rows.given[k, j] = True
            rows.temperature[k, j] = _float(diag.temperature_c)
            rows.current[k, j] = _float(diag.current_a)
            rows.load[k, j] = _float(diag.load_percent)
            rows.velocity[k, j] = _float(diag.velocity_rad_s)
            rows.moving[k, j] = math.nan if diag.moving is None else float(bool(diag.moving))
            rows.status[k, j] = _float(diag.status)

    def _evaluate(self, rows: _Rows) -> list[list[AlarmEvent]]:
        """The rules for every row at once (module doc; each row a device of its own), in the steps
        `_evaluate_one` takes for one row, in the same order."""
        np = _np()
        speeds = self._speeds(rows)
        checked, model, mismatch = self._model_check(rows, speeds)
        # The values of each kind, in _KINDS order: temperature twice, current, |load|, model mismatch, the
        # status's error bits (as _error_bits: NaN where not sent or negative).
        status = rows.status
        sent = status >= 0.0
        errors = np.where(sent, np.where(sent, status, 0.0).astype(np.int64) & self._status_mask, np.nan)
        values = np.stack(
            (rows.temperature, rows.temperature, rows.current, np.abs(rows.load), mismatch, errors), axis=2
        )
        raising, clearing = self._timers(rows, values)
        out: list[list[AlarmEvent]] = [[] for _ in range(len(rows.slots))]
        if raising.any() or clearing.any():
            self._changes(rows, (raising, clearing, values, model), out)
        self._record_seen(rows.slots, speeds, checked, model, mismatch)
        last_diagnostics, last_torques = self._last_diagnostics, self._last_torques
        for k, slot in enumerate(rows.slots.tolist()):
            last_diagnostics[slot] = rows.diagnostics[k]
            last_torques[slot] = rows.torques[k]
        return out

    def _speeds(self, rows: _Rows) -> Any:
        """Each joint's speed against the device's last pose (edge clock), only for consecutive-looking
        samples (NaN otherwise); the rows' poses become the devices' last."""
        np = _np()
        fleet = self._arrays()
        slots = rows.slots
        before = fleet.pose[slots]
        dt = (rows.stamps - fleet.pose_ms[slots]) / 1000.0
        timed = rows.posed & fleet.has_pose[slots] & (dt > 0.0) & (dt <= MAX_POSE_GAP_S)
        with np.errstate(divide="ignore", invalid="ignore"):
            speeds = np.abs(rows.angles - before) / np.where(timed, dt, 1.0)[:, None]
        speeds[~timed] = np.nan
        posed = slots[rows.posed]
        fleet.pose[posed] = rows.angles[rows.posed]
        fleet.pose_ms[posed] = rows.stamps[rows.posed]
        fleet.has_pose[posed] = True
        return speeds

    def _model_check(self, rows: _Rows, speeds: Any) -> tuple[Any, Any, Any]:
        """(checked, model load, mismatch) per row and joint: a still joint the model check looks at, with a
        load, against its holding torque from inverse dynamics (computed only for the rows with such a
        joint, together when the caller can: `rows.torques_of`)."""
        np = _np()
        limit = self.thresholds.still_velocity_rad_s
        # Still (as _still): no sign of motion, and some sign of rest.
        # (Comparisons with NaN, the unknown, are false.)
        motion = (rows.moving == 1.0) | (np.abs(rows.velocity) > limit) | (speeds > limit)
        still = ~motion & ~(np.isnan(rows.velocity) & np.isnan(speeds) & np.isnan(rows.moving))
        *_, check_joints = self._rules_as_arrays()
        checked = rows.given & check_joints & still & ~np.isnan(rows.load)
        count = len(rows.slots)
        model = np.full((count, _JOINTS), np.nan)
        mismatch = np.full((count, _JOINTS), np.nan)
        needed = np.flatnonzero(checked.any(axis=1)).tolist()
        servo = self._servo
        if not needed or servo is None:
            return checked, model, mismatch
        sources = rows.torques
        wanted = [sources[k] for k in needed]
        if rows.torques_of is not None:
            found = rows.torques_of(wanted)
        else:
            found = [source() if callable(source) else source for source in wanted]
        held = array("d")
        nan, names = math.nan, so101.JOINT_NAMES
        for k, torques in zip(needed, found, strict=True):
            sources[k] = torques
            try:
                # Computed torques have every joint, each a number: one lookup of all six and one conversion.
                # The row is whole before `held` takes it, so a failure leaves `held` as it was.
                row = array("d", _EVERY_JOINT(torques))
            except (KeyError, TypeError):
                # A joint left out, or None: NaN, as `_float` reads it on the row path.
                get = torques.get
                row = array("d", [_float(get(joint)) for joint in names])
            held.extend(row)
        # The same values as the row path's ServoVersion.load_percent, one joint at a time.
        torque = np.abs(np.frombuffer(held, dtype=np.float64).reshape(len(needed), _JOINTS))
        loads = servo.load_percents(torque, rows.voltages(needed))
        cells = checked[needed] & ~np.isnan(torque)
        model[needed] = np.where(cells, loads, nan)
        mismatch[needed] = np.where(cells, np.abs(np.abs(rows.load[needed]) - loads), nan)
        return checked, model, mismatch

    def _timers(self, rows: _Rows, values: Any) -> tuple[Any, Any]:
        """(raising, clearing) per row, joint and kind: each alarm's raise and clear timers against
        `values`, and the alarms that come to be; the devices' state takes what this round saw."""
        np = _np()
        fleet = self._arrays()
        slots = rows.slots
        raise_at, clear_at, raise_after, clear_after, _ = self._rules_as_arrays()
        given = rows.given[:, :, None]
        exists = fleet.exists[slots]
        created = given & ~exists & ~np.isnan(values)
        now = rows.now[:, None, None]
        if created.any():
            # An alarm comes to be when its kind first has a value (nothing known, nothing to remember).
            exists |= created
            fleet.exists[slots] = exists
            fleet.since[slots] = np.where(created, now, fleet.since[slots])
        evaluated = given & exists

        above = evaluated & (values >= raise_at)
        below = evaluated & (values <= clear_at)
        present = fleet.present[slots]
        # The raise timer runs while the value stays at or above the line and the condition is not yet
        # present; the clear timer while it stays at or below the clear line and the condition is present.
        # Anything else stops both: unknown, or between the lines (hold, and start afresh next time).
        held = fleet.raise_since[slots]
        raise_since = np.where(above & ~present, np.where(np.isnan(held), now, held), np.nan)
        raise_since = np.where(evaluated, raise_since, held)
        held = fleet.clear_since[slots]
        clear_since = np.where(below & present, np.where(np.isnan(held), now, held), np.nan)
        clear_since = np.where(evaluated, clear_since, held)
        raising = above & ~present & (now - raise_since >= raise_after)
        clearing = below & present & (now - clear_since >= clear_after)
        fleet.raise_since[slots] = raise_since
        fleet.clear_since[slots] = clear_since
        fleet.value[slots] = np.where(evaluated, values, fleet.value[slots])
        return raising, clearing

    def _record_seen(self, slots: Any, speeds: Any, checked: Any, model: Any, mismatch: Any) -> None:
        """What an evaluation saw, for JointHealth: rows `slots` (an index or an array of them)."""
        fleet = self._arrays()
        fleet.speeds[slots] = speeds
        fleet.checked[slots] = checked
        fleet.model[slots] = model
        fleet.mismatch[slots] = mismatch

    def _changes(self, rows: _Rows, found: tuple[Any, Any, Any, Any], out: list[list[AlarmEvent]]) -> None:
        """The rows' raises and clears (rare): `_row_changes` of each row that has some."""
        np = _np()
        raising, clearing, values, model = found
        for k in np.flatnonzero((raising | clearing).any(axis=(1, 2))).tolist():
            out[k].extend(
                self._row_changes(
                    int(rows.slots[k]),
                    float(rows.now[k]),
                    rows.diagnostics[k],
                    (raising[k].tolist(), clearing[k].tolist(), values[k].tolist(), model[k].tolist()),
                )
            )

    def _row_changes(
        self,
        slot: int,
        now: float,
        diagnostics: Mapping[str, JointDiagnostics],
        found: tuple[list[list[bool]], list[list[bool]], list[list[float]], list[float]],
    ) -> list[AlarmEvent]:
        """One row's raises and clears ([joint][kind] lists): states, counters, messages and events, in the
        order of its diagnostics' joints, then _KINDS."""
        raising, clearing, values, model = found
        fleet = self._arrays()
        latch = self.thresholds.latch
        out = []
        for joint in diagnostics:
            j = _JOINT_INDEX.get(joint)
            if j is None:
                continue
            for n in range(_N_KINDS):
                kind = _KINDS[n]
                at = (slot, j, n)
                if raising[j][n]:
                    fleet.present[at] = True
                    fleet.raise_since[at] = math.nan
                    fleet.raised[at] += 1
                    rule = self._rules[joint][kind]
                    self._messages[at] = _describe(joint, kind, values[j][n], rule, _optional(model[j]))
                    out.append(self._move(at, _ACTIVE, "raised", now=now))
                    self.counters.raised[(kind, SEVERITY[kind])] += 1
                elif clearing[j][n]:
                    fleet.present[at] = False
                    fleet.clear_since[at] = math.nan
                    self.counters.cleared[kind] += 1
                    latched = fleet.state[at] == _ACTIVE and latch
                    out.append(self._move(at, _LATCHED if latched else _NORMAL, "cleared", now=now))
        return out

    def _evaluate_one(
        self,
        slot: int,
        diagnostics: Mapping[str, JointDiagnostics],
        *,
        angles: Sequence[float] | None,
        timestamp_ms: int | None,
        now: float,
        holding_torques_nm: TorqueSource,
    ) -> list[AlarmEvent]:
        """`_evaluate` for one row, in plain Python on the row's lists: the same rules and the same
        arithmetic (IEEE doubles both; a NaN compares false in both), so the same state and events, for a
        fraction of the array path's fixed cost. `angles` in JOINT_NAMES order (NaN: not given), None
        without a pose. Its steps are `_evaluate`'s, in the same order; a call per step, never per cell."""
        now = float(now)  # as the array path's float64: an event's time is a float whatever was passed
        speeds = self._row_speeds(slot, angles, timestamp_ms)
        given, readings = _row_readings(diagnostics, self._status_mask)
        checked, model, mismatch, torques = self._row_model_check(
            diagnostics, given, readings, speeds, holding_torques_nm
        )
        raising, clearing, values_of = self._row_timers(slot, given, readings, mismatch, now)
        out = []
        if any(raising) or any(clearing):
            by_joint = [slice(j * _N_KINDS, (j + 1) * _N_KINDS) for j in range(_JOINTS)]
            found = (
                [raising[cells_of] for cells_of in by_joint],
                [clearing[cells_of] for cells_of in by_joint],
                [values_of[cells_of] for cells_of in by_joint],
                model,
            )
            out = self._row_changes(slot, now, diagnostics, found)
        self._record_seen(slot, speeds, checked, model, mismatch)
        self._last_diagnostics[slot] = diagnostics
        self._last_torques[slot] = torques
        return out

    def _row_speeds(self, slot: int, angles: Sequence[float] | None, timestamp_ms: int | None) -> list[float]:
        """`_speeds` for one row."""
        fleet = self._arrays()
        speeds = [math.nan] * _JOINTS
        if angles is not None and timestamp_ms is not None:
            dt = (timestamp_ms - int(fleet.pose_ms[slot])) / 1000.0
            if fleet.has_pose[slot] and 0.0 < dt <= MAX_POSE_GAP_S:
                speeds = [abs(a - b) / dt for a, b in zip(angles, fleet.pose[slot].tolist(), strict=True)]
            fleet.pose[slot] = angles
            fleet.pose_ms[slot] = timestamp_ms
            fleet.has_pose[slot] = True
        return speeds

    def _row_model_check(
        self,
        diagnostics: Mapping[str, JointDiagnostics],
        given: list[bool],
        readings: list[_Reading],
        speeds: list[float],
        holding_torques_nm: TorqueSource,
    ) -> tuple[list[bool], list[float], list[float], TorqueSource | _Torques]:
        """`_model_check` for one row, with still (as _still) joint by joint; also the torques, computed
        only if a joint was checked."""
        nan, isnan = math.nan, math.isnan
        limit = self.thresholds.still_velocity_rad_s
        check_joints = self._check_joints
        checked = [False] * _JOINTS
        model = [nan] * _JOINTS
        mismatch = [nan] * _JOINTS
        torques: TorqueSource | _Torques = holding_torques_nm
        for j in range(_JOINTS):
            if not (given[j] and check_joints[j]):
                continue
            _, _, load, velocity, moving, _ = readings[j]
            speed = speeds[j]
            if (
                moving == 1.0
                or abs(velocity) > limit
                or speed > limit
                or (isnan(velocity) and isnan(speed) and isnan(moving))
                or isnan(load)
            ):
                continue
            checked[j] = True
            joint = so101.JOINT_NAMES[j]
            if not isinstance(torques, _Torques):
                torques = _Torques(torques)
            value = _model_load(torques, self._servo, joint, diagnostics[joint].voltage_v)
            if value is not None:
                model[j] = value
                mismatch[j] = abs(abs(load) - value)
        return checked, model, mismatch, torques

    def _row_timers(
        self, slot: int, given: list[bool], readings: list[_Reading], mismatch: list[float], now: float
    ) -> tuple[list[bool], list[bool], list[float]]:
        """`_timers` for one row: (raising, clearing, values) per cell (j * _N_KINDS + n). The row's cells
        are read as flat lists (one numpy call each) and only what changed is written back, but the values,
        which change with nearly every message. The raise and clear timers mirror each other on purpose
        (the same rule, either direction)."""
        fleet = self._arrays()
        nan, isnan = math.nan, math.isnan
        raise_at, clear_at, raise_after, clear_after = self._rule_lists
        cells = _JOINTS * _N_KINDS
        exists = fleet.exists.reshape(-1, cells)[slot].tolist()
        present = fleet.present.reshape(-1, cells)[slot].tolist()
        raise_row = fleet.raise_since.reshape(-1, cells)[slot].tolist()
        clear_row = fleet.clear_since.reshape(-1, cells)[slot].tolist()
        value_view = fleet.value.reshape(-1, cells)
        value_row = value_view[slot].tolist()
        raising = [False] * cells
        clearing = [False] * cells
        values_of = [nan] * cells
        for j in range(_JOINTS):
            if not given[j]:
                continue
            temperature, current, load, _, _, errors = readings[j]
            first = j * _N_KINDS
            cell_values = (temperature, temperature, current, abs(load), mismatch[j], errors)
            values_of[first : first + _N_KINDS] = cell_values
            for n in range(_N_KINDS):
                c = first + n
                value = values_of[c]
                if not exists[c]:
                    if isnan(value):
                        continue
                    # An alarm comes to be when its kind first has a value.
                    fleet.exists[slot, j, n] = True
                    fleet.since[slot, j, n] = now
                value_row[c] = value
                on = present[c]
                since = raise_row[c]
                if value >= raise_at[c] and not on:
                    if isnan(since):
                        since = now
                        fleet.raise_since[slot, j, n] = now
                    raising[c] = now - since >= raise_after[c]
                elif not isnan(since):
                    fleet.raise_since[slot, j, n] = nan
                since = clear_row[c]
                if value <= clear_at[c] and on:
                    if isnan(since):
                        since = now
                        fleet.clear_since[slot, j, n] = now
                    clearing[c] = now - since >= clear_after[c]
                elif not isnan(since):
                    fleet.clear_since[slot, j, n] = nan
        value_view[slot] = value_row
        return raising, clearing, values_of

    def _move(self, at: tuple[int, int, int], state: int, action: str, *, now: float) -> AlarmEvent:
        """Alarm `at` (row, joint, kind) to `state`; its event."""
        fleet = self._arrays()
        slot, j, n = at
        previous = _STATES[int(fleet.state[at])]
        fleet.state[at] = state
        fleet.since[at] = now
        joint, kind = so101.JOINT_NAMES[j], _KINDS[n]
        rule = self._rules[joint][kind]
        new = _STATES[state]
        if action == "raised":
            message = self._messages.get(at, "")
        elif action == "cleared":
            latched = " (latched until acknowledged)" if new is AlarmState.LATCHED else ""
            back = (
                "no error bit set"
                if kind is AlarmKind.SERVO_ERROR
                else f"at or below {rule.clear_at:g} {UNITS[kind]}"
            )
            # The servo as its raise named it: the person who went to the arm finds the same motor id.
            message = (
                f"{so101.servo_name(joint)} {kind} cleared: {back} for {rule.clear_after_s:g} s{latched}"
            )
        else:
            message = f"{so101.servo_name(joint)} {kind} {action} by a person"
        device = self._devices[slot]
        return AlarmEvent(
            alarm_id=device + _ID_SUFFIX[joint, kind],
            device=device,
            joint=joint,
            kind=kind,
            severity=SEVERITY[kind],
            previous=previous,
            state=new,
            action=action,
            value=_optional(float(fleet.value[at])),
            threshold=rule.raise_at if action == "raised" else rule.clear_at,
            at=now,
            message=message,
        )

    # -- restarts -------------------------------------------------------------------------------------------

    def records(self, *, devices: Iterable[str] | None = None) -> list[AlarmRecord]:
        """Every alarm that is not NORMAL or whose condition is present (`idle` gives the others), of
        `devices` or of all."""
        fleet = self._fleet
        if fleet is None:
            return []
        wanted = None if devices is None else set(devices)
        np = _np()
        keep = self._recorded(fleet, len(self._devices))
        out = []
        for slot, j, n in np.argwhere(keep).tolist():
            at = (slot, j, n)
            device = self._devices[slot]
            if wanted is not None and device not in wanted:
                continue
            state, present = int(fleet.state[at]), bool(fleet.present[at])
            out.append(
                AlarmRecord(
                    device=device,
                    joint=so101.JOINT_NAMES[j],
                    kind=_KINDS[n],
                    state=_STATES[state],
                    since=float(fleet.since[at]),
                    present=present,
                    raised=int(fleet.raised[at]),
                    value=_optional(float(fleet.value[at])),
                    message=self._messages.get(at, ""),
                )
            )
        return out

    def restore(self, records: Iterable[AlarmRecord]) -> int:
        """Take back alarms `records` exported (after a restart, before any message of their devices): each
        replaces what the engine has for its id. Records of joints or kinds this engine does not know are
        skipped. Returns how many were restored.

        A raise or clear being timed is not taken back: its timer starts again at the alarm's first reading
        after the restart. A timer holds only while every reading keeps it running, and the readings between
        the checkpoint and that one were never checked: a restarted worker takes the messages since as a
        backlog and catches up on it (service.mirror), evaluating each arm's newest only. A model check's
        raise timer, started by one still reading among moving ones (each of which resets it), completed on
        that first reading raised a false model_mismatch on every arm of the worker at once."""
        restored = 0
        for record in records:
            j = _JOINT_INDEX.get(record.joint)
            n = _KIND_INDEX.get(record.kind)
            if j is None or n is None:
                continue
            slot = self._row(record.device)
            fleet = self._arrays()  # after _row: it may have grown the arrays
            at = (slot, j, n)
            fleet.exists[at] = True
            fleet.state[at] = _CODE[record.state]
            fleet.since[at] = record.since
            fleet.present[at] = record.present
            fleet.raised[at] = record.raised
            fleet.value[at] = _float(record.value)
            fleet.raise_since[at] = math.nan
            fleet.clear_since[at] = math.nan
            if record.message:
                self._messages[at] = record.message
            else:
                self._messages.pop(at, None)
            restored += 1
        return restored

    @staticmethod
    def _recorded(fleet: _Fleet, rows: int) -> Any:
        """Which of the first `rows` devices' alarms `records` gives (not NORMAL, or condition present), as a
        boolean array. Selected with the arrays: the agent checkpoints every mirror each second, and a walk
        over every alarm of a 1,000-arm fleet (30,000) held the worker for 40-80 ms (docs/performance.md)."""
        return fleet.exists[:rows] & ((fleet.state[:rows] != _NORMAL) | fleet.present[:rows])

    def idle(self) -> list[IdleRow]:
        """The alarms `records` leaves out (NORMAL, condition absent), by device (IdleRow):
        a worker's checkpoint carries them, so a restarted worker still counts them in NORMAL and still
        knows how often each was raised. Picked out with the arrays, a few ints per arm: every second's
        checkpoint of a 1,000-arm fleet would pay for 36,000 records."""
        fleet = self._fleet
        if fleet is None:
            return []
        np = _np()
        rows = len(self._devices)
        idle = fleet.exists[:rows] & ~self._recorded(fleet, rows)
        bits = idle.reshape(rows, _CELLS).astype(np.uint64) << np.arange(_CELLS, dtype=np.uint64)
        masks = bits.sum(axis=1).tolist()  # distinct powers of two: the sum is the mask
        raised: dict[int, list[tuple[int, int, float, str]]] = {}
        for slot, j, n in np.argwhere(idle & (fleet.raised[:rows] > 0)).tolist():
            at = (slot, j, n)
            cell = (int(fleet.raised[at]), float(fleet.since[at]), self._messages.get(at, ""))
            raised.setdefault(slot, []).append((j * _N_KINDS + n, *cell))
        return [
            (self._devices[slot], mask, tuple(raised.get(slot, ())))
            for slot, mask in enumerate(masks)
            if mask
        ]

    def restore_idle(self, rows: Iterable[IdleRow], since: float) -> None:
        """Take back the alarms `idle` exported (a restarted worker, before any message), as NORMAL, since
        `since` unless their row says when they went NORMAL (cleared, or reset by an acknowledgement); an
        alarm the engine already has stays as it is."""
        for device, mask, raised in rows:
            slot = self._row(device)
            fleet = self._arrays()  # after _row: it may have grown the arrays
            counts = {cell: (times, cleared, message) for cell, times, cleared, message in raised}
            for cell in range(_CELLS):
                at = (slot, cell // _N_KINDS, cell % _N_KINDS)
                if not mask >> cell & 1 or fleet.exists[at]:
                    continue
                times, cleared, message = counts.get(cell, (0, since, ""))
                fleet.exists[at] = True
                fleet.state[at] = _NORMAL
                fleet.since[at] = cleared
                fleet.raised[at] = times
                if message:
                    self._messages[at] = message

    def restore_counters(self, counters: AlarmCounters) -> None:
        """Add `counters` (a previous run's totals) to this engine's."""
        self.counters.raised.update(counters.raised)
        self.counters.cleared.update(counters.cleared)
        self.counters.acknowledged.update(counters.acknowledged)

    # -- people ---------------------------------------------------------------------------------------------

    def forget(self, device: str) -> Counter[AlarmState]:
        """Remove every alarm of `device` (any state) and its last evaluation: an arm retired by an operator.
        Returns how many of its alarms were in each state other than NORMAL. Its row goes to the last
        device's (the rows stay dense, as every array operation takes the first len(_devices)); a later
        message of the device makes a fresh row. The counters (raised, cleared, acknowledged) stay: they are
        the engine's totals since start, not the arm's."""
        removed: Counter[AlarmState] = Counter()
        slot = self._slot.pop(device, None)
        if slot is None:
            return removed
        fleet = self._arrays()
        for code in fleet.state[slot][fleet.exists[slot]].tolist():
            if code != _NORMAL:
                removed[_STATES[code]] += 1
        last = len(self._devices) - 1
        messages = {at: text for at, text in self._messages.items() if at[0] not in (slot, last)}
        if slot != last:
            moved = self._devices[last]
            self._devices[slot] = moved
            self._slot[moved] = slot
            self._last_diagnostics[slot] = self._last_diagnostics[last]
            self._last_torques[slot] = self._last_torques[last]
            for name, column in vars(fleet).items():
                if name != "capacity":
                    column[slot] = column[last]
            messages.update({(slot, j, n): text for (s, j, n), text in self._messages.items() if s == last})
        self._messages = messages
        # The freed last row as a new row starts (a device that arrives next takes it).
        blank = _Fleet(1)
        for name, column in vars(fleet).items():
            if name != "capacity":
                column[last] = getattr(blank, name)[0]
        del self._devices[last], self._last_diagnostics[last], self._last_torques[last]
        return removed

    def _find(self, alarm_id_: str) -> tuple[int, int, int] | None:
        device, _, rest = alarm_id_.partition("/")
        joint, _, kind_name = rest.partition("/")
        slot = self._slot.get(device)
        j = _JOINT_INDEX.get(joint)
        try:
            n = _KIND_INDEX[AlarmKind(kind_name)]
        except ValueError:
            return None
        if slot is None or j is None or self._fleet is None or not self._fleet.exists[slot, j, n]:
            return None
        return (slot, j, n)

    def acknowledge(self, alarm_id_: str, now: float) -> AlarmEvent:
        """ACTIVE -> ACKNOWLEDGED, LATCHED -> NORMAL (SiteWise's acknowledge and reset in one verb).

        Raises AlarmNotFound for an unknown id and NothingToAcknowledge for a NORMAL or ACKNOWLEDGED alarm.
        """
        at = self._find(alarm_id_)
        if at is None:
            raise AlarmNotFound(alarm_id_)
        state = int(self._arrays().state[at])
        if state == _ACTIVE:
            target, action = _ACKNOWLEDGED, "acknowledged"
        elif state == _LATCHED:
            target, action = _NORMAL, "reset"
        else:
            # NORMAL is not "acknowledged already": the alarm has cleared (and a non-latching one may never
            # have been acknowledged), which is what the person who clicked needs to read.
            why = (
                "is NORMAL, already cleared: nothing waits to be acknowledged"
                if state == _NORMAL
                else f"is {_STATES[state]}: only ACTIVE or LATCHED alarms can be acknowledged"
            )
            raise NothingToAcknowledge(f"alarm {alarm_id_} {why}", str(_STATES[state]))
        event = self._move(at, target, action, now=now)
        self.counters.acknowledged[_KINDS[at[2]]] += 1
        return event

    # -- views ----------------------------------------------------------------------------------------------

    def get(self, alarm_id_: str) -> AlarmView | None:
        at = self._find(alarm_id_)
        return None if at is None else self._view(at)

    def views_of(self, alarm_ids: Iterable[str]) -> list[AlarmView]:
        """The named alarms; raises AlarmNotFound for an unknown id."""
        out = []
        for key in alarm_ids:
            at = self._find(key)
            if at is None:
                raise AlarmNotFound(key)
            out.append(self._view(at))
        return out

    def _existing(self, device: str | None = None, *, normal: bool = True) -> list[tuple[int, int, int]]:
        """(row, joint, kind) of every alarm that exists, of one device or all; without `normal`, only those
        that are not NORMAL (picked out by numpy: at a large fleet nearly all are NORMAL, and a Python test of
        each cost a console tick tenths of a second under the mirror's lock)."""
        fleet = self._fleet
        if fleet is None:
            return []
        np = _np()
        if device is None:
            rows = len(self._devices)
            exists = fleet.exists[:rows]
            if not normal:
                exists = exists & (fleet.state[:rows] != _NORMAL)
            return [(int(s), int(j), int(n)) for s, j, n in np.argwhere(exists).tolist()]
        slot = self._slot.get(device)
        if slot is None:
            return []
        exists = fleet.exists[slot]
        if not normal:
            exists = exists & (fleet.state[slot] != _NORMAL)
        return [(slot, int(j), int(n)) for j, n in np.argwhere(exists).tolist()]

    def views(self, *, include_normal: bool = False, device: str | None = None) -> list[AlarmView]:
        """Alarms sorted worst first (severity, then state, then id); NORMAL ones only when asked."""
        out = [self._view(at) for at in self._existing(device, normal=include_normal)]
        out.sort(key=lambda v: worst_first(v.severity, v.state, v.alarm_id))
        return out

    def _view(self, at: tuple[int, int, int]) -> AlarmView:
        fleet = self._arrays()
        slot, j, n = at
        joint, kind = so101.JOINT_NAMES[j], _KINDS[n]
        device = self._devices[slot]
        return AlarmView(
            alarm_id=device + _ID_SUFFIX[joint, kind],
            device=device,
            joint=joint,
            kind=kind,
            severity=SEVERITY[kind],
            state=_STATES[int(fleet.state[at])],
            value=self._value_of(at),
            threshold=self._rules[joint][kind].raise_at,
            unit=UNITS[kind],
            since=float(fleet.since[at]),
            raised=int(fleet.raised[at]),
            message=self._messages.get(at, ""),
        )

    def _value_of(self, at: tuple[int, int, int]) -> float | None:
        """The alarm's value at the device's last evaluation."""
        fleet = self._arrays()
        slot, j, n = at
        diagnostics = self._last_diagnostics[slot]
        diag = None if diagnostics is None else diagnostics.get(so101.JOINT_NAMES[j])
        if diag is None:
            return _optional(float(fleet.value[at]))  # not in the last message: what it had when last seen
        kind = _KINDS[n]
        if kind is AlarmKind.OVER_TEMPERATURE or kind is AlarmKind.OVER_TEMPERATURE_CRITICAL:
            return diag.temperature_c
        if kind is AlarmKind.OVER_CURRENT:
            return diag.current_a
        if kind is AlarmKind.OVERLOAD:
            return None if diag.load_percent is None else abs(diag.load_percent)
        if kind is AlarmKind.SERVO_ERROR:
            return _optional(_error_bits(_float(diag.status), self._status_mask))
        return _optional(float(fleet.mismatch[slot, j])) if fleet.checked[slot, j] else None

    def joint_health(self, device: str) -> dict[str, JointHealth]:
        slot = self._slot.get(device)
        diagnostics = None if slot is None else self._last_diagnostics[slot]
        if slot is None or diagnostics is None:
            return {}
        fleet = self._arrays()
        limit = self.thresholds.still_velocity_rad_s
        out = {}
        for joint, diag in diagnostics.items():
            j = _JOINT_INDEX.get(joint)
            if j is None:
                continue
            if fleet.checked[slot, j]:
                out[joint] = JointHealth(
                    model_load_percent=_optional(float(fleet.model[slot, j])),
                    mismatch_percent=_optional(float(fleet.mismatch[slot, j])),
                    still=True,
                )
                continue
            out[joint] = JointHealth(
                mismatch_percent=None,
                still=_still(diag, _optional(float(fleet.speeds[slot, j])), limit),
                joint=joint,
                torques=self._torques_of(slot),
                servo=self._servo,
                voltage_v=diag.voltage_v,
            )
        return out

    def _torques_of(self, slot: int) -> _Torques | None:
        """The holding torques of the row's last evaluation, asked for at most once from now on."""
        source = self._last_torques[slot]
        if source is None or isinstance(source, _Torques):
            return source
        torques = self._last_torques[slot] = _Torques(source)
        return torques

    def worst_by_device(self) -> dict[str, dict[str, tuple[Severity, AlarmState]]]:
        """`worst_by_joint` of every device with an alarm that is not NORMAL, from one pass over the arrays
        (a report of the fleet asked each device's with numpy calls of its own)."""
        fleet = self._fleet
        if fleet is None:
            return {}
        rows = len(self._devices)
        states = fleet.state[:rows]
        found = _np().argwhere(fleet.exists[:rows] & (states != _NORMAL))
        out: dict[str, dict[str, tuple[Severity, AlarmState]]] = {}
        for (slot, j, n), state in zip(found.tolist(), states[tuple(found.T)].tolist(), strict=True):
            worst = out.setdefault(self._devices[slot], {})
            joint = so101.JOINT_NAMES[j]
            candidate = (SEVERITY[_KINDS[n]], _STATES[state])
            current = worst.get(joint)
            if current is None or _worse(candidate, current):
                worst[joint] = candidate
        return out

    def worst_by_joint(self, device: str) -> dict[str, tuple[Severity, AlarmState]]:
        """Per joint, the severity and state of its worst alarm that is not NORMAL (the viewer's colour)."""
        fleet = self._fleet
        worst: dict[str, tuple[Severity, AlarmState]] = {}
        for at in self._existing(device, normal=False):
            assert fleet is not None
            state = _STATES[int(fleet.state[at])]
            joint = so101.JOINT_NAMES[at[1]]
            candidate = (SEVERITY[_KINDS[at[2]]], state)
            current = worst.get(joint)
            if current is None or _worse(candidate, current):
                worst[joint] = candidate
        return worst

    def counts_by_state(self) -> Counter[tuple[Severity, AlarmState]]:
        fleet = self._fleet
        counts: Counter[tuple[Severity, AlarmState]] = Counter()
        if fleet is None:
            return counts
        np = _np()
        rows = len(self._devices)
        exists, state = fleet.exists[:rows], fleet.state[:rows]
        for n, kind in enumerate(_KINDS):
            codes = state[:, :, n][exists[:, :, n]]
            for code, count in enumerate(np.bincount(codes, minlength=len(_STATES)).tolist()):
                if count:
                    counts[(SEVERITY[kind], _STATES[code])] += count
        return counts

    def present_by_severity(self, devices: Iterable[str] | None = None) -> dict[Severity, int]:
        """How many alarms have their condition present (ACTIVE or ACKNOWLEDGED), by severity."""
        out = dict.fromkeys(Severity, 0)
        fleet = self._fleet
        if fleet is None:
            return out
        if devices is None:
            rows: Any = slice(0, len(self._devices))
        else:
            rows = [self._slot[d] for d in set(devices) if d in self._slot]
        exists, state = fleet.exists[rows], fleet.state[rows]
        condition = exists & ((state == _ACTIVE) | (state == _ACKNOWLEDGED))
        for n, kind in enumerate(_KINDS):
            out[SEVERITY[kind]] += int(condition[..., n].sum())
        return out


# ACTIVE needs a person most, then LATCHED (gone but unseen), then ACKNOWLEDGED (someone is on it).
_STATE_ORDER = {
    AlarmState.ACTIVE: 0,
    AlarmState.LATCHED: 1,
    AlarmState.ACKNOWLEDGED: 2,
    AlarmState.NORMAL: 3,
}


def record_view(record: AlarmRecord, thresholds: AlarmThresholds) -> AlarmView:
    """An alarm as a checkpoint keeps it, as /alarms shows it: what a worker being started again still has
    to show. Its value is the one it had at its device's last evaluation before the checkpoint."""
    return AlarmView(
        alarm_id=record.alarm_id,
        device=record.device,
        joint=record.joint,
        kind=record.kind,
        severity=SEVERITY[record.kind],
        state=record.state,
        value=record.value,
        threshold=thresholds.rule(record.kind, record.joint).raise_at,
        unit=UNITS[record.kind],
        since=record.since,
        raised=record.raised,
        message=record.message,
    )


def worst_first(severity: Severity | str, state: AlarmState | str, alarm_id: str) -> tuple[int, int, str]:
    """The sort key of every list of alarms: critical before warning, then ACTIVE, LATCHED, ACKNOWLEDGED,
    NORMAL, then by id. Takes the enums or their values (an AlarmInfo carries strings)."""
    return (-Severity(severity).rank, _STATE_ORDER[AlarmState(state)], alarm_id)


def _worse(a: tuple[Severity, AlarmState], b: tuple[Severity, AlarmState]) -> bool:
    return (a[0].rank, -_STATE_ORDER[a[1]]) > (b[0].rank, -_STATE_ORDER[b[1]])


# Each kind's `[alarms]` keys of its raise and clear values (the gripper's current and overload have their
# own, with a `gripper_` prefix), as AlarmThresholds.rule reads them.
_RULE_KEYS: dict[AlarmKind, tuple[str, str]] = {
    AlarmKind.OVER_TEMPERATURE: ("temperature_warning_c", "temperature_warning_clear_c"),
    AlarmKind.OVER_TEMPERATURE_CRITICAL: ("temperature_critical_c", "temperature_critical_clear_c"),
    AlarmKind.OVER_CURRENT: ("current_a", "current_clear_a"),
    AlarmKind.OVERLOAD: ("overload_percent", "overload_clear_percent"),
    AlarmKind.MODEL_MISMATCH: ("mismatch_percent", "mismatch_clear_percent"),
}


# The prefix of each kind's `*_raise_after_s` and `*_clear_after_s` keys.
_DURATION_KEYS: dict[AlarmKind, str] = {
    AlarmKind.OVER_TEMPERATURE: "temperature",
    AlarmKind.OVER_TEMPERATURE_CRITICAL: "temperature",
    AlarmKind.OVER_CURRENT: "current",
    AlarmKind.OVERLOAD: "overload",
    AlarmKind.MODEL_MISMATCH: "mismatch",
    AlarmKind.SERVO_ERROR: "servo_error",
}


def _rule_keys(kind: AlarmKind, joint: str) -> tuple[str, str]:
    """The keys of one joint's rule, so an error about it names what to change."""
    raised, cleared = _RULE_KEYS[kind]
    if joint == so101.GRIPPER and kind in (AlarmKind.OVER_CURRENT, AlarmKind.OVERLOAD):
        return f"gripper_{raised}", f"gripper_{cleared}"
    return raised, cleared


def _describe(joint: str, kind: AlarmKind, value: float, rule: Hysteresis, model: float | None) -> str:
    servo = so101.servo_name(joint)
    if kind is AlarmKind.OVER_TEMPERATURE:
        return f"{servo} at {value:.0f} C (warning at {rule.raise_at:g} C; the servo cuts out at 70 C)"
    if kind is AlarmKind.OVER_TEMPERATURE_CRITICAL:
        return f"{servo} at {value:.0f} C, near the 70 C cut-out (critical at {rule.raise_at:g} C)"
    if kind is AlarmKind.OVER_CURRENT:
        return f"{servo} draws {value:.2f} A (alarm at {rule.raise_at:.2f} A)"
    if kind is AlarmKind.OVERLOAD:
        return (
            f"{servo} load {value:.1f} % of stall torque held over {rule.raise_after_s:g} s "
            f"(alarm at {rule.raise_at:g} %)"
        )
    if kind is AlarmKind.SERVO_ERROR:
        bits = int(value)
        # "(status bits N)": what a LATCHED error's advice is for (`_raised_bits`).
        return (
            f"{servo} reports an error of its own: {', '.join(sts3215.status_names(bits))} (status bits "
            f"{bits}); its protection acted and may have cut or limited its torque"
        )
    return (
        f"{servo} load differs from the model's holding load ({model or 0.0:.1f} %) by {value:.1f} points "
        f"while still (alarm at {rule.raise_at:g}): contact, a payload or a failing servo"
    )
