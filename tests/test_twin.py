"""twin.core.twin.DeviceTwin on the bundled SO-101 (and a weightless variant for the torque baseline)."""

from __future__ import annotations

import os

# The first module to import mujoco binds its GL backend; headless, so that later render tests work too.
os.environ.setdefault("MUJOCO_GL", "egl")

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
from twin.core.modes import TwinMode
from twin.core.twin import DeviceTwin, TwinSnapshot
from twin.robot import so101
from twin.robot.model import RobotModel

# The LeRobot rest pose from the edge's docs (degrees), fed to the model as radians: the tip is on the table.
REST_DEG = {
    "shoulder_pan": 2.01,
    "shoulder_lift": -98.89,
    "elbow_flex": 97.27,
    "wrist_flex": 63.70,
    "wrist_roll": -3.44,
    "gripper": 0.0,
}
REST = {name: REST_DEG[name] * so101.DEG for name in so101.JOINT_NAMES}
ZERO = dict.fromkeys(so101.JOINT_NAMES, 0.0)


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


def inside(robot: RobotModel, angles: dict[str, float]) -> dict[str, float]:
    return {n: min(max(v, robot.joint_ranges[n][0]), robot.joint_ranges[n][1]) for n, v in angles.items()}


# -- kinematic mode --------------------------------------------------------------------------------


def test_kinematic_apply_sets_angles_exactly(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    pose = {
        "shoulder_pan": 0.3,
        "shoulder_lift": -0.7,
        "elbow_flex": 1.1,
        "wrist_flex": -0.25,
        "wrist_roll": 2.0,
        "gripper": 0.9,
    }
    assert twin.apply(pose, 1000) is True
    assert twin.joint_angles == pose  # exact, no filtering
    assert twin.targets == pose
    for name, value in pose.items():
        assert twin.data.qpos[robot.qpos_addr[name]] == value
    assert (twin.applied, twin.ignored_stale, twin.clamped) == (1, 0, 0)
    assert twin.last_timestamp_ms == 1000
    # Forward kinematics ran: the TCP matches an independent FK of the same pose.
    data = mujoco.MjData(robot.model)
    for name, value in pose.items():
        data.qpos[robot.qpos_addr[name]] = value
    mujoco.mj_forward(robot.model, data)
    assert twin.tcp_position == pytest.approx(data.site_xpos[robot.tcp_site_id], abs=1e-12)


def test_rest_pose_puts_the_tcp_on_the_floor(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(REST, 1)
    x, y, z = twin.tcp_position
    assert abs(z) < 0.03, f"tcp z = {z:.4f} m, expected on the floor"
    assert 0.10 < x < 0.25  # in front of the base, folded back from the 0.39 m reach at q = 0
    assert abs(y) < 0.03
    # elbow_flex 97.27 deg is past the model's 96.8 deg (upstream's 5 deg calibration margin): clamped.
    assert twin.clamped == 1
    assert twin.joint_angles["elbow_flex"] == robot.joint_ranges["elbow_flex"][1]


def test_out_of_range_angles_are_clamped_and_counted(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    lo_pan, hi_pan = robot.joint_ranges["shoulder_pan"]
    lo_grip, _ = robot.joint_ranges["gripper"]
    twin.apply(dict(ZERO, shoulder_pan=5.0, gripper=-3.0), 1)
    assert twin.joint_angles["shoulder_pan"] == hi_pan
    assert twin.joint_angles["gripper"] == lo_grip
    assert twin.clamped == 2
    twin.apply(dict(ZERO, shoulder_pan=-5.0), 2)
    assert twin.joint_angles["shoulder_pan"] == lo_pan
    assert twin.clamped == 3
    twin.apply(dict(ZERO, shoulder_pan=hi_pan), 3)  # exactly at the limit is not a clamp
    assert twin.clamped == 3


def test_stale_and_duplicate_timestamps_are_ignored_and_counted(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    assert twin.apply(dict(ZERO, elbow_flex=0.5), 2000)
    before = (twin.joint_angles, twin.joint_torques, twin.tcp_position.copy())
    assert twin.apply(dict(ZERO, elbow_flex=-0.5), 2000) is False  # duplicate
    assert twin.apply(dict(ZERO, elbow_flex=-0.9), 1999) is False  # out of order
    assert twin.joint_angles == before[0]
    assert twin.joint_torques == before[1]
    assert np.array_equal(twin.tcp_position, before[2])
    assert (twin.applied, twin.ignored_stale, twin.last_timestamp_ms) == (1, 2, 2000)
    assert twin.apply(dict(ZERO, elbow_flex=-0.5), 2001) is True
    assert twin.joint_angles["elbow_flex"] == -0.5
    assert (twin.applied, twin.ignored_stale) == (2, 2)


def test_missing_joints_keep_their_target_and_unknown_names_are_ignored(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(dict(ZERO, wrist_flex=0.4), 1)
    twin.apply({"elbow_flex": 0.2, "not_a_joint": 9.0}, 2)
    assert twin.joint_angles == dict(ZERO, wrist_flex=0.4, elbow_flex=0.2)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_angle_raises_and_changes_nothing(robot: RobotModel, bad: float) -> None:
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(dict(ZERO, shoulder_pan=0.1), 1)
    with pytest.raises(ValueError, match="elbow_flex"):
        twin.apply(dict(ZERO, shoulder_pan=0.7, elbow_flex=bad), 2)
    assert twin.joint_angles == dict(ZERO, shoulder_pan=0.1)
    assert (twin.applied, twin.last_timestamp_ms) == (1, 1)


def test_body_poses_are_world_frame_copies(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(REST, 1)
    poses = twin.body_poses()
    assert list(poses) == list(so101.BODY_NAMES)
    for name, (pos, quat) in poses.items():
        bid = robot.body_ids[name]
        assert pos.shape == (3,) and quat.shape == (4,)
        assert np.array_equal(pos, twin.data.xpos[bid])
        assert np.array_equal(quat, twin.data.xquat[bid])
        assert np.linalg.norm(quat) == pytest.approx(1.0)
    assert np.array_equal(poses["base"][0], [0, 0, 0])
    # Copies: a later apply does not move what the caller already holds.
    held = poses["wrist"][0].copy()
    twin.apply(ZERO, 2)
    assert np.array_equal(poses["wrist"][0], held)
    assert not np.allclose(twin.body_poses()["wrist"][0], held)


# -- inverse dynamics ------------------------------------------------------------------------------


def independent_inverse(path: Path, angles: dict[str, float]) -> dict[str, float]:
    """mj_inverse on a fresh compile of the same MJCF, qvel = qacc = 0, constraints off."""
    inverse_model = mujoco.MjModel.from_xml_path(str(path))
    inverse_model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    data = mujoco.MjData(inverse_model)
    for name, value in angles.items():
        data.qpos[inverse_model.joint(name).qposadr[0]] = value
    mujoco.mj_inverse(inverse_model, data)
    return {name: float(data.qfrc_inverse[inverse_model.joint(name).dofadr[0]]) for name in angles}


def test_gravity_torques_at_zero_pose(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(dict(ZERO, shoulder_pan=0.4), 1)  # pan a little so the test does not start at qpos0
    twin.apply(ZERO, 2)
    torques = twin.joint_torques
    assert set(torques) == set(so101.JOINT_NAMES)
    # Upper arm up, forearm horizontal: lift and elbow hold the forearm's weight, ~0.5 N m each; the pan axis
    # is vertical, so gravity gives it nothing.
    assert abs(torques["shoulder_lift"]) > 0.2
    assert abs(torques["elbow_flex"]) > 0.2
    assert torques["shoulder_pan"] == pytest.approx(0.0, abs=1e-9)
    assert torques == pytest.approx(independent_inverse(robot.path, ZERO), abs=1e-9)


def test_torques_follow_each_applied_pose(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    for ts, pose in enumerate([REST, ZERO, dict(ZERO, shoulder_lift=0.8, wrist_flex=-1.0)], start=1):
        twin.apply(pose, ts)
        assert twin.joint_torques == pytest.approx(
            independent_inverse(robot.path, inside(robot, pose)), abs=1e-9
        )


def test_zero_gravity_gives_zero_torques(robot: RobotModel, tmp_path: Path) -> None:
    text = Path(robot.path).with_name("so101.xml").read_text()
    scene = tmp_path / "weightless.xml"
    (tmp_path / "so101.xml").write_text(text)
    (tmp_path / "meshes").symlink_to(Path(robot.path).with_name("meshes"))  # meshdir is relative to it
    scene.write_text('<mujoco><include file="so101.xml"/><option gravity="0 0 0"/></mujoco>')
    weightless = RobotModel.load(scene)
    twin = DeviceTwin(weightless, "arm-001")
    twin.apply(dict(ZERO, shoulder_lift=0.8, elbow_flex=-0.6), 1)
    assert max(abs(t) for t in twin.joint_torques.values()) < 1e-9


# -- physics mode ----------------------------------------------------------------------------------


def test_physics_first_message_starts_at_the_measured_pose(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001", TwinMode.PHYSICS)
    pose = dict(ZERO, shoulder_lift=0.5, elbow_flex=-0.5)
    twin.apply(pose, 1)
    assert twin.joint_angles == pose
    for name, value in pose.items():
        assert twin.data.ctrl[robot.actuator_ids[name]] == value


def test_physics_step_converges_to_a_step_target(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001", TwinMode.PHYSICS)
    twin.apply(ZERO, 1)
    twin.step(0.5)
    target = dict(ZERO, shoulder_lift=0.5, elbow_flex=-0.5)
    twin.apply(target, 2)
    twin.step(0.05)
    # Not teleported: 50 ms in, the joint is still on its way.
    assert 0.0 < twin.joint_angles["shoulder_lift"] < 0.4
    # Measured: ~20 % overshoot at 0.2 s, inside 0.005 rad by 0.45 s. Documented bound: 5 mrad within 0.5 s.
    twin.step(0.45)
    for name in ("shoulder_lift", "elbow_flex"):
        assert twin.joint_angles[name] == pytest.approx(target[name], abs=0.005)
    assert twin.data.time == pytest.approx(1.0, abs=robot.model.opt.timestep / 2)


def test_physics_gravity_sag_matches_holding_torque_over_kp(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001", TwinMode.PHYSICS)
    twin.apply(ZERO, 1)
    twin.step(1.0)
    angles = twin.joint_angles
    torques = twin.joint_torques
    for name in ("shoulder_lift", "elbow_flex"):
        kp = robot.model.actuator_gainprm[robot.actuator_ids[name], 0]
        # Measured steady-state error ~0.54 mrad (lift) and ~0.45 mrad (elbow): the servo's P term balances
        # the weight, err = -tau/kp. Joint friction (0.052 N m) can hold up to 0.052/kp of it: the tolerance.
        friction = robot.model.dof_frictionloss[robot.dof_addr[name]]
        assert abs(angles[name]) > 2e-4, "gravity must pull the arm off its target"
        assert angles[name] == pytest.approx(-torques[name] / kp, abs=friction / kp + 2e-5)


def test_step_runs_whole_timesteps_and_carries_the_remainder(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001", TwinMode.PHYSICS)
    dt = robot.model.opt.timestep
    twin.step(dt * 0.6)
    assert twin.data.time == 0.0
    twin.step(dt * 0.6)
    assert twin.data.time == pytest.approx(dt)
    twin.step(0.0)
    twin.step(-1.0)
    assert twin.data.time == pytest.approx(dt)


def test_kinematic_step_is_a_no_op(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(dict(ZERO, shoulder_lift=0.6), 1)
    twin.step(1.0)
    assert twin.data.time == 0.0
    assert twin.joint_angles["shoulder_lift"] == 0.6


# -- snapshots -------------------------------------------------------------------------------------


def test_snapshot_is_an_immutable_copy(robot: RobotModel) -> None:
    twin = DeviceTwin(robot, "arm-007")
    twin.apply(REST, 10)
    snap = twin.snapshot()
    assert isinstance(snap, TwinSnapshot)
    assert snap.device_id == "arm-007"
    assert snap.timestamp_ms == 10
    assert snap.joint_angles == twin.joint_angles
    assert snap.targets == twin.targets
    assert snap.joint_torques == twin.joint_torques
    assert snap.tcp_position == tuple(twin.tcp_position)
    assert all(type(v) is float for v in snap.tcp_position)
    assert (snap.applied, snap.clamped, snap.mode) == (1, 1, TwinMode.KINEMATIC)
    frozen = (dict(snap.joint_angles), dict(snap.joint_torques), snap.tcp_position)
    twin.apply(dict(ZERO, shoulder_pan=1.0), 11)
    assert (snap.joint_angles, snap.joint_torques, snap.tcp_position) == frozen
    assert snap.timestamp_ms == 10
    with pytest.raises(AttributeError):
        snap.timestamp_ms = 11  # type: ignore[misc]


def test_holding_torques_are_reused_only_for_a_pose_that_close(robot: RobotModel) -> None:
    from twin.core.twin import HOLDING_POSE_RAD

    pose = inside(robot, {"shoulder_pan": 0.3, "shoulder_lift": -0.8, "elbow_flex": 0.9, "wrist_flex": 0.2})
    twin = DeviceTwin(robot, "arm-001")
    twin.apply(pose, 1)
    first = dict(twin.holding_torques_when_read()())
    assert first == twin.joint_torques  # the pose's own inverse dynamics
    # An encoder step or two away (every joint within HOLDING_POSE_RAD): the same torques, not recomputed.
    near = {n: v + 0.8 * HOLDING_POSE_RAD for n, v in pose.items()}
    twin.apply(near, 2)
    assert dict(twin.holding_torques_when_read()()) == first
    assert twin.joint_torques != first  # readers of the twin still get the exact pose's
    # One joint further than that: computed afresh, for this pose.
    far = {**near, "shoulder_lift": pose["shoulder_lift"] + 3 * HOLDING_POSE_RAD}
    twin.apply(far, 3)
    assert dict(twin.holding_torques_when_read()()) == twin.joint_torques != first


def test_holding_torques_of_many_poses_are_inverse_dynamics_of_each(robot: RobotModel) -> None:
    """The batch loop gives exactly what one call per pose gives, also after a caller left a velocity and an
    acceleration in the shared workspace (which would add inertia and damping if the loop kept them)."""
    rng = np.random.default_rng(3)
    lo = np.array(robot.joint_tables.lo)
    hi = np.array(robot.joint_tables.hi)
    poses = [tuple(p) for p in rng.uniform(lo, hi, (40, 6)).tolist()]
    robot.inverse_dynamics(poses[0], velocity=[1.0] * 6, acceleration=[5.0] * 6)
    assert robot.holding_torques(poses) == [robot.inverse_dynamics(p) for p in poses]
    assert robot.holding_torques([]) == []


def test_holding_torques_of_sources_are_what_each_call_gives_and_kept_the_same_way(robot: RobotModel) -> None:
    """`holding_torques_of` (the model check's batch) against each source called by itself: the same values
    in the same order, the twin's kept torques reused within HOLDING_POSE_RAD (the same object), a fresh pose
    computed and kept, the snapshot of that pose sharing them; other sources taken as they are."""
    from twin.core.twin import HOLDING_POSE_RAD, holding_torques_of

    rng = np.random.default_rng(4)
    lo = np.array(robot.joint_tables.lo)
    hi = np.array(robot.joint_tables.hi)
    twins = [DeviceTwin(robot, f"arm-{i}") for i in range(6)]
    for twin, pose in zip(twins, rng.uniform(lo, hi, (6, 6)).tolist(), strict=True):
        twin.apply(dict(zip(so101.JOINT_NAMES, pose, strict=True)), 1)
    kept = twins[0].holding_torques_at(twins[0].target_values)()  # twin 0 has its torques kept
    near = {n: v + 0.5 * HOLDING_POSE_RAD for n, v in twins[0].targets.items()}
    twins[0].apply(near, 2)
    snapshots = [twin.snapshot() for twin in twins[:4]]  # twins 4 and 5 have none: nothing shares theirs
    given = {"shoulder_pan": 0.25}
    called = {"shoulder_pan": -0.5}
    sources = [twin.holding_torques_at(twin.target_values) for twin in twins]
    sources[3:3] = [given, lambda: called]
    got = holding_torques_of(sources)
    assert got[0] is kept  # reused, as the call would
    assert got[3] is given and got[4] is called
    fresh = got[1:3] + got[5:]
    assert fresh == [robot.inverse_dynamics(twin.target_values) for twin in twins[1:]]
    for twin, torques in zip(twins[1:], fresh, strict=True):
        # Kept for the next message of a pose that close.
        assert twin.holding_torques_at(twin.target_values)() is torques
    for snapshot, torques in zip(snapshots[1:], fresh, strict=False):
        assert snapshot.figures._torques is torques  # the snapshot of the pose reads them for free
    # Asked again: every twin's kept torques, nothing computed.
    again = holding_torques_of([twin.holding_torques_at(twin.target_values) for twin in twins])
    assert all(a is b for a, b in zip(again, [kept, *fresh], strict=True))
