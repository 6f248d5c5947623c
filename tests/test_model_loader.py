"""twin.robot.model: the bundled SO-101 loads; bad models fail with errors that name the problem and the
fix."""

from __future__ import annotations

import os

# The first module to import mujoco binds its GL backend; headless, so that later render tests work too.
os.environ.setdefault("MUJOCO_GL", "egl")

import logging
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import copy_bundled_scene
from twin.core.modes import TwinMode
from twin.core.twin import DeviceTwin
from twin.robot import model as model_module
from twin.robot import so101
from twin.robot.model import ModelError, RobotModel, default_model_path, precompile


def chain_mjcf(*, site: str | None = None, actuators: str = "position", names: tuple[str, ...] = ()) -> str:
    """A minimal serial chain with the SO-101 joint names (or `names`), an optional tip site and actuators."""
    joints = names or so101.JOINT_NAMES
    bodies = ""
    closing = ""
    for i, joint in enumerate(joints):
        axis = "0 0 1" if i in (0, 4) else "0 1 0"
        bodies += (
            f'<body name="link{i}" pos="0 0 0.05"><joint name="{joint}" axis="{axis}" range="-1.5 1.5"/>'
            f'<geom type="capsule" fromto="0 0 0 0 0 0.05" size="0.01" mass="0.1"/>'
        )
        closing += "</body>"
    tip = f'<site name="{site}" pos="0 0 0.05"/>' if site else ""
    acts = ""
    if actuators == "position":
        acts = "".join(f'<position name="servo{i}" joint="{j}" kp="50"/>' for i, j in enumerate(joints))
    elif actuators == "motor":
        acts = "".join(f'<motor joint="{j}"/>' for j in joints)
    return (
        '<mujoco><compiler autolimits="true"/><worldbody>'
        f"{bodies}{tip}{closing}</worldbody><actuator>{acts}</actuator></mujoco>"
    )


def write(tmp_path: Path, xml: str, name: str = "arm.xml") -> Path:
    path = tmp_path / name
    path.write_text(xml)
    return path


def test_default_path_is_the_bundled_scene() -> None:
    path = default_model_path()
    assert path.name == "scene.xml"
    assert path.parent.name == "so101"
    assert path.is_file()


def test_bundled_model_loads_with_everything_the_twin_needs() -> None:
    robot = RobotModel.load()
    assert robot.path == default_model_path()
    assert robot.joint_names == so101.JOINT_NAMES
    assert set(robot.joint_ranges) == set(so101.JOINT_NAMES)
    for name in so101.JOINT_NAMES:
        lo, hi = robot.joint_ranges[name]
        assert (lo, hi) == pytest.approx(so101.JOINT_RANGES_RAD[name], abs=1e-6)
        jid = robot.joint_ids[name]
        assert robot.qpos_addr[name] == robot.model.jnt_qposadr[jid]
        assert robot.dof_addr[name] == robot.model.jnt_dofadr[jid]
        act = robot.actuator_ids[name]
        assert robot.model.actuator_trnid[act, 0] == jid
    assert robot.missing_actuators == ()
    assert robot.tcp_site == so101.TCP_SITE
    assert list(robot.body_ids) == list(so101.BODY_NAMES)
    assert "overview" in robot.camera_names
    # The inverse-dynamics copy must not share option storage with the simulated model.
    assert robot.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONSTRAINT == 0
    assert robot.inverse_model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONSTRAINT


def test_a_precompiled_model_is_taken_by_the_next_load_only(tmp_path: Path) -> None:
    # The workers' fork server compiles the bundled scene ahead (twin.service.worker_preload); each forked
    # worker's first load takes that model, any later load compiles the file as it is then.
    path = tmp_path / "arm.xml"
    path.write_text(chain_mjcf(site="tcp"))
    precompile(tmp_path / "." / "arm.xml")  # the same file by another spelling of its path
    compiled = model_module._PRECOMPILED[path.resolve()]
    first = RobotModel.load(path)
    assert first.model is compiled
    assert path.resolve() not in model_module._PRECOMPILED
    second = RobotModel.load(path)
    assert second.model is not compiled
    assert second.joint_names == first.joint_names == so101.JOINT_NAMES


def test_a_model_that_fails_to_precompile_is_reported_by_its_load(tmp_path: Path) -> None:
    path = tmp_path / "broken.xml"
    path.write_text("<mujoco><worldbody><body></mujoco>")
    precompile(path)  # no error here: nothing is left for the load to take
    assert path.resolve() not in model_module._PRECOMPILED
    with pytest.raises(ModelError, match="could not be loaded by MuJoCo"):
        RobotModel.load(path)


def test_renamed_joint_is_named_in_the_error(tmp_path: Path) -> None:
    copy_bundled_scene(tmp_path)
    arm = tmp_path / "so101.xml"
    text = arm.read_text()
    assert 'joint name="elbow_flex"' in text
    arm.write_text(
        text.replace('joint name="elbow_flex"', 'joint name="elbow"').replace(
            'joint="elbow_flex"', 'joint="elbow"'
        )
    )
    with pytest.raises(ModelError) as err:
        RobotModel.load(tmp_path / "scene.xml")
    message = str(err.value)
    assert "missing joints: elbow_flex" in message
    assert "elbow," in message  # what the model has instead, so the user sees the typo
    assert "[twin] model" in message
    assert str(tmp_path / "scene.xml") in message


def test_slide_joint_is_reported_as_not_hinge(tmp_path: Path) -> None:
    xml = chain_mjcf().replace('<joint name="wrist_flex"', '<joint type="slide" name="wrist_flex"')
    with pytest.raises(ModelError, match=r"not hinge joints: wrist_flex \(is slide\)"):
        RobotModel.load(write(tmp_path, xml))


def test_nonexistent_path(tmp_path: Path) -> None:
    missing = tmp_path / "nope" / "scene.xml"
    with pytest.raises(ModelError) as err:
        RobotModel.load(missing)
    assert str(missing) in str(err.value)
    assert "[twin] model" in str(err.value)


def test_bad_xml_carries_mujocos_reason(tmp_path: Path) -> None:
    path = write(tmp_path, "<mujoco><worldbody><body></mujoco>")
    with pytest.raises(ModelError) as err:
        RobotModel.load(path)
    assert "could not be loaded by MuJoCo" in str(err.value)
    assert "[twin] model" in str(err.value)
    assert isinstance(err.value, ValueError)


def test_no_tcp_site_falls_back_to_a_body_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="twin.robot.model"):
        robot = RobotModel.load(write(tmp_path, chain_mjcf()))
    assert robot.tcp_site is None
    assert robot.tcp_site_id is None
    # No body called "gripper" here: the body the gripper joint moves stands in.
    gripper_body = robot.model.jnt_bodyid[robot.joint_ids[so101.GRIPPER]]
    assert robot.tcp_body_id == gripper_body
    assert any("no TCP site" in r.getMessage() for r in caplog.records)
    twin = DeviceTwin(robot, "arm")
    assert twin.tcp_position == pytest.approx(twin.data.xpos[gripper_body])
    # The chain is straight up at q = 0: six links of 5 cm.
    assert twin.tcp_position == pytest.approx([0, 0, 0.30])
    # User bodies are not the SO-101's: body_poses returns the ones that exist (none here).
    assert twin.body_poses() == {}


def test_menagerie_site_name_is_found_and_a_configured_name_wins(tmp_path: Path) -> None:
    path = write(tmp_path, chain_mjcf(site="gripperframe"))
    assert RobotModel.load(path).tcp_site == "gripperframe"
    custom = write(tmp_path, chain_mjcf(site="fingertip"), "custom.xml")
    robot = RobotModel.load(custom, tcp_site="fingertip")
    assert robot.tcp_site == "fingertip"
    assert robot.tcp_site_id == robot.model.site("fingertip").id


def test_actuators_are_found_by_target_joint_not_by_name(tmp_path: Path) -> None:
    robot = RobotModel.load(write(tmp_path, chain_mjcf(actuators="position")))
    assert robot.missing_actuators == ()
    for name in so101.JOINT_NAMES:
        assert robot.model.actuator(robot.actuator_ids[name]).name.startswith("servo")
        assert robot.model.actuator_trnid[robot.actuator_ids[name], 0] == robot.joint_ids[name]


def test_missing_position_actuators_only_block_physics_mode(tmp_path: Path) -> None:
    for kind in ("motor", "none"):
        robot = RobotModel.load(write(tmp_path, chain_mjcf(actuators=kind), f"{kind}.xml"))
        assert robot.missing_actuators == so101.JOINT_NAMES
        DeviceTwin(robot, "arm", TwinMode.KINEMATIC)  # fine without actuators
        with pytest.raises(ModelError) as err:
            DeviceTwin(robot, "arm", TwinMode.PHYSICS)
        assert "physics mode" in str(err.value)
        assert "shoulder_pan" in str(err.value)


def test_holding_torques_read_the_joints_wherever_the_model_keeps_them(tmp_path: Path) -> None:
    """The batch of holding torques indexes the joints by a slice where their addresses are consecutive and
    by a list otherwise: both give exactly what one inverse_dynamics call per pose gives."""
    reverse = RobotModel.load(
        write(tmp_path, chain_mjcf(site="tcp", names=tuple(reversed(so101.JOINT_NAMES))), "reverse.xml")
    )
    box = '<body name="box" pos="1 0 0"><freejoint/><geom type="box" size=".01 .01 .01"/></body>'
    floating = RobotModel.load(
        write(tmp_path, chain_mjcf(site="tcp").replace("<worldbody>", f"<worldbody>{box}", 1), "floating.xml")
    )
    assert reverse.joint_indexes == ([5, 4, 3, 2, 1, 0], [5, 4, 3, 2, 1, 0])
    assert floating.joint_indexes == (slice(7, 13), slice(6, 12))
    rng = np.random.default_rng(5)
    for robot in (reverse, floating, RobotModel.load()):
        lo, hi = np.array(robot.joint_tables.lo), np.array(robot.joint_tables.hi)
        poses = [tuple(p) for p in rng.uniform(lo, hi, (8, 6)).tolist()]
        assert robot.holding_torques(poses) == [robot.inverse_dynamics(p) for p in poses]
