"""`twin edge-sim --servos physical`: loads from the model's gravity and motion torques, current from the
load, temperature from a first-order thermal model, in payloads the agent's decoder accepts.

Figures are checked against MuJoCo directly (the mass matrix, the agent's own holding torques) and against
the closed form of a first-order lag, not against numbers copied from the code.
"""

from __future__ import annotations

import json
import math
import random

import mujoco
import numpy as np
import pytest
from conftest import wait_for
from twin.cli import main
from twin.core.alarms import AlarmState, ServoAlarms
from twin.core.telemetry import RAD_PER_TICK, DecoderConfig, TelemetryDecoder, Units
from twin.core.topics import DEFAULT_TOPIC_PREFIX, topic_filters
from twin.core.twin import DeviceTwin
from twin.edge import simulator as simulator_module
from twin.edge.payload import (
    encode,
    make_payload,
    mock_motion_rates,
    mock_motion_ticks,
    mock_ticks,
    physical_readings,
)
from twin.edge.servo_faults import ModelLoads, ServoFault
from twin.edge.servo_physics import (
    ArmDynamics,
    PhysicalArm,
    PhysicalServoConfig,
    ThermalModel,
    parse_speedup,
    payload_model,
)
from twin.edge.simulator import EdgeSimConfig, EdgeSimulator
from twin.rig.demo import STORY_JOINT, STORY_PAYLOAD_KG, STORY_SPEEDUP
from twin.rig.mosquitto import MosquittoBroker
from twin.robot import so101, sts3215
from twin.robot.model import RobotModel
from twin.transport.broker import BrokerConfig
from twin.transport.subscriber import TelemetrySubscriber

TS0 = 1_764_000_000_000
SERVO = sts3215.servo_version(sts3215.DEFAULT_SERVO_VERSION)
SUPPLY_V = 5.0
STILL = [0.0] * len(so101.JOINT_NAMES)


@pytest.fixture(scope="module")
def dynamics() -> ArmDynamics:
    return ArmDynamics(payload_model(0.0))


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


def ticks_of(angles: dict[str, float]) -> list[int]:
    """Whole ticks of arm-joint angles (radians), the rest at the homing pose; the decoder's map inverted."""
    return [round(so101.TICK_HOME + angles.get(n, 0.0) / RAD_PER_TICK) for n in so101.JOINT_NAMES]


def reach(robot: RobotModel, ticks: list[int]) -> float:
    """Horizontal distance (m) of the gripper tip (the TCP site) from the shoulder_lift axis at a pose."""
    angles = TelemetryDecoder(DecoderConfig(units=Units.TICKS)).decode(payload_at(ticks)).angles_rad
    data = mujoco.MjData(robot.model)
    for name, value in angles.items():
        data.qpos[robot.qpos_addr[name]] = value
    mujoco.mj_kinematics(robot.model, data)
    assert robot.tcp_site_id is not None
    shoulder = data.xpos[robot.body_ids["upper_arm"]]
    return float(np.linalg.norm((data.site_xpos[robot.tcp_site_id] - shoulder)[:2]))


def payload_at(ticks: list[int]) -> str:
    return json.dumps(
        {
            "device_id": "a",
            "timestamp": TS0,
            "joints": {n: {"position": p} for n, p in zip(so101.JOINT_NAMES, ticks, strict=True)},
        }
    )


# Folded: the rest pose of a real follower (LeRobot degrees read from one; docs/robot-model.md); stretched:
# the upper arm leant 60 degrees forward from upright, the forearm and gripper level, reaching out.
FOLDED = ticks_of({"shoulder_lift": math.radians(-98.9), "elbow_flex": math.radians(96.0)})
STRETCHED = ticks_of({"shoulder_lift": math.radians(60.0), "elbow_flex": math.radians(-60.0)})


@pytest.mark.parametrize("version", sorted(sts3215.SERVO_VERSIONS))
def test_load_percents_of_arrays_equal_load_percent_of_each_value(version: str) -> None:
    # The alarm engine's batch path (load_percents) must give the row path's values exactly: the supply
    # range's edges, just outside them, no supply (None; NaN in an array), and torques of either sign.
    servo = sts3215.SERVO_VERSIONS[version]
    supplies = [None, 0.0, 0.99, 1.0, 5.0, 7.4, 12.0, 20.0, 20.01, 25.0, -3.0]
    torques = [0.0, 0.013, -0.25, 1.7, 3.1e-5]
    volts = np.array([[math.nan if v is None else v] * len(torques) for v in supplies])
    got = servo.load_percents(np.array([torques] * len(supplies)), volts)
    want = [[servo.load_percent(t, v) for t in torques] for v in supplies]
    assert got.tolist() == want


def test_shoulder_load_follows_gravity_stretched_out_versus_folded(
    dynamics: ArmDynamics, robot: RobotModel
) -> None:
    assert reach(robot, STRETCHED) > 2 * reach(robot, FOLDED)  # the poses are what their names say
    folded = PhysicalArm(PhysicalServoConfig(), dynamics).readings(0.0, FOLDED, STILL, STILL)
    stretched = PhysicalArm(PhysicalServoConfig(), dynamics).readings(0.0, STRETCHED, STILL, STILL)
    lift = "shoulder_lift"
    assert abs(stretched[lift].load_percent) > 25.0
    assert abs(stretched[lift].load_percent) > 4 * abs(folded[lift].load_percent)
    # Holding still, the load is the agent's own holding torque as a share of the stall torque at 5 V: the
    # same inverse dynamics as its model check.
    for ticks, readings in ((FOLDED, folded), (STRETCHED, stretched)):
        twin = DeviceTwin(robot, "a")
        twin.apply(
            TelemetryDecoder(DecoderConfig(units=Units.TICKS)).decode(payload_at(ticks)).angles_rad, TS0
        )
        for joint, torque in twin.joint_torques.items():
            assert readings[joint].load_percent == pytest.approx(
                SERVO.load_percent(torque, SUPPLY_V), abs=1e-9
            )
            assert readings[joint].velocity_steps_s == 0.0


def test_motion_adds_the_inertial_torque(dynamics: ArmDynamics, robot: RobotModel) -> None:
    # Accelerating one joint from rest adds M[:, j] * a to every joint's torque (inverse dynamics is linear in
    # the acceleration): checked against MuJoCo's own mass matrix at the pose.
    pose, accel_ticks = STRETCHED, 800.0
    still = dynamics.torques(pose, STILL, STILL)
    j = so101.JOINT_NAMES.index("elbow_flex")
    accelerations = [accel_ticks if i == j else 0.0 for i in range(len(pose))]
    moving = dynamics.torques(pose, STILL, accelerations)
    model = robot.inverse_model
    data = mujoco.MjData(model)
    angles = TelemetryDecoder(DecoderConfig(units=Units.TICKS)).decode(payload_at(pose)).angles_rad
    for name in so101.JOINT_NAMES:
        data.qpos[robot.qpos_addr[name]] = angles[name]
    mujoco.mj_forward(model, data)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    column = mass[:, robot.dof_addr["elbow_flex"]] * accel_ticks * RAD_PER_TICK
    for name in so101.JOINT_NAMES:
        assert moving[name] - still[name] == pytest.approx(column[robot.dof_addr[name]], abs=1e-9), name
    assert abs(column[robot.dof_addr["elbow_flex"]]) > 0.005  # a real difference, not rounding


def test_a_payload_loads_the_shoulder_more(robot: RobotModel) -> None:
    bare = PhysicalArm(PhysicalServoConfig(), ArmDynamics(payload_model(0.0)))
    laden = PhysicalArm(PhysicalServoConfig(payload_kg=0.1), ArmDynamics(payload_model(0.1)))
    lift_bare = bare.readings(0.0, STRETCHED, STILL, STILL)["shoulder_lift"].load_percent
    lift_laden = laden.readings(0.0, STRETCHED, STILL, STILL)["shoulder_lift"].load_percent
    # 100 g at the tip: its weight's moment about the shoulder_lift axis, (r x m g) . axis, more torque.
    angles = TelemetryDecoder(DecoderConfig(units=Units.TICKS)).decode(payload_at(STRETCHED)).angles_rad
    data = mujoco.MjData(robot.model)
    for name, value in angles.items():
        data.qpos[robot.qpos_addr[name]] = value
    mujoco.mj_kinematics(robot.model, data)
    assert robot.tcp_site_id is not None
    joint = robot.joint_ids["shoulder_lift"]
    lever = data.site_xpos[robot.tcp_site_id] - data.xanchor[joint]
    weight = 0.1 * robot.model.opt.gravity
    extra_nm = abs(float(np.dot(np.cross(lever, weight), data.xaxis[joint])))
    assert extra_nm > 0.3
    assert abs(lift_laden) - abs(lift_bare) == pytest.approx(
        100.0 * extra_nm / SERVO.stall_torque_at(SUPPLY_V), rel=1e-6
    )


def test_current_follows_the_load() -> None:
    stall_5v = sts3215.STALL_CURRENT_A * SUPPLY_V / SERVO.quoted_at_v
    assert SERVO.current_a(0.0, SUPPLY_V) == sts3215.NO_LOAD_CURRENT_A
    assert SERVO.current_a(100.0, SUPPLY_V) == pytest.approx(stall_5v)
    assert SERVO.current_a(-100.0, SUPPLY_V) == pytest.approx(stall_5v)  # the sign is only the direction
    assert SERVO.current_a(250.0, SUPPLY_V) == pytest.approx(stall_5v)  # the register saturates
    currents = [SERVO.current_a(load, SUPPLY_V) for load in range(0, 101, 10)]
    steps = np.diff(currents)
    assert np.all(steps > 0) and np.allclose(steps, steps[0])  # linear in the load
    assert stall_5v < 0.8 * sts3215.PROTECTION_CURRENT_A  # never the over-current alarm by itself


def test_readings_current_follows_their_load(dynamics: ArmDynamics) -> None:
    arm = PhysicalArm(PhysicalServoConfig(), dynamics)
    pairs = []
    for k in range(0, 200, 7):
        t = k / 10
        rates, accelerations = mock_motion_rates(t)
        for r in arm.readings(t, mock_ticks(t), rates, accelerations).values():
            pairs.append((abs(r.load_percent), r.current_a))
            assert r.current_a == pytest.approx(SERVO.current_a(r.load_percent, SUPPLY_V))
    loads, currents = zip(*sorted(pairs), strict=True)
    assert loads[-1] > 30.0 and np.all(np.diff(currents) >= -1e-12)


def test_thermal_model_is_a_first_order_lag() -> None:
    thermal = ThermalModel(ambient_c=25.0)
    current = 1.5
    steady = thermal.steady_c(current)
    assert steady == pytest.approx(25.0 + sts3215.HEATING_C_PER_A2 * current**2)
    tau = thermal.time_constant_s
    after_tau = thermal.step(25.0, current, tau)
    assert (after_tau - 25.0) / (steady - 25.0) == pytest.approx(1.0 - math.exp(-1.0))
    # However the time is cut, the same temperature (the lag is solved exactly).
    temperature = 25.0
    for _ in range(570):
        temperature = thermal.step(temperature, current, tau / 570)
    assert temperature == pytest.approx(after_tau)
    assert thermal.step(25.0, current, 5 * tau) == pytest.approx(steady, abs=0.01 * (steady - 25.0))
    # The SOARM-134 fit the figures come from: the 12 V servo at half its stall torque draws 1.44 A, +23 C
    # after an hour, +15 C after 10 minutes (docs/servo-health.md).
    half_stall = sts3215.NO_LOAD_CURRENT_A + 0.5 * (sts3215.STALL_CURRENT_A - sts3215.NO_LOAD_CURRENT_A)
    assert thermal.step(25.0, half_stall, 3600.0) - 25.0 == pytest.approx(23.0, abs=0.5)
    assert thermal.step(25.0, half_stall, 600.0) - 25.0 == pytest.approx(15.0, abs=0.5)
    # Plausible for an STS3215: minutes, not seconds or hours.
    assert 120.0 <= tau <= 1800.0


def test_temperature_rises_with_the_time_constant_and_falls_when_the_load_goes() -> None:
    heavy = PhysicalServoConfig(payload_kg=0.15, speedup={"shoulder_lift": 60.0})
    arm = PhysicalArm(heavy, ArmDynamics(payload_model(heavy.payload_kg)))
    tau_s = sts3215.THERMAL_TIME_CONSTANT_S / 60.0  # 9.5 s of the clock at 60x
    first = arm.readings(0.0, STRETCHED, STILL, STILL)["shoulder_lift"]
    assert first.temperature_c == 25.0  # starts at the ambient
    steady = ThermalModel().steady_c(first.current_a)
    assert steady > 60.0  # held out with 150 g the shoulder would pass the warning line
    for k in range(1, round(tau_s * 10) + 1):
        reading = arm.readings(k / 10, STRETCHED, STILL, STILL)["shoulder_lift"]
    assert (reading.temperature_c - 25.0) / (steady - 25.0) == pytest.approx(1.0 - math.exp(-1.0), abs=0.01)
    # The servos that hold nothing stay at the ambient: no speed-up, and little current.
    assert arm.temperatures_c["shoulder_pan"] == pytest.approx(25.0, abs=0.1)
    # Folded, the load is gone: the shoulder cools towards its no-load steady state.
    hot = reading.temperature_c
    t0 = round(tau_s * 10) + 1
    cooling = [arm.readings((t0 + k) / 10, FOLDED, STILL, STILL)["shoulder_lift"] for k in range(100)]
    temps = [r.temperature_c for r in cooling]
    assert all(b < a for a, b in zip([hot, *temps], temps, strict=False))
    cool_steady = ThermalModel().steady_c(cooling[-1].current_a)
    assert cool_steady < 35.0 < hot - 10.0
    assert (temps[-1] - cool_steady) / (hot - cool_steady) == pytest.approx(math.exp(-10.0 / tau_s), abs=0.02)


@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_physical_payloads_are_valid_edge_payloads(variant: str) -> None:
    units = Units.TICKS if variant == "ticks" else Units.DEGREES
    decoder = TelemetryDecoder(DecoderConfig(units=units))
    config = PhysicalServoConfig(payload_kg=0.1, speedup={"elbow_flex": 30.0})
    arm = PhysicalArm(config, ArmDynamics(payload_model(0.1)))
    mirror = PhysicalArm(config, ArmDynamics(payload_model(0.1)))  # the same readings, for comparison
    rng = random.Random(1)
    mock = make_payload("a", 0.0, variant, rng)
    for k in range(60):
        t = k / 10
        msg = make_payload("arm-001", t, variant, rng, timestamp_ms=TS0 + k * 100, physical=arm)
        assert set(msg) == set(mock) and set(msg["joints"]) == set(mock["joints"])
        for joint, fields in msg["joints"].items():
            assert set(fields) >= set(mock["joints"][joint]), joint
        telemetry = decoder.decode(encode(msg))  # raises on anything the agent would reject
        assert telemetry.device_id == "arm-001" and telemetry.timestamp_ms == TS0 + k * 100
        rates, accelerations = mock_motion_rates(t)
        expected = mirror.readings(t, mock_ticks(t), rates, accelerations)
        for joint, diag in telemetry.diagnostics.items():
            r = expected[joint]
            assert diag.load_percent == pytest.approx(r.load_percent, abs=0.051), joint  # 0.1 % units
            assert diag.current_a == pytest.approx(r.current_a, abs=0.00326), joint  # 6.5 mA units
            assert diag.temperature_c == round(r.temperature_c), joint  # whole degrees, like the register
            assert diag.voltage_v == pytest.approx(SUPPLY_V)
            assert diag.velocity_steps_s == round(r.velocity_steps_s), joint
        # The pose is the mock motion's, as the mock mode sends it.
        motion = mock_motion_ticks(t)
        assert telemetry.angles_rad["shoulder_lift"] == pytest.approx(
            (int(motion[1]) - so101.TICK_HOME) * RAD_PER_TICK, abs=0.11 if variant == "degrees" else 1e-9
        )


def test_a_fault_holding_a_joint_holds_it_still_in_physical_mode(dynamics: ArmDynamics) -> None:
    arm = PhysicalArm(PhysicalServoConfig(), dynamics)
    fault = ServoFault("contact", "elbow_flex", 1.0, 10.0)
    msg = make_payload("a", 3.0, "ticks", random.Random(2), servo_faults=(fault,), physical=arm)
    joint = msg["joints"]["elbow_flex"]
    assert joint["position"] == mock_ticks(1.0)[2] and joint["velocity"] == 0
    heat = ServoFault("heat", "wrist_flex", 0.0, 20.0)
    msg = make_payload("a", 10.0, "degrees", random.Random(2), servo_faults=(heat,), physical=arm)
    assert msg["joints"]["wrist_flex"]["temp"] > 60.0  # the fault's temperature wins over the model's


def test_settings_are_checked() -> None:
    assert parse_speedup("shoulder_lift:80") == ("shoulder_lift", 80.0)
    for text in ("shoulder_lift", "shoulder_lift:fast", "shoulder_lift:nan"):
        with pytest.raises(ValueError, match="JOINT:FACTOR"):
            parse_speedup(text)
    for kwargs, match in [
        ({"payload_kg": 160.0}, "in kilograms"),
        ({"payload_kg": -0.1}, "payload"),
        ({"speedup": {"elbow": 10.0}}, "not a joint"),
        ({"speedup": {"elbow_flex": 0.0}}, "above 0"),
        ({"ambient_c": 250.0}, "ambient"),
        ({"supply_v": 0.0}, "supply"),
        ({"servo_version": "9v"}, "7.4v"),
    ]:
        with pytest.raises(ValueError, match=match):
            PhysicalServoConfig(**kwargs)
    broker = BrokerConfig(url="mqtt://127.0.0.1:1883")
    with pytest.raises(ValueError, match="give one"):
        EdgeSimConfig(broker=broker, servos="physical", model_loads=True)
    with pytest.raises(ValueError, match="not one of mock, physical"):
        EdgeSimConfig(broker=broker, servos="real")
    with pytest.raises(ValueError, match="arm-009"):
        EdgeSimConfig(broker=broker, servos="physical", physical_by_device={"arm-009": PhysicalServoConfig()})
    with pytest.raises(ValueError, match="model_loads or physical"):
        arm = PhysicalArm(PhysicalServoConfig(), ArmDynamics(payload_model(0.0)))
        make_payload("a", 0.0, "ticks", random.Random(1), model_loads=ModelLoads(), physical=arm)


def test_the_demo_story_raises_the_alarm_on_the_hot_servo_only(robot: RobotModel) -> None:
    """The demo's settings through the agent's decoder, twin and alarm engine (no broker): the laden arm's
    shoulder raises the over-temperature warning and then the critical alarm, below the servo's 70 C cut-out;
    an arm carrying nothing raises no alarm at all."""
    hot = PhysicalServoConfig(payload_kg=STORY_PAYLOAD_KG, speedup={STORY_JOINT: STORY_SPEEDUP})
    arms = {
        "arm-001": PhysicalArm(hot, ArmDynamics(payload_model(STORY_PAYLOAD_KG))),
        "arm-002": PhysicalArm(PhysicalServoConfig(), ArmDynamics(payload_model(0.0))),
    }
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    twins = {device: DeviceTwin(robot, device) for device in arms}
    alarms = ServoAlarms()
    raised: dict[str, list[tuple[str, str, float]]] = {device: [] for device in arms}
    peak = 0.0
    for k in range(400):
        t, ts = k / 10, TS0 + k * 100
        for device, arm in arms.items():
            telemetry = decoder.decode(
                encode(make_payload(device, t, "ticks", random.Random(k), timestamp_ms=ts, physical=arm))
            )
            twins[device].apply(telemetry.angles_rad, ts)
            for event in alarms.evaluate(
                device,
                telemetry.diagnostics,
                twins[device].joint_torques,
                t,
                angles_rad=twins[device].joint_angles,
                timestamp_ms=ts,
            ):
                if event.state is AlarmState.ACTIVE:
                    raised[device].append((event.joint, str(event.kind), t))
        peak = max(peak, arms["arm-001"].temperatures_c[STORY_JOINT])
    assert raised["arm-002"] == []
    hot_kinds = {kind: t for joint, kind, t in raised["arm-001"] if joint == STORY_JOINT}
    assert {"over_temperature", "over_temperature_critical"} <= set(hot_kinds)
    assert hot_kinds["over_temperature"] < 20.0 < hot_kinds["over_temperature_critical"] < 30.0
    assert {joint for joint, _, _ in raised["arm-001"]} == {STORY_JOINT}
    assert 65.0 < peak < sts3215.MAX_TEMPERATURE_C


def _skipped_temperature(start: int, gap: int) -> tuple[float, float, float, EdgeSimulator]:
    """The story's servo at the tick after `gap` ticks skipped from tick `start`: (through the simulator's
    skip, stepped through every tick, given only that next sample), and the simulator."""
    hot = PhysicalServoConfig(payload_kg=STORY_PAYLOAD_KG, speedup={STORY_JOINT: STORY_SPEEDUP})
    simulator = EdgeSimulator(
        EdgeSimConfig(
            broker=BrokerConfig(url="mqtt://127.0.0.1:1883"),
            devices=["arm-001"],
            servos="physical",
            physical_by_device={"arm-001": hot},
        )
    )
    skipped = simulator._arms["arm-001"]
    every_tick = PhysicalArm(hot, ArmDynamics(payload_model(STORY_PAYLOAD_KG)))
    one_sample = PhysicalArm(hot, ArmDynamics(payload_model(STORY_PAYLOAD_KG)))
    period = 0.1
    for k in range(start):
        for physical in (skipped, every_tick, one_sample):
            physical_readings(k * period, physical)
    simulator._skip(start, gap, period)
    for k in range(start, start + gap):
        physical_readings(k * period, every_tick)
    t = (start + gap) * period
    return (
        physical_readings(t, skipped)[1][STORY_JOINT].temperature_c,
        physical_readings(t, every_tick)[1][STORY_JOINT].temperature_c,
        physical_readings(t, one_sample)[1][STORY_JOINT].temperature_c,
        simulator,
    )


def test_ticks_the_simulator_skips_still_heat_its_servos() -> None:
    """An edge simulator that fell over a second behind skips ticks unpublished; its servos ran on meanwhile,
    so their temperatures must come out as if every tick had been taken. The demo once read 70 C after 7 s
    skipped: the next sample's current had stood for the whole gap."""
    skipped, expected, naive, simulator = _skipped_temperature(150, 70)
    assert skipped == pytest.approx(expected, abs=1e-9)
    assert simulator.report.skipped_ticks == 70
    # What the gap did before: one sample's current over 7 s, far from the servo's path and past its cut-out.
    assert naive > sts3215.MAX_TEMPERATURE_C > expected + 5.0


def test_a_long_skip_is_stepped_on_a_bounded_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    """A large physical fleet must not fall further behind catching up: a skip takes at most
    MAX_SKIPPED_READINGS readings in all, spread over the gap, and still lands near the servo's path."""
    monkeypatch.setattr(simulator_module, "MAX_SKIPPED_READINGS", 10)
    calls: list[float] = []
    stepped = simulator_module.physical_readings

    def counted(t: float, physical: PhysicalArm, faults: tuple = ()) -> object:
        calls.append(t)
        return stepped(t, physical, faults)

    monkeypatch.setattr(simulator_module, "physical_readings", counted)
    skipped, expected, naive, _ = _skipped_temperature(150, 70)
    assert len(calls) == 10 and calls[-1] == pytest.approx(219 * 0.1)
    assert abs(skipped - expected) < 1.0 < naive - expected


@pytest.mark.slow
def test_the_cli_publishes_physical_servos_through_a_broker(
    mosquitto: MosquittoBroker, capsys: pytest.CaptureFixture[str]
) -> None:
    """`twin edge-sim --servos physical` end to end through a real mosquitto: every message decodes to the
    readings of an arm computed beside it, and the sped-up shoulder heats within the second."""
    received: list[bytes] = []
    sub = TelemetrySubscriber(
        BrokerConfig(url=mosquitto.url),
        topic_filters(DEFAULT_TOPIC_PREFIX, ["*"]),
        lambda _topic, payload, _at: received.append(payload),
    )
    sub.start()
    assert sub.wait_subscribed(15)
    args = ["--rate", "20", "--seconds", "1", "--payload", "0.1", "--thermal-speedup", "shoulder_lift:600"]
    try:
        code = main(["edge-sim", "--broker", mosquitto.url, "--servos", "physical", *args, "--json"])
        assert code == 0
        report = json.loads(capsys.readouterr().out)
        wait_for(lambda: len(received) >= report["published"] == 20, 15, "all 20 messages")
    finally:
        sub.stop(5)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    messages = sorted((decoder.decode(p) for p in received), key=lambda m: m.timestamp_ms)
    mirror = PhysicalArm(
        PhysicalServoConfig(payload_kg=0.1, speedup={"shoulder_lift": 600.0}), ArmDynamics(payload_model(0.1))
    )
    for k, message in enumerate(messages):
        t = k / 20
        rates, accelerations = mock_motion_rates(t)
        expected = mirror.readings(t, mock_ticks(t), rates, accelerations)
        for joint, diag in message.diagnostics.items():
            assert diag.load_percent == pytest.approx(expected[joint].load_percent, abs=0.051), (k, joint)
            assert diag.temperature_c == round(expected[joint].temperature_c), (k, joint)
    temps = [m.diagnostics["shoulder_lift"].temperature_c or 0.0 for m in messages]
    assert temps[0] == 25.0 and temps[-1] > 35.0  # 600x: a time constant of about a second
    # Settings of the physical mode without it, or naming no joint, are refused with the fix.
    assert main(["edge-sim", "--broker", mosquitto.url, "--payload", "0.2", "--seconds", "1"]) == 2
    assert "--payload and --thermal-speedup are settings of --servos physical" in capsys.readouterr().err
    bad = ["--servos", "physical", "--thermal-speedup", "elbow:5", "--seconds", "1"]
    assert main(["edge-sim", "--broker", mosquitto.url, *bad]) == 2
    assert "'elbow': not a joint" in capsys.readouterr().err
