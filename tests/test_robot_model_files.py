"""The bundled SO-101 MJCF against the upstream figures (docs/robot-model.md), as literals, not re-derived."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
from twin.robot import so101

ROBOT_DIR = Path(__file__).resolve().parents[1] / "robots" / "so101"
SO101_XML = ROBOT_DIR / "so101.xml"
SCENE_XML = ROBOT_DIR / "scene.xml"

# Every joint is a hinge about local +Z; ranges of the upstream "new calibration" model (docs/robot-model.md).
EXPECTED_RANGES = {
    "shoulder_pan": (-1.91986, 1.91986),
    "shoulder_lift": (-1.7453293, 1.7453293),
    "elbow_flex": (-1.69, 1.69),
    "wrist_flex": (-1.658063, 1.658063),
    "wrist_roll": (-2.7438473, 2.8412063),
    "gripper": (-0.174533, 1.7453292),
}
EXPECTED_CTRLRANGES = {
    "shoulder_pan": (-1.91986, 1.91986),
    "shoulder_lift": (-1.74533, 1.74533),
    "elbow_flex": (-1.69, 1.69),
    "wrist_flex": (-1.65806, 1.65806),
    "wrist_roll": (-2.74385, 2.84121),
    "gripper": (-0.17453, 1.74533),
}
# Joint axes in the world frame at q = 0 (docs/robot-model.md, "Frames and joints").
EXPECTED_WORLD_AXES_AT_ZERO = {
    "shoulder_pan": (0, 0, -1),
    "shoulder_lift": (0, 1, 0),
    "elbow_flex": (0, 1, 0),
    "wrist_flex": (0, 1, 0),
    "wrist_roll": (-1, 0, 0),
    "gripper": (0, -math.cos(0.0486795), -math.sin(0.0486795)),
}
EXPECTED_BODY_ORIGINS_AT_ZERO = {
    "shoulder": (0.0388, 0, 0.0624),
    "upper_arm": (0.0692, -0.0183, 0.1166),
    "lower_arm": (0.0972, -0.0183, 0.2292),
    "wrist": (0.2321, -0.0183, 0.2344),
    "gripper": (0.2932, -0.0002, 0.2344),
    "moving_jaw": (0.3166, 0.0176, 0.2555),
}
EXPECTED_MASSES = {
    "base": 0.147,
    "shoulder": 0.100006,
    "upper_arm": 0.103,
    "lower_arm": 0.104,
    "wrist": 0.079,
    "gripper": 0.087,
    "moving_jaw": 0.012,
}
# LeRobot degrees of a real rest pose (telemetry contract, Variant B example).
REST_POSE_DEG = {
    "shoulder_pan": 2.01,
    "shoulder_lift": -98.89,
    "elbow_flex": 97.27,
    "wrist_flex": 63.70,
    "wrist_roll": -3.44,
    "gripper": 4.83,
}
# Measured with this model (docs/robot-model.md): 0.395 s to stay within 2 % of a 0.5 rad shoulder_lift step.
SETTLE_LIMIT_S = 0.5


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(SCENE_XML))


def _set_pose(model: mujoco.MjModel, data: mujoco.MjData, angles: dict[str, float]) -> None:
    for name, value in angles.items():
        data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(model, data)


def test_both_files_load_and_scene_adds_floor_and_camera(model: mujoco.MjModel) -> None:
    arm = mujoco.MjModel.from_xml_path(str(SO101_XML))
    assert arm.nbody == len(so101.BODY_NAMES) + 1  # plus the world body
    floor = model.geom("floor")
    assert floor.type[0] == mujoco.mjtGeom.mjGEOM_PLANE
    assert model.geom_pos[floor.id][2] == 0.0
    # mj_name2id answers -1 for a missing name (model.camera() would raise instead of failing the assert).
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "overview") != -1
    assert model.nlight >= 1


def test_names_are_the_shared_constants(model: mujoco.MjModel) -> None:
    joints = [model.joint(i).name for i in range(model.njnt)]
    bodies = [model.body(i).name for i in range(1, model.nbody)]
    actuators = [model.actuator(i).name for i in range(model.nu)]
    assert tuple(joints) == so101.JOINT_NAMES
    assert tuple(bodies) == so101.BODY_NAMES
    assert tuple(actuators) == so101.JOINT_NAMES
    tcp = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, so101.TCP_SITE)
    assert tcp != -1
    # The tool centre point rides on the gripper body (the fixed jaw), not on a link it would lag behind.
    assert model.site_bodyid[tcp] == model.body("gripper").id


@pytest.mark.parametrize("joint", so101.JOINT_NAMES)
def test_joint_axis_range_and_dynamics(model: mujoco.MjModel, joint: str) -> None:
    j = model.joint(joint)
    assert j.type[0] == mujoco.mjtJoint.mjJNT_HINGE
    np.testing.assert_allclose(j.axis, (0, 0, 1))
    assert j.limited[0] == 1
    np.testing.assert_allclose(j.range, EXPECTED_RANGES[joint], atol=1e-9)
    np.testing.assert_allclose(j.range, so101.JOINT_RANGES_RAD[joint], atol=1e-9)
    dof = j.dofadr[0]
    assert model.dof_damping[dof] == pytest.approx(0.60)
    assert model.dof_frictionloss[dof] == pytest.approx(0.052)
    assert model.dof_armature[dof] == pytest.approx(0.028)


@pytest.mark.parametrize("joint", so101.JOINT_NAMES)
def test_position_actuator_per_joint(model: mujoco.MjModel, joint: str) -> None:
    act = model.actuator(joint)
    assert act.trntype[0] == mujoco.mjtTrn.mjTRN_JOINT
    assert act.trnid[0] == model.joint(joint).id
    # A position servo: force = kp * (ctrl - q) - kv * qdot.
    assert act.gainprm[0] == pytest.approx(998.22)
    assert act.biasprm[1] == pytest.approx(-998.22)
    assert act.biasprm[2] == pytest.approx(-2.731)
    assert act.ctrllimited[0] == 1
    np.testing.assert_allclose(act.ctrlrange, EXPECTED_CTRLRANGES[joint], atol=1e-9)
    assert act.forcelimited[0] == 1
    np.testing.assert_allclose(act.forcerange, (-2.94, 2.94))


def test_options(model: mujoco.MjModel) -> None:
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert model.opt.timestep == pytest.approx(0.005)
    assert model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert model.opt.impratio == pytest.approx(10)


def test_masses_and_inertias(model: mujoco.MjModel) -> None:
    masses = {name: model.body(name).mass[0] for name in so101.BODY_NAMES}
    assert masses == pytest.approx(EXPECTED_MASSES)
    assert sum(masses.values()) == pytest.approx(0.632, abs=1e-4)
    # The gripper's full inertia has off-diagonal terms; the compiler must keep its principal moments.
    full = np.array(
        [
            [2.75087e-5, -3.35241e-7, -5.7352e-6],
            [-3.35241e-7, 4.33657e-5, -5.17847e-8],
            [-5.7352e-6, -5.17847e-8, 3.45059e-5],
        ]
    )
    np.testing.assert_allclose(
        np.sort(model.body("gripper").inertia), np.sort(np.linalg.eigvalsh(full)), rtol=1e-4
    )
    np.testing.assert_allclose(model.body("gripper").ipos, (0.000213627, 0.000245138, -0.025187), atol=1e-9)


def test_zero_pose_frames_and_tcp(model: mujoco.MjModel) -> None:
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    for body, expected in EXPECTED_BODY_ORIGINS_AT_ZERO.items():
        np.testing.assert_allclose(data.body(body).xpos, expected, atol=1e-3, err_msg=body)
    for joint, expected in EXPECTED_WORLD_AXES_AT_ZERO.items():
        np.testing.assert_allclose(data.xaxis[model.joint(joint).id], expected, atol=1e-3, err_msg=joint)
    np.testing.assert_allclose(data.site(so101.TCP_SITE).xpos, (0.3914, 0, 0.2265), atol=0.01)


def test_lerobot_rest_pose_puts_the_tip_on_the_table(model: mujoco.MjModel) -> None:
    data = mujoco.MjData(model)
    _set_pose(model, data, {name: math.radians(deg) for name, deg in REST_POSE_DEG.items()})
    tcp = data.site(so101.TCP_SITE).xpos
    assert abs(tcp[2] - (-0.009)) < 0.02, tcp
    # The folded arm stays in front of its base, within reach of the table.
    assert 0.05 < tcp[0] < 0.25, tcp


def test_positive_shoulder_lift_tilts_the_arm_forward_and_down(model: mujoco.MjModel) -> None:
    data = mujoco.MjData(model)
    _set_pose(model, data, {})
    tip_zero = data.site(so101.TCP_SITE).xpos.copy()
    _set_pose(model, data, {"shoulder_lift": 0.5})
    tip_lifted = data.site(so101.TCP_SITE).xpos
    assert tip_lifted[2] < tip_zero[2] - 0.05


def test_position_actuator_settles_a_shoulder_lift_step(model: mujoco.MjModel) -> None:
    data = mujoco.MjData(model)
    lift = model.joint("shoulder_lift").qposadr[0]
    for _ in range(200):  # let gravity sag settle at the zero target first
        mujoco.mj_step(model, data)
    start = data.qpos[lift]
    step = 0.5
    data.ctrl[model.actuator("shoulder_lift").id] = step
    t0 = data.time
    times, angles = [], []
    while data.time - t0 < 2.0:
        mujoco.mj_step(model, data)
        times.append(data.time - t0)
        angles.append(data.qpos[lift])
    err = np.abs(np.array(angles) - step)
    outside = np.nonzero(err > 0.02 * abs(step - start))[0]
    settle = times[outside[-1] + 1] if outside.size else times[0]
    assert settle < SETTLE_LIMIT_S, f"settled after {settle:.3f} s"
    assert err[-1] < 0.005  # gravity offset of a kp ~ 1000 servo stays well under a degree


def test_the_servo_ids_alarms_name_are_lerobots() -> None:
    # LeRobot's calibration file records each motor's bus id; alarms name the servo by it (so101.servo_name).
    calibration = json.loads((ROBOT_DIR / "calibration" / "so101_follower_example.json").read_text())
    assert {joint: entry["id"] for joint, entry in calibration.items()} == so101.MOTOR_IDS
    assert so101.servo_name("gripper") == "gripper servo (motor id 6)"
    assert so101.servo_name("tool") == "tool servo"  # a joint outside the six keeps its name alone
