"""Servo faults for `twin edge-sim`: a servo heating up, an overload, and a contact (the load jumps while the
pose holds), each on one joint for a stretch of the run; and model-consistent loads to run them on.

A fault is written `KIND:JOINT[:START_S[:DURATION_S]]` (seconds since the simulation started), e.g.
`heat:elbow_flex:5:30`. While it lasts it rewrites that joint's readings in physical units, which the
simulator then encodes like the real registers (sign bits, 0.1 % and 6.5 mA units):

- heat: the temperature ramps up over the first quarter to HEAT_PEAK_C (above the agent's critical level,
  below the servo's 70 C cut-out), holds for half, and ramps back down over the last quarter;
- overload: the joint stalls where it is (position held, velocity 0) with OVERLOAD_LOAD_PERCENT load and
  OVERLOAD_CURRENT_A current, past the servo's 80 % overload line and 90 % of its 3.25 A protection current;
  once that has lasted the servo's overload protection time (2 s) its status reports the overload bit, as an
  edge that forwards the status register sends it (an arm with an overload fault sends `status` on every
  joint, 0 where no bit is set);
- contact: the joint stops where it is and its load rises by CONTACT_JUMP_PERCENT, staying under the overload
  line: only the model check can tell it from holding still.

Overload and contact release after RELEASE_AT of their duration while the pose still holds for the rest:
the servo is still and back to its holding load, which is what lets the model check clear.

The edge's mock mode sends random loads of 0.5..5 % whatever the pose. `ModelLoads` instead sends the load
the servo would report holding each pose (the bundled model's inverse dynamics, as the agent computes it),
so the model check has a true baseline to compare against (`twin edge-sim --model-loads`).
The alarms each fault should raise are listed in docs/servo-health.md.
"""

from __future__ import annotations

from dataclasses import dataclass

from twin.robot import so101, sts3215

FAULT_KINDS: tuple[str, ...] = ("heat", "overload", "contact")
DEFAULT_START_S = 5.0
DEFAULT_DURATION_S = 20.0

HEAT_BASE_C = 35.0
HEAT_PEAK_C = sts3215.MAX_TEMPERATURE_C - 2.0
OVERLOAD_LOAD_PERCENT = 90.0
OVERLOAD_CURRENT_A = 0.9 * sts3215.PROTECTION_CURRENT_A
CONTACT_JUMP_PERCENT = 45.0
RELEASE_AT = 0.6
OVERLOAD_STATUS = 1 << sts3215.STATUS_BITS.index("overload")


@dataclass(frozen=True, slots=True)
class ServoFault:
    kind: str
    joint: str
    start_s: float = DEFAULT_START_S
    duration_s: float = DEFAULT_DURATION_S

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"servo fault {self.kind!r} is not one of {', '.join(FAULT_KINDS)}")
        if self.joint not in so101.JOINT_NAMES:
            raise ValueError(
                f"servo fault {self.kind}: joint {self.joint!r} is not one of {', '.join(so101.JOINT_NAMES)}"
            )
        if not self.start_s >= 0 or not self.duration_s > 0:
            raise ValueError(
                f"servo fault {self.kind}:{self.joint}: start {self.start_s} s must be >= 0 and duration "
                f"{self.duration_s} s > 0"
            )

    def active(self, t: float) -> bool:
        return self.start_s <= t < self.start_s + self.duration_s

    def heat_envelope(self, t: float) -> float:
        """0..1: up over the first quarter, 1 for the middle half, down over the last quarter."""
        if not self.active(t):
            return 0.0
        x = (t - self.start_s) / self.duration_s
        return min(1.0, 4.0 * x, 4.0 * (1.0 - x))


def parse_fault(text: str) -> ServoFault:
    """`KIND:JOINT[:START_S[:DURATION_S]]` -> ServoFault; raises ValueError naming the expected form."""
    parts = text.split(":")
    if not 2 <= len(parts) <= 4:
        raise ValueError(
            f"servo fault {text!r} must be KIND:JOINT[:START_S[:DURATION_S]], e.g. heat:elbow_flex:5:30"
        )
    try:
        numbers = [float(p) for p in parts[2:]]
    except ValueError:
        raise ValueError(f"servo fault {text!r}: START_S and DURATION_S must be numbers of seconds") from None
    return ServoFault(parts[0], parts[1], *numbers)


@dataclass(slots=True)
class JointOverride:
    """What the faults do to one joint's readings at one moment (None = leave the simulated value)."""

    hold_at_s: float | None = None  # keep the position the joint had at this time, velocity 0
    temperature_c: float | None = None
    load_percent: float | None = None  # replaces the load
    load_add_percent: float | None = None  # adds to the load, away from zero
    current_a: float | None = None
    status: int | None = None  # the status register's error bits


def overrides_at(faults: tuple[ServoFault, ...], t: float) -> dict[str, JointOverride]:
    """The readings the active faults impose at `t`, by joint."""
    out: dict[str, JointOverride] = {}
    for fault in faults:
        if not fault.active(t):
            continue
        o = out.setdefault(fault.joint, JointOverride())
        if fault.kind == "heat":
            o.temperature_c = HEAT_BASE_C + fault.heat_envelope(t) * (HEAT_PEAK_C - HEAT_BASE_C)
            continue
        o.hold_at_s = fault.start_s
        if t >= fault.start_s + RELEASE_AT * fault.duration_s:
            continue  # released: still, at its holding load
        if fault.kind == "overload":
            o.load_percent = OVERLOAD_LOAD_PERCENT
            o.current_a = OVERLOAD_CURRENT_A
            if t >= fault.start_s + sts3215.OVERLOAD_PROTECTION_TIME_S:
                o.status = OVERLOAD_STATUS  # the servo's own protection has tripped
        else:
            o.load_add_percent = CONTACT_JUMP_PERCENT
    return out


class ModelLoads:
    """The load (percent of stall torque, signed like the model's torque) each servo reports holding a pose,
    and the current that load draws.

    Uses the same bundled model, tick conversion and inverse dynamics as the agent, so a simulated arm with
    no fault agrees with the agent's model check. Loads MuJoCo; one per simulator thread.
    """

    def __init__(self, servo_version: str = sts3215.DEFAULT_SERVO_VERSION, supply_v: float = 5.0) -> None:
        # Imported here: only `--model-loads` pays for MuJoCo in the simulator.
        from twin.core.twin import DeviceTwin  # noqa: PLC0415
        from twin.edge.servo_physics import TickAngles  # noqa: PLC0415
        from twin.robot.model import RobotModel  # noqa: PLC0415

        self._servo = sts3215.servo_version(servo_version)
        self.supply_v = supply_v
        self._angles = TickAngles()
        self._twin = DeviceTwin(RobotModel.load(), "edge-sim")

    def current_a(self, load_percent: float) -> float:
        """The current a servo draws at `load_percent` (the servo's own conversion, at this supply)."""
        return self._servo.current_a(load_percent, self.supply_v)

    def percent(self, ticks: list[int]) -> dict[str, float]:
        angles = self._angles.decode(ticks)
        self._twin.apply(angles, self._angles.stamp)
        return {
            joint: self._servo.load_percent(torque, self.supply_v)
            for joint, torque in self._twin.joint_torques.items()
        }


def load_register(percent: float) -> int:
    """Signed load percent -> Present_Load register (0.1 % units, direction in bit 10)."""
    units = min(1000, round(abs(percent) * sts3215.LOAD_UNITS_PER_PERCENT))
    return units + sts3215.LOAD_SIGN_BIT if percent < 0 else units


def current_register(amperes: float) -> int:
    """Amperes -> Present_Current register (6.5 mA units)."""
    return round(amperes * 1000.0 / sts3215.CURRENT_MA_PER_UNIT)
