"""SessionRecorder: the recorded USD stage, reopened with usd-core, reproduces MuJoCo's forward kinematics."""

from __future__ import annotations

import itertools
import logging
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import full_disk
from pxr import Gf, Sdf, Usd, UsdGeom
from twin.core.twin import DeviceTwin
from twin.output.recorder import SessionRecorder, default_asset_path, sanitise_prim_name
from twin.robot import so101
from twin.robot.model import RobotModel

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "robots" / "so101" / "scene.xml"
BODY_REL = {  # where the bundled asset (mujoco-usd-converter layout) nests the bodies
    "base": "Geometry/base",
    "shoulder": "Geometry/base/shoulder",
    "upper_arm": "Geometry/base/shoulder/upper_arm",
    "lower_arm": "Geometry/base/shoulder/upper_arm/lower_arm",
    "wrist": "Geometry/base/shoulder/upper_arm/lower_arm/wrist",
    "gripper": "Geometry/base/shoulder/upper_arm/lower_arm/wrist/gripper",
    "moving_jaw": "Geometry/base/shoulder/upper_arm/lower_arm/wrist/gripper/moving_jaw",
}
# Decoded angle sets (rad, JOINT_NAMES order): zero, the LeRobot rest pose, and two arbitrary in-range poses.
ANGLE_SETS = [
    (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    tuple(math.radians(d) for d in (2.01, -98.89, 97.27, 63.70, -3.44, 4.83)),
    (1.2, -0.7, 1.1, -1.3, 2.5, 1.5),
    (-1.8, 1.6, -1.6, 1.6, -2.7, -0.1),
]


def _fk_poses(model: mujoco.MjModel, data: mujoco.MjData, angles) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    for name, value in zip(so101.JOINT_NAMES, angles, strict=True):
        data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(model, data)
    return {name: (data.body(name).xpos.copy(), data.body(name).xquat.copy()) for name in so101.BODY_NAMES}


def _quat_matrix(quat: np.ndarray) -> np.ndarray:
    m = np.empty(9)
    mujoco.mju_quat2Mat(m, quat)
    return m.reshape(3, 3)


def _assert_world_pose(
    prim: Usd.Prim, time_code: float, pos: np.ndarray, quat: np.ndarray, label: str
) -> None:
    world = UsdGeom.XformCache(Usd.TimeCode(time_code)).GetLocalToWorldTransform(prim)
    np.testing.assert_allclose(world.ExtractTranslation(), pos, atol=1e-5, err_msg=label)
    # Gf is row-vector: its 3x3 block is the transpose of MuJoCo's rotation matrix.
    rotation = np.array(world.ExtractRotationMatrix()).T
    np.testing.assert_allclose(rotation, _quat_matrix(quat), atol=1e-5, err_msg=label)


@pytest.fixture(scope="module")
def mj() -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_path(str(SCENE))
    return model, mujoco.MjData(model)


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])  # text by default; crate for long sessions
def test_recorded_world_transforms_equal_mujoco_fk(tmp_path: Path, mj, suffix: str) -> None:
    model, data = mj
    session = tmp_path / "sessions" / f"run1{suffix}"
    expected: dict[tuple[str, float], dict] = {}
    with SessionRecorder(session, time_codes_per_second=30.0) as rec:
        for i, angles in enumerate(ANGLE_SETS):
            t = 100.0 + 0.1 * i  # any monotonic clock: the first sample becomes time code 0
            for device, sign in (("arm-001", 1.0), ("lab/arm 2", -1.0)):
                # The second device mirrors the first so both are checked at different poses.
                mirrored = [
                    float(np.clip(sign * a if j != "gripper" else a, *so101.JOINT_RANGES_RAD[j]))
                    for j, a in zip(so101.JOINT_NAMES, angles, strict=True)
                ]
                poses = _fk_poses(model, data, mirrored)
                assert rec.record(device, t, poses)
                expected[device, rec.time_code(t)] = poses
        assert rec.time_origin_s == 100.0
        devices = rec.devices
    assert devices == {"arm-001": "/World/arm_001", "lab/arm 2": "/World/lab_arm_2"}

    stage = Usd.Stage.Open(str(session))
    assert stage.GetTimeCodesPerSecond() == 30.0
    assert stage.GetStartTimeCode() == 0.0
    assert stage.GetEndTimeCode() == pytest.approx(9.0)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    for (device, time_code), poses in expected.items():
        root = stage.GetPrimAtPath(devices[device])
        assert root.GetCustomDataByKey("twin:deviceId") == device
        for body, (pos, quat) in poses.items():
            prim = stage.GetPrimAtPath(f"{devices[device]}/{BODY_REL[body]}")
            assert prim, body
            _assert_world_pose(prim, time_code, pos, quat, f"{device} {body} @ {time_code}")


def test_asset_is_referenced_relative_to_the_session_file(tmp_path: Path, mj) -> None:
    model, data = mj
    session = tmp_path / "run.usda"
    with SessionRecorder(session) as rec:
        rec.record("arm", 0.0, _fk_poses(model, data, ANGLE_SETS[0]))
    layer = Sdf.Layer.OpenAsAnonymous(str(session))
    refs = layer.GetPrimAtPath("/World/arm").referenceList.prependedItems
    assert len(refs) == 1
    asset = refs[0].assetPath
    assert not Path(asset).is_absolute()
    assert (session.parent / asset).resolve() == default_asset_path().resolve()


def test_device_twin_body_poses_round_trip(tmp_path: Path) -> None:
    robot = RobotModel.load()
    twin = DeviceTwin(robot, "arm-7")
    session = tmp_path / "twin.usda"
    recorded = []
    with SessionRecorder(session, time_codes_per_second=10.0) as rec:
        for i, angles in enumerate(ANGLE_SETS):
            assert twin.apply(dict(zip(so101.JOINT_NAMES, angles, strict=True)), 1_000 + 100 * i)
            poses = twin.body_poses()
            assert rec.record("arm-7", 0.1 * i, poses)
            recorded.append((rec.time_code(0.1 * i), poses))
    stage = Usd.Stage.Open(str(session))
    for time_code, poses in recorded:
        for body, (pos, quat) in poses.items():
            prim = stage.GetPrimAtPath(f"/World/arm_7/{BODY_REL[body]}")
            _assert_world_pose(prim, time_code, pos, quat, f"{body} @ {time_code}")


def test_flush_writes_samples_before_close(tmp_path: Path, mj) -> None:
    model, data = mj
    session = tmp_path / "live.usda"
    # The flush clock is the test's, so a loaded machine cannot let the interval pass early.
    now = [100.0]
    rec = SessionRecorder(session, flush_interval_s=0.2, clock=lambda: now[0])
    try:
        now[0] += 0.15
        rec.record("arm", 0.0, _fk_poses(model, data, ANGLE_SETS[1]))
        on_disk = Sdf.Layer.OpenAsAnonymous(str(session))
        assert not on_disk.GetPrimAtPath("/World/arm"), "saved before the flush interval elapsed"
        assert rec.flushes == 0
        now[0] += 0.1  # 0.25 s since the stage was created
        rec.record("arm", 1.0, _fk_poses(model, data, ANGLE_SETS[2]))
        assert rec.flushes >= 1
        on_disk = Sdf.Layer.OpenAsAnonymous(str(session))
        attr = on_disk.GetAttributeAtPath(f"/World/arm/{BODY_REL['wrist']}.xformOp:orient:twin")
        assert attr is not None
        assert sorted(on_disk.ListTimeSamplesForPath(attr.path)) == [0.0, 30.0]
        assert on_disk.endTimeCode == 30.0
    finally:
        rec.close()
    rec.close()  # idempotent
    assert rec.closed


def test_a_save_the_disk_has_no_room_for_is_not_made_so_the_file_stays_whole(
    tmp_path: Path, mj, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """usd-core saves a usdc session in place: a save cut short by a full disk tore a walk's whole 6 MB file.
    With too little room the save is not made: the session is set aside, its file as its last save left it."""
    from twin.output import recorder

    model, data = mj
    session = tmp_path / "live.usdc"
    now = [100.0]
    rec = SessionRecorder(session, flush_interval_s=0.2, clock=lambda: now[0])
    real = recorder.os.statvfs
    try:
        rec.record("arm", 0.0, _fk_poses(model, data, ANGLE_SETS[1]))
        rec.flush()
        assert rec.flushes == 1 and not rec.broken
        full = real(tmp_path)

        class Full:
            f_frsize, f_bavail = full.f_frsize, (recorder.MIN_FREE_FOR_SAVE_BYTES // full.f_frsize) - 1

        monkeypatch.setattr(recorder.os, "statvfs", lambda _path: Full)
        rec.record("arm", 1.0, _fk_poses(model, data, ANGLE_SETS[2]))
        now[0] += 1.0
        rec.flush()
        assert rec.broken and rec.flush_errors == 1 and rec.flushes == 1
        assert "not saved: " in caplog.text and "Its file holds what it had at its last save" in caplog.text
        assert not rec.record("arm", 2.0, _fk_poses(model, data, ANGLE_SETS[3]))  # dropped, counted
        assert rec.samples_dropped == 1
    finally:
        monkeypatch.setattr(recorder.os, "statvfs", real)
        rec.close()
    on_disk = Sdf.Layer.OpenAsAnonymous(str(session))  # the file, not the recorder's layer in memory
    attr = on_disk.GetAttributeAtPath(f"/World/arm/{BODY_REL['wrist']}.xformOp:orient:twin")
    assert sorted(on_disk.ListTimeSamplesForPath(attr.path)) == [0.0]  # the last save's, whole


def test_a_session_that_cannot_be_saved_at_its_start_leaves_no_empty_file(tmp_path: Path) -> None:
    """On a full disk each attempt to begin a session left a 0-byte file behind (24 a minute in a walk).
    A real full filesystem: a 1 MiB tmpfs, filled (the tests run as root, as `make setup` does)."""
    with full_disk(tmp_path / "disk") as disk:
        for n in range(3):
            with pytest.raises(OSError, match="could not be saved; check disk space"):
                SessionRecorder(disk / f"session-{n}.usdc")
        assert sorted(p.name for p in disk.iterdir()) == ["filler"]


def test_a_session_that_recorded_no_sample_leaves_no_file_at_close(tmp_path: Path, mj) -> None:
    """A walk: `twin run --workers 3 --record-dir DIR` with one arm left two empty session files, one for each
    worker given no arm. A session that recorded nothing (a sample rejected or dropped is not recorded) is
    removed at close; one that recorded a sample is kept."""
    model, data = mj
    empty = SessionRecorder(tmp_path / "session-empty.usdc")
    assert not empty.record("arm", 0.0, {})  # rejected: nothing of it in the file
    assert empty.path.is_file()  # begun at once, so a full disk is told at start
    empty.close()
    empty.close()
    recorded = SessionRecorder(tmp_path / "session-kept.usdc")
    assert recorded.record("arm", 0.0, _fk_poses(model, data, ANGLE_SETS[0]))
    recorded.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session-kept.usdc"]


def test_at_most_time_codes_per_second_per_device(tmp_path: Path, mj) -> None:
    model, data = mj
    poses = _fk_poses(model, data, ANGLE_SETS[2])
    with SessionRecorder(tmp_path / "rate.usda", time_codes_per_second=10.0) as rec:
        kept = [rec.record("fast", i / 100.0, poses) for i in range(101)]  # 100 Hz for 1 s
        assert sum(kept) == 11  # time codes 0, 1, ..., 10
        assert rec.samples_dropped == 90
        assert not rec.record("fast", 0.5, poses)  # out of order: never rewrites the past
        assert rec.record("slow", 0.55, poses)  # another device keeps its own pace
    layer = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "rate.usda"))
    path = Sdf.Path(f"/World/fast/{BODY_REL['base']}.xformOp:translate:twin")
    assert layer.ListTimeSamplesForPath(path) == [float(i) for i in range(11)]


def test_bad_input_is_counted_not_raised(tmp_path: Path, mj, caplog: pytest.LogCaptureFixture) -> None:
    model, data = mj
    good = _fk_poses(model, data, ANGLE_SETS[0])
    nan_pose = dict(good, wrist=(np.array([np.nan, 0, 0]), good["wrist"][1]))
    short_quat = dict(good, gripper=(good["gripper"][0], np.array([1.0, 0.0])))
    rec = SessionRecorder(tmp_path / "bad.usda")
    with caplog.at_level(logging.WARNING, logger="twin.output.recorder"):
        assert not rec.record("arm", 0.0, {})
        assert not rec.record("arm", 0.0, {"elbow": (np.zeros(3), np.array([1.0, 0, 0, 0]))})
        assert not rec.record("arm", 0.0, nan_pose)
        assert not rec.record("arm", 0.0, short_quat)
        assert not rec.record("arm", float("nan"), good)
        assert not rec.record("arm", 0.0, [1, 2, 3])  # type: ignore[arg-type]
        assert not rec.record("arm", 0.0, dict(good, wrist=(good["wrist"][0], np.zeros(4))))
        assert not rec.record("arm", 0.0, dict(good, wrist=("abc", good["wrist"][1])))
        assert not rec.record(
            "arm", 0.0, dict(good, wrist=(np.array(["a", "b", "c"], dtype=object), good["wrist"][1]))
        )
    assert rec.samples_rejected == 9
    assert "so101.BODY_NAMES" in caplog.text and "'wrist'" in caplog.text
    assert rec.record("arm", 0.0, good)
    rec.close()
    assert not rec.record("arm", 5.0, good)  # after close: dropped, no exception
    assert rec.samples_written == 1


def test_missing_body_keeps_the_asset_pose_and_follows_its_parent(tmp_path: Path, mj) -> None:
    model, data = mj
    # The bundled asset's jaw transform is the MJCF's at gripper = 0, so the expected jaw pose is FK there.
    poses = _fk_poses(model, data, (*ANGLE_SETS[2][:5], 0.0))
    jaw_pos, jaw_quat = poses.pop("moving_jaw")  # like a user MJCF whose jaw body has another name
    session = tmp_path / "partial.usda"
    with SessionRecorder(session) as rec:
        assert rec.record("arm", 0.0, poses)
    stage = Usd.Stage.Open(str(session))
    _assert_world_pose(
        stage.GetPrimAtPath(f"/World/arm/{BODY_REL['moving_jaw']}"), 0.0, jaw_pos, jaw_quat, "jaw"
    )


def test_device_names_are_sanitised_and_unique(tmp_path: Path, mj) -> None:
    model, data = mj
    poses = _fk_poses(model, data, ANGLE_SETS[0])
    assert sanitise_prim_name("arm-001") == "arm_001"
    assert sanitise_prim_name("7th arm") == "_7th_arm"
    with SessionRecorder(tmp_path / "names.usda") as rec:
        rec.record("arm-1", 0.0, poses)
        rec.record("arm_1", 0.0, poses)
        assert rec.devices == {"arm-1": "/World/arm_1", "arm_1": "/World/arm_1_2"}


def test_constructor_errors_name_the_fix(tmp_path: Path) -> None:
    existing = tmp_path / "exists.usda"
    existing.write_text("#usda 1.0\n")
    with pytest.raises(FileExistsError, match="pick a new name"):
        SessionRecorder(existing)
    with pytest.raises(FileNotFoundError, match="make usd-asset"):
        SessionRecorder(tmp_path / "a.usda", asset_path=tmp_path / "missing.usda")
    with pytest.raises(ValueError, match="time_codes_per_second"):
        SessionRecorder(tmp_path / "b.usda", time_codes_per_second=0)
    with pytest.raises(ValueError, match="flush_interval_s"):
        SessionRecorder(tmp_path / "c.usda", flush_interval_s=float("nan"))


# Golden-style check on a tiny inline model: every body hinges about z, 0.1 m along x from its parent body,
# and the hand-written asset hides each child under a static "Mount" Xform (0.05 m along x), so the recorder
# must remove that offset. At 90 degrees on the first joint, each body's local sample is exactly known.
TINY_MJCF = """
<mujoco>
  <worldbody>
    <body name="base">
      <body name="shoulder" pos="0.1 0 0"><joint name="j1" axis="0 0 1"/><geom size="0.01"/>
        <body name="upper_arm" pos="0.1 0 0"><joint name="j2" axis="0 0 1"/><geom size="0.01"/>
          <body name="lower_arm" pos="0.1 0 0"><geom size="0.01"/>
            <body name="wrist" pos="0.1 0 0"><geom size="0.01"/>
              <body name="gripper" pos="0.1 0 0"><geom size="0.01"/>
                <body name="moving_jaw" pos="0.1 0 0"><geom size="0.01"/></body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _tiny_asset(path: Path) -> None:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/tiny")
    stage.SetDefaultPrim(root.GetPrim())
    parent = UsdGeom.Xform.Define(stage, "/tiny/base")
    for name in so101.BODY_NAMES[1:]:
        mount = UsdGeom.Xform.Define(stage, parent.GetPath().AppendChild("Mount"))
        mount.AddTranslateOp().Set(Gf.Vec3d(0.05, 0, 0))
        body = UsdGeom.Xform.Define(stage, mount.GetPath().AppendChild(name))
        body.AddTranslateOp().Set(Gf.Vec3d(0.05, 0, 0))
        parent = body
    stage.GetRootLayer().Save()


def test_golden_tiny_model(tmp_path: Path) -> None:
    _tiny_asset(tmp_path / "tiny.usda")
    model = mujoco.MjModel.from_xml_string(TINY_MJCF)
    data = mujoco.MjData(model)
    data.qpos[:] = (math.pi / 2, 0.0)
    mujoco.mj_kinematics(model, data)
    poses = {name: (data.body(name).xpos.copy(), data.body(name).xquat.copy()) for name in so101.BODY_NAMES}
    with SessionRecorder(tmp_path / "out" / "s.usda", asset_path=tmp_path / "tiny.usda") as rec:
        assert rec.record("tiny", 2.0, poses)
    layer = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "out" / "s.usda"))
    assert layer.GetPrimAtPath("/World/tiny").referenceList.prependedItems[0].assetPath == "../tiny.usda"
    shoulder = "/World/tiny/base/Mount/shoulder"
    upper = f"{shoulder}/Mount/upper_arm"
    half = math.sqrt(0.5)
    golden = {
        f"{shoulder}.xformOp:translate:twin": Gf.Vec3d(0.05, 0, 0),
        f"{shoulder}.xformOp:orient:twin": Gf.Quatd(half, 0, 0, half),
        f"{upper}.xformOp:translate:twin": Gf.Vec3d(0.05, 0, 0),
        f"{upper}.xformOp:orient:twin": Gf.Quatd(1, 0, 0, 0),
        "/World/tiny/base.xformOp:orient:twin": Gf.Quatd(1, 0, 0, 0),
    }
    for path, value in golden.items():
        samples = layer.ListTimeSamplesForPath(Sdf.Path(path))
        assert samples == [0.0], path
        got = layer.QueryTimeSample(Sdf.Path(path), 0.0)
        if isinstance(value, Gf.Quatd):
            assert abs(Gf.Dot(got, value)) == pytest.approx(1.0, abs=1e-12), (path, got)
        else:
            assert Gf.IsClose(got, value, 1e-12), (path, got)
    order = layer.GetAttributeAtPath(f"{shoulder}.xformOpOrder").default
    assert list(order) == ["xformOp:translate:twin", "xformOp:orient:twin"]
    stage = Usd.Stage.Open(str(tmp_path / "out" / "s.usda"))
    tip = stage.GetPrimAtPath(f"{upper}/Mount/lower_arm/Mount/wrist/Mount/gripper/Mount/moving_jaw")
    _assert_world_pose(tip, 0.0, poses["moving_jaw"][0], poses["moving_jaw"][1], "tiny tip")


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_servo_diagnostics_are_time_sampled_on_the_device_prim(tmp_path: Path, mj, suffix: str) -> None:
    from twin.core.telemetry import JointDiagnostics
    from twin.output.recorder import servo_attribute_name

    model, data = mj
    poses = _fk_poses(model, data, ANGLE_SETS[1])
    hot = JointDiagnostics(velocity_rad_s=-0.25, load_percent=-31.3, temperature_c=61.0, current_a=0.65)
    session = tmp_path / f"servos{suffix}"
    with SessionRecorder(session) as rec:
        rec.record("arm-001", 10.0, poses, {"elbow_flex": hot, "gripper": JointDiagnostics()})
        rec.record(
            "arm-001", 11.0, poses, {"elbow_flex": JointDiagnostics(temperature_c=62.0, voltage_v=5.0)}
        )
        rec.record("arm-001", 12.0, poses)  # no diagnostics: the poses alone
    stage = Usd.Stage.Open(str(session))
    prim = stage.GetPrimAtPath("/World/arm_001")
    temp = prim.GetAttribute(servo_attribute_name("elbow_flex", "temperatureCelsius"))
    assert temp.GetTimeSamples() == [0.0, 30.0]
    assert (temp.Get(0.0), temp.Get(30.0)) == (61.0, 62.0)
    load = prim.GetAttribute("twin:servo:elbow_flex:loadPercent")
    assert load.GetTimeSamples() == [0.0] and load.Get(0.0) == pytest.approx(-31.3)
    assert prim.GetAttribute("twin:servo:elbow_flex:currentAmperes").Get(0.0) == pytest.approx(0.65)
    assert prim.GetAttribute("twin:servo:elbow_flex:velocityRadPerSecond").Get(0.0) == pytest.approx(-0.25)
    assert prim.GetAttribute("twin:servo:elbow_flex:voltageVolts").GetTimeSamples() == [30.0]
    # Readings never sent have no attribute at all, rather than a made-up zero.
    assert not prim.GetAttribute("twin:servo:gripper:temperatureCelsius")


def test_recorded_part_meshes_sit_where_mujoco_draws_them(tmp_path: Path, mj) -> None:
    # What a USD viewer shows of a session: the asset's part meshes moved by the recorded body samples. Their
    # world points at each time code are MuJoCo's mesh vertices at that pose.
    model, data = mj
    session = tmp_path / "meshes.usda"
    with SessionRecorder(session) as rec:
        for i, angles in enumerate(ANGLE_SETS[1:]):
            rec.record("arm", float(i), _fk_poses(model, data, angles))
    stage = Usd.Stage.Open(str(session))
    checked = 0
    for i, angles in enumerate(ANGLE_SETS[1:]):
        _fk_poses(model, data, angles)
        cache = UsdGeom.XformCache(Usd.TimeCode(rec.time_code(float(i))))
        for name in ("upper_arm_so101", "wrist_roll_servo", "moving_jaw_so101"):
            geom = model.geom(name)
            body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, geom.bodyid[0])
            prim = stage.GetPrimAtPath(f"/World/arm/{BODY_REL[body]}/{name}")
            assert prim.IsA(UsdGeom.Mesh), name
            points = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(), dtype=float)
            world = np.array(cache.GetLocalToWorldTransform(prim))
            start, count = model.mesh_vertadr[geom.dataid[0]], model.mesh_vertnum[geom.dataid[0]]
            drawn = model.mesh_vert[start : start + count] @ data.geom_xmat[geom.id].reshape(3, 3).T
            np.testing.assert_allclose(
                points @ world[:3, :3] + world[3, :3],
                drawn + data.geom_xpos[geom.id],
                atol=1e-5,
                err_msg=name,
            )
            checked += 1
    assert checked == 9


def test_poses_as_lists_integers_or_unnormalised_quaternions_are_recorded_as_floats(
    tmp_path: Path, mj
) -> None:
    # The pose check converts to floats itself (not numpy): lists and integer arrays are poses too, and a
    # quaternion off unit length is normalised, as with float arrays.
    model, data = mj
    good = _fk_poses(model, data, ANGLE_SETS[0])
    as_lists = {name: (list(pos), [2.0 * q for q in quat]) for name, (pos, quat) in good.items()}
    as_lists["base"] = (np.zeros(3, dtype=np.int64), np.array([1, 0, 0, 0]))
    rec = SessionRecorder(tmp_path / "lists.usda")
    assert rec.record("a", 0.0, good)
    assert rec.record("b", 0.0, dict(good, base=(np.zeros(3), np.array([1.0, 0, 0, 0]))))
    assert rec.record("c", 0.0, as_lists)
    rec.close()
    stage = Usd.Stage.Open(str(tmp_path / "lists.usda"))
    cache = UsdGeom.XformCache(Usd.TimeCode(0.0))
    b, c = (stage.GetPrimAtPath(rec.devices[d]) for d in ("b", "c"))
    for child_b, child_c in zip(Usd.PrimRange(b), Usd.PrimRange(c), strict=True):
        mb = cache.GetLocalToWorldTransform(child_b) * cache.GetLocalToWorldTransform(b).GetInverse()
        mc = cache.GetLocalToWorldTransform(child_c) * cache.GetLocalToWorldTransform(c).GetInverse()
        assert np.allclose(np.array(mb), np.array(mc), atol=1e-9), child_c.GetPath()


def _random_quat(rng: np.random.Generator) -> tuple[float, ...]:
    q = rng.normal(size=4)
    return tuple((q / np.linalg.norm(q)).tolist())


def _gf_matrix(quat: tuple[float, ...], pos: tuple[float, ...]) -> Gf.Matrix4d:
    m = Gf.Matrix4d(1.0)
    m.SetRotateOnly(Gf.Quatd(quat[0], Gf.Vec3d(*quat[1:])))
    m.SetTranslateOnly(Gf.Vec3d(*pos))
    return m


def test_float_pose_math_equals_gf_matrices() -> None:
    # The recorder composes poses with float quaternions; the values must be what Gf row-vector matrices give
    # (world = local * parent), including the sign Gf's ExtractRotationQuat picks for a first sample.
    from twin.output.recorder import _compose, _gf_sign, _relative

    rng = np.random.default_rng(3)
    for _ in range(200):
        parent = (_random_quat(rng), tuple(rng.normal(size=3).tolist()))
        world = (_random_quat(rng), tuple(rng.normal(size=3).tolist()))
        gf_parent, gf_world = _gf_matrix(*parent), _gf_matrix(*world)
        local = gf_world * gf_parent.GetInverse()
        quat, pos = _relative(parent, world)
        expected_quat = local.ExtractRotationQuat().GetNormalized()
        np.testing.assert_allclose(pos, local.ExtractTranslation(), atol=1e-9)
        np.testing.assert_allclose(
            _gf_sign(quat), (expected_quat.GetReal(), *expected_quat.GetImaginary()), atol=1e-9
        )
        composed = _gf_matrix(*_compose(parent, (quat, pos)))
        assert np.allclose(np.array(composed), np.array(gf_world), atol=1e-9)


def test_orient_samples_stay_in_one_hemisphere_when_the_pose_quaternion_flips_sign(tmp_path: Path) -> None:
    # The base turns about z in 40 degree steps past a full turn, its quaternion passed as w >= 0 and then
    # negated on every other sample (the same rotations): the written orients must never jump to the other
    # hemisphere, or orient interpolation between two samples takes the long way round.
    session = tmp_path / "flip.usda"
    angles = [math.radians(40.0 * k) for k in range(12)]
    with SessionRecorder(session) as rec:
        for k, angle in enumerate(angles):
            quat = np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])
            quat = quat if quat[0] >= 0 else -quat
            assert rec.record("arm", float(k), {"base": (np.zeros(3), -quat if k % 2 else quat)})
    stage = Usd.Stage.Open(str(session))
    base = stage.GetPrimAtPath(f"/World/arm/{BODY_REL['base']}")
    orient = base.GetAttribute("xformOp:orient:twin")
    times = orient.GetTimeSamples()
    assert len(times) == len(angles)
    written = [orient.Get(t) for t in times]
    for previous, current in itertools.pairwise(written):
        assert Gf.Dot(previous, current) > 0.5  # 40 degrees apart: cos(20 degrees), never negative
    for t, angle in zip(times, angles, strict=True):
        expected = np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])
        _assert_world_pose(base, t, np.zeros(3), expected, f"base @ {t}")


def test_a_session_usd_the_disk_cuts_short_is_not_left_where_the_console_serves_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The console serves a completed session's file from disk once it exists: an export the disk cut short
    (usd-core leaves its part of a file and raises) must not be left at that name, and is refused with why."""
    from pxr import Tf
    from twin.ops.sessions import HistorySessions
    from twin.service.console import SessionInfo

    class TornExport:
        def Flatten(self) -> TornExport:  # noqa: N802 - USD's name
            return self

        def Export(self, path: str) -> bool:  # noqa: N802 - USD's name
            Path(path).write_bytes(b"PXR-USDC" + bytes(4096))  # what a full disk leaves
            Tf.RaiseRuntimeError("Error occurred writing file: No space left on device")
            return True

    catalog = HistorySessions("unused")
    monkeypatch.setattr(catalog, "_reader", lambda: None)
    monkeypatch.setattr(catalog, "_robot", lambda: None)
    monkeypatch.setattr(catalog, "_samples", lambda *args: iter(()))
    real_open = Usd.Stage.Open

    def open_stage(path: str, *args: object) -> object:
        # The rebuilt session's stage only; the recorder opens the robot's asset as ever.
        return TornExport() if ".recorded." in str(path) else real_open(path, *args)

    monkeypatch.setattr(Usd.Stage, "Open", staticmethod(open_stage))
    session = SessionInfo("arm-001", start=1_000.0, end=1_010.0, messages=100)
    with pytest.raises(ValueError, match="No space left on device"):
        catalog.session_file(session, "usd", tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("kind", ["csv", "png"])
def test_a_session_file_whose_export_fails_leaves_no_part_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str
) -> None:
    """An export that fails half way (a full disk) left its `.part` file in the session-files directory
    until the agent stopped; the bound on that directory does not count such files."""
    from twin.ops import history
    from twin.ops.sessions import HistorySessions
    from twin.service.console import SessionInfo

    def torn(reader: object, path: Path, *args: object, **kwargs: object) -> None:
        Path(path).write_bytes(b"device,time\n" * 1000)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(history, "export", torn)
    monkeypatch.setattr(history, "plot", lambda reader, device, path, **kw: torn(reader, path))
    catalog = HistorySessions("unused")
    monkeypatch.setattr(catalog, "_reader", lambda: None)
    session = SessionInfo("arm-001", start=1_000.0, end=1_010.0, messages=100)
    with pytest.raises(OSError, match="No space left on device"):
        catalog.session_file(session, kind, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
