"""Physical servos for `twin edge-sim --servos physical`: what an arm's six STS3215s would report following
the motion, instead of the edge mock mode's uniform noise.

The edge's mock mode sends random velocity, load, temperature and current whatever the arm does; the real
edge sends exactly that, so it stays the simulator's default. The physical mode derives each reading from the
motion the simulator publishes:

- load: the torque each joint needs, by inverse dynamics on the bundled model (`RobotModel.inverse_dynamics`,
  the same computation as the agent's model check, here with the motion's velocity and acceleration), as a
  percent of the servo's stall torque at the supply voltage: what Present_Load reads at standstill
  (docs/servo-health.md). Gravity, inertia (with the rotors' armature) and the Coriolis and centrifugal terms
  count; the model's joint damping and friction loss do not: they are the physics mode's figures for how a
  driven joint settles, and counted as load they would put every joint moving at the mock motion's speeds at
  up to a third of its stall torque, the gripper past LeRobot's 25 % gripper overload line at each sweep.
  A payload (a mass held at the gripper tip) is added to the model when asked for. The load register cannot
  read past 100 %: a torque beyond the stall torque reads 100 %.
- current: follows the load, from the no-load current to the stall current (`ServoVersion.current_a`).
- temperature: a first-order thermal model of the current, per servo, starting at the ambient temperature
  (`ThermalModel`). A servo's thermal time may run faster than the clock (`speedup`), so a demo shows in
  seconds the heating that takes a real servo minutes.
- velocity: the motion's speed in steps/s; voltage: the supply.

The figures and their sources are in twin.robot.sts3215; docs/servo-health.md ("Physical servos") lists them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from twin.core.telemetry import RAD_PER_TICK, DecoderConfig, TelemetryDecoder, Units
from twin.robot import so101, sts3215

if TYPE_CHECKING:
    # MuJoCo loads only when physical servos are built: the simulator's settings need none of it.
    from twin.robot.model import RobotModel

SERVO_MODES: tuple[str, ...] = ("mock", "physical")
DEFAULT_SUPPLY_V = 5.0  # the follower's bill of materials: the 7.4 V servos on a 5 V supply
DEFAULT_AMBIENT_C = 25.0  # a room; SOARM-134's fit assumes the same (twin.robot.sts3215)
# A payload is a mass at the tool-centre point, inertia of a solid sphere this size around it.
PAYLOAD_RADIUS_M = 0.02
MAX_PAYLOAD_KG = 2.0  # far past what the arm lifts; a guard against grams typed as kilograms
MAX_SPEEDUP = 10_000.0


@dataclass(frozen=True, slots=True)
class ThermalModel:
    """One servo's temperature as a first-order lag of its copper losses: it approaches
    `ambient_c + heating_c_per_a2 * I^2` with time constant `time_constant_s` (twin.robot.sts3215 says where
    the two figures come from)."""

    ambient_c: float = DEFAULT_AMBIENT_C
    time_constant_s: float = sts3215.THERMAL_TIME_CONSTANT_S
    heating_c_per_a2: float = sts3215.HEATING_C_PER_A2

    def steady_c(self, current_a: float) -> float:
        """Where the temperature settles when `current_a` flows for long."""
        return self.ambient_c + self.heating_c_per_a2 * current_a * current_a

    def step(self, temperature_c: float, current_a: float, dt_s: float) -> float:
        """The temperature `dt_s` later with `current_a` flowing throughout: the exact solution of the lag,
        so the result does not depend on how the time is cut into steps."""
        steady = self.steady_c(current_a)
        return steady + (temperature_c - steady) * math.exp(-max(dt_s, 0.0) / self.time_constant_s)


@dataclass(frozen=True)
class PhysicalServoConfig:
    """Settings of one simulated arm's physical servos (`twin edge-sim --servos physical`)."""

    servo_version: str = sts3215.DEFAULT_SERVO_VERSION
    supply_v: float = DEFAULT_SUPPLY_V
    ambient_c: float = DEFAULT_AMBIENT_C
    payload_kg: float = 0.0
    # Joint -> how many times faster than the clock its thermal model runs (1 = real time).
    speedup: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        sts3215.servo_version(self.servo_version)  # raises with the choices
        if not 1.0 <= self.supply_v <= 20.0:
            raise ValueError(f"supply {self.supply_v} V must be between 1 and 20 V (the follower's is 5 V)")
        if not -20.0 <= self.ambient_c <= 60.0:
            raise ValueError(f"ambient {self.ambient_c} C must be between -20 and 60 C (a room is about 25)")
        if not 0.0 <= self.payload_kg <= MAX_PAYLOAD_KG:
            raise ValueError(
                f"payload {self.payload_kg} kg must be between 0 and {MAX_PAYLOAD_KG:g} kg (in kilograms: "
                "0.2 is 200 g)"
            )
        for joint, factor in self.speedup.items():
            if joint not in so101.JOINT_NAMES:
                raise ValueError(
                    f"thermal speed-up for {joint!r}: not a joint; choose from {', '.join(so101.JOINT_NAMES)}"
                )
            if not 0.0 < factor <= MAX_SPEEDUP:
                raise ValueError(
                    f"thermal speed-up {joint}:{factor:g} must be above 0 and at most {MAX_SPEEDUP:g}"
                )

    @property
    def thermal(self) -> ThermalModel:
        return ThermalModel(ambient_c=self.ambient_c)


def parse_speedup(text: str) -> tuple[str, float]:
    """`JOINT:FACTOR` -> (joint, factor); ValueError naming the expected form."""
    joint, sep, factor = text.partition(":")
    try:
        value = float(factor)
    except ValueError:
        value = math.nan
    if not sep or not math.isfinite(value):
        raise ValueError(f"thermal speed-up {text!r} must be JOINT:FACTOR, e.g. shoulder_lift:60")
    return joint, value


def payload_model(payload_kg: float, path: str | None = None) -> RobotModel:
    """The robot model (None = the bundled SO-101) with `payload_kg` held at its tool-centre point."""
    import mujoco  # noqa: PLC0415 - see TYPE_CHECKING above

    from twin.robot.model import RobotModel  # noqa: PLC0415

    robot = RobotModel.load(path)
    if payload_kg <= 0.0:
        return robot
    spec = mujoco.MjSpec.from_file(str(robot.path))
    if robot.tcp_site_id is not None:
        body_id = int(robot.model.site_bodyid[robot.tcp_site_id])
        position = [float(v) for v in robot.model.site_pos[robot.tcp_site_id]]
    else:
        body_id, position = robot.tcp_body_id, [0.0, 0.0, 0.0]
    body_name = mujoco.mj_id2name(robot.model, mujoco.mjtObj.mjOBJ_BODY, body_id)
    inertia = 0.4 * payload_kg * PAYLOAD_RADIUS_M**2
    # The centre of mass at the body's origin, said explicitly: left unset, the compiler puts it elsewhere.
    spec.body(body_name).add_body(
        name="edge_sim_payload",
        pos=position,
        mass=payload_kg,
        ipos=[0.0, 0.0, 0.0],
        inertia=[inertia] * 3,
        explicitinertial=True,
    )
    return RobotModel.from_model(spec.compile(), robot.path)


@dataclass(frozen=True, slots=True)
class ServoReading:
    """What one servo reports, in physical units (the payload encodes them as its registers)."""

    velocity_steps_s: float
    load_percent: float  # signed like the model's torque; 100 % is the stall torque at the supply
    current_a: float
    temperature_c: float
    voltage_v: float


class TickAngles:
    """Raw tick positions -> joint angles (rad) through the agent's own decoder (ticks, no calibration file),
    so the edge simulator's physics agree with the pose the agent will mirror."""

    def __init__(self) -> None:
        self._decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
        self.stamp = 946_684_800_000  # any increasing edge time will do; advanced once per decode

    def decode(self, ticks: Sequence[int]) -> dict[str, float]:
        doc = {
            "device_id": "edge-sim",
            "timestamp": self.stamp,
            "joints": {n: {"position": p} for n, p in zip(so101.JOINT_NAMES, ticks, strict=True)},
        }
        self.stamp += 1
        return self._decoder.decode(json.dumps(doc)).angles_rad


class ArmDynamics:
    """Tick positions, rates and accelerations -> joint torques on one robot model (with its payload).

    Positions are decoded by the agent's own decoder (ticks, no calibration file), so the pose is the one the
    agent will mirror; rates and accelerations scale by the same radians per tick. Uses this thread's MuJoCo
    workspace: one per simulator thread.
    """

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self._angles = TickAngles()

    def torques(
        self, ticks: Sequence[int], rates: Sequence[float], accelerations: Sequence[float]
    ) -> dict[str, float]:
        angles = self._angles.decode(ticks)
        names = self.robot.joint_names
        return self.robot.inverse_dynamics(
            [angles[n] for n in names],
            [r * RAD_PER_TICK for r in rates],
            [a * RAD_PER_TICK for a in accelerations],
            passive=False,
        )


class PhysicalArm:
    """The six servos of one simulated arm: each message's readings from its motion, the temperatures kept
    from one message to the next (edge time `t`, seconds since the simulation began)."""

    def __init__(self, config: PhysicalServoConfig, dynamics: ArmDynamics) -> None:
        self.config = config
        self.dynamics = dynamics
        self._servo = sts3215.servo_version(config.servo_version)
        self._thermal = config.thermal
        self.temperatures_c = dict.fromkeys(so101.JOINT_NAMES, config.ambient_c)
        self._last_t: float | None = None

    def readings(
        self, t: float, ticks: Sequence[int], rates: Sequence[float], accelerations: Sequence[float]
    ) -> dict[str, ServoReading]:
        """Readings at `t` of servos at `ticks` moving at `rates` (ticks/s) with `accelerations` (ticks/s²),
        all in JOINT_NAMES order. Calls must come in time order: the temperatures integrate between them."""
        config = self.config
        dt = 0.0 if self._last_t is None else max(t - self._last_t, 0.0)
        self._last_t = t
        torques = self.dynamics.torques(ticks, rates, accelerations)
        out: dict[str, ServoReading] = {}
        for i, name in enumerate(so101.JOINT_NAMES):
            load = self._servo.load_percent(torques[name], config.supply_v)
            load = max(-100.0, min(100.0, load))
            current = self._servo.current_a(load, config.supply_v)
            temperature = self._thermal.step(
                self.temperatures_c[name], current, dt * config.speedup.get(name, 1.0)
            )
            self.temperatures_c[name] = temperature
            out[name] = ServoReading(
                velocity_steps_s=rates[i],
                load_percent=load,
                current_a=current,
                temperature_c=temperature,
                voltage_v=config.supply_v,
            )
        return out
