"""Servo alarms: over-temperature, over-current, sustained overload and model mismatch, per joint of each arm.

Pure and I/O free, with the time passed in (the agent's monotonic receive time), so every rule is tested
without sleeping. The worker calls `ServoAlarms.evaluate` for each applied message; people acknowledge
through the HTTP API (`acknowledge`).

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
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from typing import TYPE_CHECKING, Final

from twin.robot import so101, sts3215

if TYPE_CHECKING:
    # Annotations only: the config loads the alarm thresholds from here, and `twin --help` must not need the
    # decoder's msgspec (tests/infra/test_userdata.py installs the package without its dependencies).
    from twin.core.telemetry import JointDiagnostics


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


SEVERITY: dict[AlarmKind, Severity] = {
    AlarmKind.OVER_TEMPERATURE: Severity.WARNING,
    AlarmKind.OVER_TEMPERATURE_CRITICAL: Severity.CRITICAL,
    AlarmKind.OVER_CURRENT: Severity.CRITICAL,
    AlarmKind.OVERLOAD: Severity.WARNING,
    AlarmKind.MODEL_MISMATCH: Severity.WARNING,
}
UNITS: dict[AlarmKind, str] = {
    AlarmKind.OVER_TEMPERATURE: "C",
    AlarmKind.OVER_TEMPERATURE_CRITICAL: "C",
    AlarmKind.OVER_CURRENT: "A",
    AlarmKind.OVERLOAD: "%",
    AlarmKind.MODEL_MISMATCH: "% points",
}
# The order evaluate() feeds values in: temperature (twice), current, |load|, model mismatch.
_KINDS: tuple[AlarmKind, ...] = (
    AlarmKind.OVER_TEMPERATURE,
    AlarmKind.OVER_TEMPERATURE_CRITICAL,
    AlarmKind.OVER_CURRENT,
    AlarmKind.OVERLOAD,
    AlarmKind.MODEL_MISMATCH,
)
_JOINT_SET = frozenset(so101.JOINT_NAMES)
# What follows the device in an alarm id (`alarm_id`), per joint and kind.
_ID_SUFFIX = {(joint, kind): f"/{joint}/{kind.value}" for joint in so101.JOINT_NAMES for kind in AlarmKind}
# Poses further apart than this (edge clock) say nothing about the speed between them.
MAX_POSE_GAP_S = 1.0
# States in which the condition is present; LATCHED is remembered, not present.
CONDITION_PRESENT = frozenset({AlarmState.ACTIVE, AlarmState.ACKNOWLEDGED})


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
    current_a: float = 0.8 * sts3215.PROTECTION_CURRENT_A
    current_clear_a: float = 0.65 * sts3215.PROTECTION_CURRENT_A
    # LeRobot limits the gripper to 1.625 A; same 80 % / 65 % shares.
    gripper_current_a: float = 0.8 * sts3215.GRIPPER_PROTECTION_CURRENT_A
    gripper_current_clear_a: float = 0.65 * sts3215.GRIPPER_PROTECTION_CURRENT_A
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

    def __post_init__(self) -> None:
        sts3215.servo_version(self.servo_version)  # raises with the choices
        for kind in AlarmKind:
            for joint in (so101.ARM_JOINTS[0], so101.GRIPPER):
                rule = self.rule(kind, joint)
                if not all(math.isfinite(v) for v in dataclasses.astuple(rule)):
                    raise ValueError(f"alarms: the {kind} thresholds must be finite numbers, got {rule}")
                if rule.clear_at >= rule.raise_at:
                    raise ValueError(
                        f"alarms: {kind} clears at {rule.clear_at:g}, which is not below where it is raised "
                        f"({rule.raise_at:g}); the clear value must be lower so the alarm has hysteresis"
                    )
                if rule.raise_after_s < 0 or rule.clear_after_s < 0:
                    raise ValueError(f"alarms: {kind} durations must be >= 0 seconds, got {rule}")
        if not self.still_velocity_rad_s >= 0:
            raise ValueError(f"alarms.still_velocity_rad_s must be >= 0, got {self.still_velocity_rad_s}")
        unknown = [j for j in self.mismatch_joints if j not in so101.JOINT_NAMES]
        if unknown:
            raise ValueError(
                f"alarms.mismatch_joints names unknown joints {unknown}; "
                f"choose from {list(so101.JOINT_NAMES)}"
            )

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
        return Hysteresis(
            self.mismatch_percent,
            self.mismatch_clear_percent,
            self.mismatch_raise_after_s,
            self.mismatch_clear_after_s,
        )


class AlarmNotFound(KeyError):  # noqa: N818 - reads as the HTTP answer it becomes (404)
    """No alarm has this id."""


class NothingToAcknowledge(ValueError):  # noqa: N818 - reads as the HTTP answer it becomes (409)
    """The alarm is NORMAL or already ACKNOWLEDGED."""


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


@dataclass(slots=True)
class _Alarm:
    device: str
    joint: str
    kind: AlarmKind
    state: AlarmState = AlarmState.NORMAL
    since: float = 0.0
    value: float | None = None
    present: bool = False  # the debounced condition
    raise_since: float | None = None
    clear_since: float | None = None
    raised: int = 0
    message: str = ""

    @property
    def alarm_id(self) -> str:
        return alarm_id(self.device, self.joint, self.kind)


@dataclass(frozen=True, slots=True)
class AlarmRecord:
    """What an alarm must carry across a restart: its state and the condition's debounce, the times on the
    engine's clock (monotonic seconds). `ServoAlarms.records` exports them, `ServoAlarms.restore` takes them
    back; the agent keeps them over a worker's restart and, for the states a person must see, in its state
    file over its own (service.persist)."""

    device: str
    joint: str
    kind: AlarmKind
    state: AlarmState
    since: float
    present: bool
    raised: int
    value: float | None = None
    message: str = ""
    raise_since: float | None = None
    clear_since: float | None = None

    @property
    def alarm_id(self) -> str:
        return alarm_id(self.device, self.joint, self.kind)


class _JointAlarms:
    """One joint's alarms, one slot per kind in _KINDS order (None until the kind first has a value), and
    whether all of them are idle: not present and no raise timer running."""

    __slots__ = ("alarms", "idle")

    def __init__(self, alarms: list[_Alarm | None]) -> None:
        self.alarms = alarms
        self.idle = False  # the first evaluation takes the full path


TorqueSource = Mapping[str, float] | Callable[[], Mapping[str, float]]


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


@dataclass(frozen=True, slots=True)
class _Evaluation:
    """What one evaluation of a device saw, kept until the next: its JointHealth, built when first read."""

    diagnostics: Mapping[str, JointDiagnostics]
    speeds: Mapping[str, float]
    torques: _Torques
    checked: Mapping[str, tuple[float | None, float | None]]

    def joint_health(
        self, thresholds: AlarmThresholds, servo: sts3215.ServoVersion
    ) -> dict[str, JointHealth]:
        out = {}
        for joint, diag in self.diagnostics.items():
            if joint not in _JOINT_SET:
                continue
            model_check = self.checked.get(joint)
            if model_check is not None:
                model, mismatch = model_check
                out[joint] = JointHealth(model_load_percent=model, mismatch_percent=mismatch, still=True)
                continue
            out[joint] = JointHealth(
                mismatch_percent=None,
                still=_still(diag, self.speeds.get(joint), thresholds.still_velocity_rad_s),
                joint=joint,
                torques=self.torques,
                servo=servo,
                voltage_v=diag.voltage_v,
            )
        return out


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


class ServoAlarms:
    """Every alarm of every device. Not thread-safe: the agent's worker evaluates, and the HTTP thread's
    acknowledgements go through the service lock like every other read of worker state."""

    def __init__(self, thresholds: AlarmThresholds | None = None) -> None:
        self.thresholds = thresholds or AlarmThresholds()
        self._servo = self.thresholds.servo
        self._alarms: dict[str, _Alarm] = {}
        # What the last evaluation of each device saw; its JointHealth is built from it when read, since
        # six objects per applied message would cost the fleet more than every reader of /state together.
        self._last: dict[str, _Evaluation] = {}
        self._last_pose: dict[str, tuple[int, Mapping[str, float]]] = {}
        # Each device's alarms, for the per-device readers (worst_by_joint, views(device=...)): scanning every
        # alarm of the fleet per device made a fleet's /state quadratic in its size.
        self._by_device: dict[str, list[_Alarm]] = {}
        self.counters = AlarmCounters()
        # Per device, per joint, one slot per kind (in _KINDS order): evaluate runs for every applied
        # message, so it indexes lists instead of formatting ids.
        self._slots: dict[str, dict[str, _JointAlarms]] = {}
        # Rules resolved once per joint, and each joint's raise lines in _KINDS order with the lower of the
        # two temperature lines first (the quiet check compares a temperature once).
        self._rule_list = {
            joint: [self.thresholds.rule(kind, joint) for kind in _KINDS] for joint in so101.JOINT_NAMES
        }
        self._raise_at = {joint: tuple(r.raise_at for r in rules) for joint, rules in self._rule_list.items()}
        self._quiet = {
            joint: (min(raise_at[0], raise_at[1]), *raise_at[1:])
            for joint, raise_at in self._raise_at.items()
        }
        self._rules = {
            joint: {kind: self.thresholds.rule(kind, joint) for kind in AlarmKind}
            for joint in so101.JOINT_NAMES
        }
        self._mismatch_joints = frozenset(self.thresholds.mismatch_joints)

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
        speeds = self._pose_speeds(device, angles_rad, timestamp_ms)
        events: list[AlarmEvent] = []
        slots_of = self._slots.get(device)
        if slots_of is None:
            slots_of = self._slots[device] = {}
        torques = _Torques(holding_torques_nm)
        mismatch_joints = self._mismatch_joints
        # Joints whose model check ran (still, load known): (model load %, mismatch) for their JointHealth.
        checked: dict[str, tuple[float | None, float | None]] = {}
        for joint, diag in diagnostics.items():
            if joint not in self._rule_list:
                continue
            load = diag.load_percent
            model = mismatch = None
            if joint in mismatch_joints and load is not None:
                model, mismatch = self._model_check(
                    joint, diag, load, pose_speed=speeds.get(joint), torques=torques, checked=checked
                )
            temp = diag.temperature_c
            current = diag.current_a
            slots = slots_of.get(joint)
            if slots is None:
                slots = slots_of[joint] = _JointAlarms([None] * len(_KINDS))
            elif slots.idle:
                # The common case, a quiet servo: every value below its line (and already given an alarm to
                # remember it by), nothing raised or pending on the joint: nothing can change. The views
                # read the values from the last evaluation, so nothing is written either. Inline, not a call:
                # it runs for every joint of every applied message.
                quiet = self._quiet[joint]
                alarms = slots.alarms
                if (
                    (temp is None or (temp < quiet[0] and alarms[0] is not None))
                    and (current is None or (current < quiet[2] and alarms[2] is not None))
                    and (load is None or (abs(load) < quiet[3] and alarms[3] is not None))
                    and (mismatch is None or (mismatch < quiet[4] and alarms[4] is not None))
                ):
                    continue
            values = (temp, temp, current, None if load is None else abs(load), mismatch)
            self._step_joint(device, joint, slots, values, model=model, now=now, events=events)
        self._last[device] = _Evaluation(diagnostics, speeds, torques, checked)
        return events

    def _model_check(
        self,
        joint: str,
        diag: JointDiagnostics,
        load: float,
        *,
        pose_speed: float | None,
        torques: _Torques,
        checked: dict[str, tuple[float | None, float | None]],
    ) -> tuple[float | None, float | None]:
        """(model load %, | |load| - model |) while the joint is still (recorded in `checked`), else Nones."""
        if not _still(diag, pose_speed, self.thresholds.still_velocity_rad_s):
            return None, None
        model = _model_load(torques, self._servo, joint, diag.voltage_v)
        mismatch = None if model is None else abs(abs(load) - model)
        checked[joint] = (model, mismatch)
        return model, mismatch

    def _step_joint(
        self,
        device: str,
        joint: str,
        slots: _JointAlarms,
        values: tuple[float | None, ...],
        *,
        model: float | None,
        now: float,
        events: list[AlarmEvent],
    ) -> None:
        """Every kind of one joint that is not quiet steps through its rule (values in _KINDS order); the
        joint is idle afterwards when none of its alarms is present or timing a raise."""
        alarms = slots.alarms
        rules = self._rule_list[joint]
        raise_at = self._raise_at[joint]
        idle = True
        for k, value in enumerate(values):
            alarm = alarms[k]
            if alarm is None:
                if value is None:
                    continue  # nothing known, nothing to remember
                alarm = alarms[k] = self._new_alarm(device, joint, _KINDS[k], now)
            elif (
                value is not None and value < raise_at[k] and not alarm.present and alarm.raise_since is None
            ):
                continue  # quiet: nothing to change (the views read the value from the evaluation)
            self._step(alarm, value, rules[k], now=now, events=events, model=model)
            if alarm.present or alarm.raise_since is not None:
                idle = False
        slots.idle = idle

    def _new_alarm(self, device: str, joint: str, kind: AlarmKind, now: float) -> _Alarm:
        alarm = _Alarm(device, joint, kind, since=now)
        # alarm_id's f-string formats the StrEnum, slowly; a new arm creates its 29 alarms at once.
        self._alarms[device + _ID_SUFFIX[joint, kind]] = alarm
        self._by_device.setdefault(device, []).append(alarm)
        return alarm

    def _pose_speeds(
        self, device: str, angles: Mapping[str, float] | None, timestamp_ms: int | None
    ) -> dict[str, float]:
        """|dθ/dt| per joint between this pose and the last one (edge clock), when both are known."""
        if angles is None or timestamp_ms is None:
            return {}
        previous = self._last_pose.get(device)
        self._last_pose[device] = (timestamp_ms, dict(angles))
        if previous is None:
            return {}
        dt = (timestamp_ms - previous[0]) / 1000.0
        # Only consecutive-looking samples: across a gap of seconds the arm may have moved and come back.
        if not 0.0 < dt <= MAX_POSE_GAP_S:
            return {}
        last = previous[1]
        return {j: abs(a - last[j]) / dt for j, a in angles.items() if j in last}

    def _step(
        self,
        alarm: _Alarm,
        value: float | None,
        rule: Hysteresis,
        *,
        now: float,
        events: list[AlarmEvent],
        model: float | None = None,
    ) -> None:
        kind = alarm.kind
        alarm.value = value
        if value is None or rule.clear_at < value < rule.raise_at:
            # Between the lines, or unknown: hold, and make a new excursion start its timer afresh.
            alarm.raise_since = alarm.clear_since = None
            return
        if value >= rule.raise_at:
            alarm.clear_since = None
            if alarm.present:
                return
            if alarm.raise_since is None:
                alarm.raise_since = now
            if now - alarm.raise_since >= rule.raise_after_s:
                alarm.present = True
                alarm.raise_since = None
                alarm.raised += 1
                alarm.message = _describe(alarm, value, rule, model)
                # From NORMAL or LATCHED (ACKNOWLEDGED always has its condition present, so never here).
                self._move(alarm, AlarmState.ACTIVE, "raised", rule=rule, now=now, events=events)
                self.counters.raised[(kind, SEVERITY[kind])] += 1
            return
        alarm.raise_since = None
        if not alarm.present:
            return
        if alarm.clear_since is None:
            alarm.clear_since = now
        if now - alarm.clear_since >= rule.clear_after_s:
            alarm.present = False
            alarm.clear_since = None
            self.counters.cleared[kind] += 1
            if alarm.state is AlarmState.ACTIVE and self.thresholds.latch:
                self._move(alarm, AlarmState.LATCHED, "cleared", rule=rule, now=now, events=events)
            else:
                self._move(alarm, AlarmState.NORMAL, "cleared", rule=rule, now=now, events=events)

    def _move(
        self,
        alarm: _Alarm,
        state: AlarmState,
        action: str,
        *,
        rule: Hysteresis,
        now: float,
        events: list[AlarmEvent],
    ) -> None:
        previous = alarm.state
        alarm.state = state
        alarm.since = now
        if action == "raised":
            message = alarm.message
        elif action == "cleared":
            message = (
                f"{alarm.joint} {alarm.kind} cleared: at or below {rule.clear_at:g} {UNITS[alarm.kind]} for "
                f"{rule.clear_after_s:g} s"
                + (" (latched until acknowledged)" if state is AlarmState.LATCHED else "")
            )
        else:
            message = f"{alarm.joint} {alarm.kind} {action} by a person"
        events.append(
            AlarmEvent(
                alarm_id=alarm.alarm_id,
                device=alarm.device,
                joint=alarm.joint,
                kind=alarm.kind,
                severity=SEVERITY[alarm.kind],
                previous=previous,
                state=state,
                action=action,
                value=alarm.value,
                threshold=rule.raise_at if action == "raised" else rule.clear_at,
                at=now,
                message=message,
            )
        )

    # -- restarts -------------------------------------------------------------------------------------------

    def records(self, *, devices: Iterable[str] | None = None) -> list[AlarmRecord]:
        """Every alarm that is not NORMAL or whose condition is present or timing a raise (a NORMAL, idle
        alarm is made again from the next message), of `devices` or of all."""
        wanted = None if devices is None else set(devices)
        out = []
        for alarm in self._alarms.values():
            if wanted is not None and alarm.device not in wanted:
                continue
            if alarm.state is AlarmState.NORMAL and not alarm.present and alarm.raise_since is None:
                continue
            out.append(
                AlarmRecord(
                    device=alarm.device,
                    joint=alarm.joint,
                    kind=alarm.kind,
                    state=alarm.state,
                    since=alarm.since,
                    present=alarm.present,
                    raised=alarm.raised,
                    value=alarm.value,
                    message=alarm.message,
                    raise_since=alarm.raise_since,
                    clear_since=alarm.clear_since,
                )
            )
        return out

    def restore(self, records: Iterable[AlarmRecord]) -> int:
        """Take back alarms `records` exported (after a restart, before any message of their devices): each
        replaces what the engine has for its id. Records of joints or kinds this engine does not know are
        skipped. Returns how many were restored."""
        restored = 0
        for record in records:
            if record.joint not in self._rule_list or record.kind not in _KINDS:
                continue
            key = record.device + _ID_SUFFIX[record.joint, record.kind]
            alarm = self._alarms.get(key)
            slots_of = self._slots.setdefault(record.device, {})
            slots = slots_of.get(record.joint)
            if slots is None:
                slots = slots_of[record.joint] = _JointAlarms([None] * len(_KINDS))
            if alarm is None:
                alarm = self._new_alarm(record.device, record.joint, record.kind, record.since)
                slots.alarms[_KINDS.index(record.kind)] = alarm
            # The joint's next evaluation takes the full path, so a restored condition can clear.
            slots.idle = False
            alarm.state = record.state
            alarm.since = record.since
            alarm.present = record.present
            alarm.raised = record.raised
            alarm.value = record.value
            alarm.message = record.message
            alarm.raise_since = record.raise_since
            alarm.clear_since = record.clear_since
            restored += 1
        return restored

    def restore_counters(self, counters: AlarmCounters) -> None:
        """Add `counters` (a previous run's totals) to this engine's."""
        self.counters.raised.update(counters.raised)
        self.counters.cleared.update(counters.cleared)
        self.counters.acknowledged.update(counters.acknowledged)

    # -- people ---------------------------------------------------------------------------------------------

    def acknowledge(self, alarm_id_: str, now: float) -> AlarmEvent:
        """ACTIVE -> ACKNOWLEDGED, LATCHED -> NORMAL (SiteWise's acknowledge and reset in one verb).

        Raises AlarmNotFound for an unknown id and NothingToAcknowledge for a NORMAL or ACKNOWLEDGED alarm.
        """
        alarm = self._alarms.get(alarm_id_)
        if alarm is None:
            raise AlarmNotFound(alarm_id_)
        if alarm.state is AlarmState.ACTIVE:
            target, action = AlarmState.ACKNOWLEDGED, "acknowledged"
        elif alarm.state is AlarmState.LATCHED:
            target, action = AlarmState.NORMAL, "reset"
        else:
            raise NothingToAcknowledge(
                f"alarm {alarm_id_} is {alarm.state}: only ACTIVE or LATCHED alarms can be acknowledged"
            )
        events: list[AlarmEvent] = []
        rule = self._rules[alarm.joint][alarm.kind]
        self._move(alarm, target, action, rule=rule, now=now, events=events)
        self.counters.acknowledged[alarm.kind] += 1
        return events[0]

    # -- views ----------------------------------------------------------------------------------------------

    def get(self, alarm_id_: str) -> AlarmView | None:
        alarm = self._alarms.get(alarm_id_)
        return None if alarm is None else self._view(alarm)

    def views_of(self, alarm_ids: Iterable[str]) -> list[AlarmView]:
        """The named alarms; raises AlarmNotFound for an unknown id."""
        out = []
        for key in alarm_ids:
            alarm = self._alarms.get(key)
            if alarm is None:
                raise AlarmNotFound(key)
            out.append(self._view(alarm))
        return out

    def views(self, *, include_normal: bool = False, device: str | None = None) -> list[AlarmView]:
        """Alarms sorted worst first (severity, then state, then id); NORMAL ones only when asked."""
        alarms = self._alarms.values() if device is None else self._by_device.get(device, ())
        out = [self._view(a) for a in alarms if include_normal or a.state is not AlarmState.NORMAL]
        out.sort(key=lambda v: worst_first(v.severity, v.state, v.alarm_id))
        return out

    def _view(self, alarm: _Alarm) -> AlarmView:
        rule = self._rules[alarm.joint][alarm.kind]
        return AlarmView(
            alarm_id=alarm.alarm_id,
            device=alarm.device,
            joint=alarm.joint,
            kind=alarm.kind,
            severity=SEVERITY[alarm.kind],
            state=alarm.state,
            value=self._value_of(alarm),
            threshold=rule.raise_at,
            unit=UNITS[alarm.kind],
            since=alarm.since,
            raised=alarm.raised,
            message=alarm.message,
        )

    def _value_of(self, alarm: _Alarm) -> float | None:
        """The alarm's value at the device's last evaluation (a quiet evaluation does not write it)."""
        last = self._last.get(alarm.device)
        diag = None if last is None else last.diagnostics.get(alarm.joint)
        if last is None or diag is None:
            return alarm.value  # the joint was not in the last message: what it had when last evaluated
        kind = alarm.kind
        if kind is AlarmKind.OVER_TEMPERATURE or kind is AlarmKind.OVER_TEMPERATURE_CRITICAL:
            return diag.temperature_c
        if kind is AlarmKind.OVER_CURRENT:
            return diag.current_a
        if kind is AlarmKind.OVERLOAD:
            return None if diag.load_percent is None else abs(diag.load_percent)
        checked = last.checked.get(alarm.joint)
        return None if checked is None else checked[1]

    def joint_health(self, device: str) -> dict[str, JointHealth]:
        last = self._last.get(device)
        return {} if last is None else last.joint_health(self.thresholds, self._servo)

    def worst_by_joint(self, device: str) -> dict[str, tuple[Severity, AlarmState]]:
        """Per joint, the severity and state of its worst alarm that is not NORMAL (the viewer's colour)."""
        worst: dict[str, tuple[Severity, AlarmState]] = {}
        for alarm in self._by_device.get(device, ()):
            if alarm.state is AlarmState.NORMAL:
                continue
            candidate = (SEVERITY[alarm.kind], alarm.state)
            current = worst.get(alarm.joint)
            if current is None or _worse(candidate, current):
                worst[alarm.joint] = candidate
        return worst

    def counts_by_state(self) -> Counter[tuple[Severity, AlarmState]]:
        return Counter((SEVERITY[a.kind], a.state) for a in self._alarms.values())

    def present_by_severity(self, devices: Iterable[str] | None = None) -> dict[Severity, int]:
        """How many alarms have their condition present (ACTIVE or ACKNOWLEDGED), by severity."""
        wanted = None if devices is None else set(devices)
        out = dict.fromkeys(Severity, 0)
        for alarm in self._alarms.values():
            if alarm.state in CONDITION_PRESENT and (wanted is None or alarm.device in wanted):
                out[SEVERITY[alarm.kind]] += 1
        return out


# ACTIVE needs a person most, then LATCHED (gone but unseen), then ACKNOWLEDGED (someone is on it).
_STATE_ORDER = {
    AlarmState.ACTIVE: 0,
    AlarmState.LATCHED: 1,
    AlarmState.ACKNOWLEDGED: 2,
    AlarmState.NORMAL: 3,
}


def worst_first(severity: Severity | str, state: AlarmState | str, alarm_id: str) -> tuple[int, int, str]:
    """The sort key of every list of alarms: critical before warning, then ACTIVE, LATCHED, ACKNOWLEDGED,
    NORMAL, then by id. Takes the enums or their values (an AlarmInfo carries strings)."""
    return (-Severity(severity).rank, _STATE_ORDER[AlarmState(state)], alarm_id)


def _worse(a: tuple[Severity, AlarmState], b: tuple[Severity, AlarmState]) -> bool:
    return (a[0].rank, -_STATE_ORDER[a[1]]) > (b[0].rank, -_STATE_ORDER[b[1]])


def _describe(alarm: _Alarm, value: float, rule: Hysteresis, model: float | None) -> str:
    kind, joint = alarm.kind, alarm.joint
    if kind is AlarmKind.OVER_TEMPERATURE:
        return f"{joint} servo at {value:.0f} C (warning at {rule.raise_at:g} C; the servo cuts out at 70 C)"
    if kind is AlarmKind.OVER_TEMPERATURE_CRITICAL:
        return f"{joint} servo at {value:.0f} C, near the 70 C cut-out (critical at {rule.raise_at:g} C)"
    if kind is AlarmKind.OVER_CURRENT:
        return f"{joint} servo draws {value:.2f} A (alarm at {rule.raise_at:.2f} A)"
    if kind is AlarmKind.OVERLOAD:
        return (
            f"{joint} servo load {value:.1f} % of stall torque held over {rule.raise_after_s:g} s "
            f"(alarm at {rule.raise_at:g} %)"
        )
    return (
        f"{joint} load differs from the model's holding load ({model or 0.0:.1f} %) by {value:.1f} points "
        f"while still (alarm at {rule.raise_at:g}): contact, a payload or a failing servo"
    )
