"""Feetech STS3215 servo facts: register scales, factory protection settings and torque figures, in one place.

Every figure names its source (docs/servo-health.md repeats them in a table):

- FT-TBL: the STS3215 memory table as transcribed in Mickael-Roger/python-st3215 `README.md` (register
  address, unit and factory default of each field);
- L-FT: huggingface/lerobot `src/lerobot/motors/feetech/tables.py` and `feetech.py` (the same registers as
  LeRobot reads them) and `robots/so_follower` (what LeRobot writes at connect);
- SOARM: TheRobotStudio/SO-ARM100 `README.md`, footnote 1 (the follower's two servo versions and their stall
  torques);
- SOARM-132: TheRobotStudio/SO-ARM100 issue #132 (the 12 V version's no-load and stall currents; the same
  figures are the inputs of the actuator model in Gregory119/RBE501-RL-arm-project
  `gymnasium_env/calc_actuator_model.py`);
- SOARM-134: TheRobotStudio/SO-ARM100 issue #134 (a bench test of the 12 V version: its temperature rise
  under a steady load).

The alarm thresholds in `twin.core.alarms` are derived from these; nothing else in the project should spell
one of these numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# 1 kgf·cm in N·m (standard gravity 9.80665 m/s², 1 cm = 0.01 m): datasheets quote torque in kg·cm.
NM_PER_KGF_CM = 9.80665 / 100.0

# --- register scales (FT-TBL; L-FT agrees) -----------------------------------------------------------------

STEPS_PER_TURN = 4096
RAD_PER_STEP = 2.0 * math.pi / STEPS_PER_TURN
# Present_Velocity (address 58) is sign-magnitude with the direction in bit 15; the edge passes it on raw.
VELOCITY_SIGN_BIT = 1 << 15
# Present_Load (address 60): "the voltage duty cycle of the current control output driving the motor",
# magnitude 0..1000 in 0.1 % units with the direction in bit 10 (1024 + n means -n).
LOAD_SIGN_BIT = 1 << 10
# The 0.1 % and 0.1 V registers are divided by 10, not multiplied by 0.1: a register of 12 then reads 1.2,
# the nearest double to the decimal, where 12 * 0.1 gave 1.2000000000000002.
LOAD_UNITS_PER_PERCENT = 10
# Present_Current (address 69): 6.5 mA per unit, at most 500 units (3.25 A) measurable.
CURRENT_MA_PER_UNIT = 6.5
# Present_Voltage (address 62): 0.1 V per unit.
VOLTAGE_UNITS_PER_VOLT = 10
# Status (address 65): the servo's error bits, lowest first; what the servo itself says is wrong.
STATUS_BITS = ("voltage", "sensor", "temperature", "current", "angle", "overload")


def status_names(status: int) -> tuple[str, ...]:
    """The names of the error bits set in a status value (bits above the sixth are ignored; a negative value
    is no register's and names none: Python's -1 has every bit set)."""
    if status < 0:
        return ()
    return tuple(name for bit, name in enumerate(STATUS_BITS) if status >> bit & 1)


# --- factory protection settings (FT-TBL, EEPROM defaults) -------------------------------------------------

# Maximum temperature (address 13, default 70): above it the servo's temperature protection cuts the torque.
MAX_TEMPERATURE_C = 70.0
# Protection current (address 28, default 500 x 6.5 mA) held for the over-current protection time
# (address 38, default 200 x 10 ms) trips the servo's current protection.
PROTECTION_CURRENT_A = 500 * CURRENT_MA_PER_UNIT / 1000.0
OVERCURRENT_PROTECTION_TIME_S = 200 * 0.010
# Overload torque (address 36, default 80 % of the maximum torque) held for the protection time (address 35,
# default 200 x 10 ms) makes the servo drop to the protection torque (address 34, default 20 %).
OVERLOAD_TORQUE_PERCENT = 80.0
OVERLOAD_PROTECTION_TIME_S = 200 * 0.010
PROTECTION_TORQUE_PERCENT = 20.0
# The maximum-torque register (address 16) and the load scale share one reference: 1000 = 100 % of the
# locked-rotor (stall) torque. So the decoded load percent is a percent of the stall torque.
LOAD_REFERENCE = "stall torque"

# LeRobot's SO follower writes smaller limits to the gripper servo at connect (L-FT `configure_motors` via
# robots/so_follower): Protection_Current 250 (x 6.5 mA) and Overload_Torque 25 %, so a grasp cannot burn
# the jaw servo.
GRIPPER_PROTECTION_CURRENT_A = 250 * CURRENT_MA_PER_UNIT / 1000.0
GRIPPER_OVERLOAD_TORQUE_PERCENT = 25.0

# --- current and heating (the edge simulator's physical servos, twin.edge.servo_physics) --------------------

# SOARM-132: the 12 V version draws 0.18 A running free and 2.7 A stalled, at 12 V. Our sources give no
# current for the 7.4 V version; the simulator takes the same two figures at its quoted voltage.
NO_LOAD_CURRENT_A = 0.18
STALL_CURRENT_A = 2.7
# A first-order thermal model, T' = (T_ambient + HEATING_C_PER_A2 * I^2 - T) / THERMAL_TIME_CONSTANT_S, fitted
# to SOARM-134: holding 15 kg·cm (half the 12 V version's 30 kg·cm stall torque, so 0.18 + 0.5 * 2.52 =
# 1.44 A) the servo settled at 48 C after an hour, +23 C over a room taken as 25 C (the test does not say):
# 23 / 1.44^2 = 11.1 C per A^2. Lifting the same torque it was +15 C after 10 minutes: 1 - exp(-10 / tau) =
# 15 / 23 gives tau = 9.5 minutes. Copper losses (I^2 R) dominate a loaded DC motor, hence I^2.
HEATING_C_PER_A2 = 11.1
THERMAL_TIME_CONSTANT_S = 570.0

# A Present_Voltage reading outside this range is no supply voltage (an unpowered bus, a bad read): the
# figures that scale with the supply then take it as quoted.
SUPPLY_V_MIN = 1.0
SUPPLY_V_MAX = 20.0


@dataclass(frozen=True, slots=True)
class ServoVersion:
    """One STS3215 version: its stall torque at the voltage the figure is quoted for."""

    name: str
    stall_torque_nm: float
    quoted_at_v: float
    source: str

    def stall_torque_at(self, supply_v: float | None = None) -> float:
        """Stall torque (N·m) at `supply_v`, or at the quoted voltage when the supply is unknown.

        A DC motor's stall torque is Kt·V/R, proportional to the supply, and the servo's load register is the
        drive duty cycle: at standstill the load percent is the torque as a share of the stall torque at the
        present supply. A reading outside 1..20 V is no supply voltage and is ignored.
        """
        if supply_v is None or not SUPPLY_V_MIN <= supply_v <= SUPPLY_V_MAX:
            return self.stall_torque_nm
        return self.stall_torque_nm * supply_v / self.quoted_at_v

    def load_percent(self, torque_nm: float, supply_v: float | None = None) -> float:
        """The load (percent of stall torque) a servo reports while holding `torque_nm` still."""
        return 100.0 * torque_nm / self.stall_torque_at(supply_v)

    def load_percents(self, torques_nm: Any, supply_v: Any) -> Any:
        """`load_percent` of numpy arrays (broadcast together; NaN for an unknown supply), element for element
        the same values, in the same operations: for the alarm engine's model check of a batch."""
        # Imported here: the agent's receiving process and `twin --help` import this module and must not load
        # numpy (core.alarms says why).
        import numpy as np  # noqa: PLC0415

        supplied = (supply_v >= SUPPLY_V_MIN) & (supply_v <= SUPPLY_V_MAX)
        stall = np.where(supplied, self.stall_torque_nm * supply_v / self.quoted_at_v, self.stall_torque_nm)
        return 100.0 * torques_nm / stall

    def stall_current_at(self, supply_v: float | None = None) -> float:
        """Stall current (A) at `supply_v`: V/R, proportional to the supply like the stall torque
        (STALL_CURRENT_A at the quoted voltage; the same rule for a reading that is no supply voltage)."""
        if supply_v is None or not SUPPLY_V_MIN <= supply_v <= SUPPLY_V_MAX:
            return STALL_CURRENT_A
        return STALL_CURRENT_A * supply_v / self.quoted_at_v

    def current_a(self, load_percent: float, supply_v: float | None = None) -> float:
        """The current (A) a servo draws at `load_percent` of its stall torque: a DC motor's current follows
        its torque, from the no-load current to the stall current."""
        share = min(abs(load_percent), 100.0) / 100.0
        stall = self.stall_current_at(supply_v)
        return NO_LOAD_CURRENT_A + share * max(stall - NO_LOAD_CURRENT_A, 0.0)


SERVO_VERSIONS: dict[str, ServoVersion] = {
    # The follower's bill of materials lists the 7.4 V servo (C001) on a 5 V supply.
    "7.4v": ServoVersion(
        "7.4v",
        16.5 * NM_PER_KGF_CM,
        6.0,
        "TheRobotStudio/SO-ARM100 README.md footnote 1: 16.5 kg·cm at 6 V",
    ),
    "12v": ServoVersion(
        "12v",
        30.0 * NM_PER_KGF_CM,
        12.0,
        "TheRobotStudio/SO-ARM100 README.md footnote 1: 30 kg·cm (12 V version, 12 V supply)",
    ),
}
DEFAULT_SERVO_VERSION = "7.4v"


def servo_version(name: str) -> ServoVersion:
    """The named version; raises ValueError naming the choices."""
    try:
        return SERVO_VERSIONS[name]
    except KeyError:
        raise ValueError(
            f"servo version {name!r} is not one of {', '.join(SERVO_VERSIONS)}; the SO-101 follower ships "
            "with the 7.4v servo, the optional high-torque one is 12v"
        ) from None
