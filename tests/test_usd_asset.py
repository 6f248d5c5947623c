"""The committed USD asset (robots/so101/usd, from `make usd-asset`) still matches the MJCF it came from."""

from __future__ import annotations

import math
import tomllib
from fnmatch import fnmatch
from pathlib import Path

import mujoco
import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdPhysics, UsdShade
from twin.robot import so101
from twin.robot.visuals import visual_geoms

ROOT = Path(__file__).resolve().parents[1]
ASSET_DIR = ROOT / "robots" / "so101" / "usd"
ASSET = ASSET_DIR / "so101.usda"
MJCF = ROOT / "robots" / "so101" / "so101.xml"


@pytest.fixture(scope="module")
def stage() -> Usd.Stage:
    stage = Usd.Stage.Open(str(ASSET))
    assert stage is not None, f"cannot open {ASSET}; run `make usd-asset`"
    return stage


@pytest.fixture(scope="module")
def mj() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(MJCF))


def _revolute_joints(stage: Usd.Stage) -> dict[str, UsdPhysics.RevoluteJoint]:
    return {
        prim.GetName(): UsdPhysics.RevoluteJoint(prim)
        for prim in stage.Traverse()
        if prim.IsA(UsdPhysics.RevoluteJoint)
    }


def _body_prims(stage: Usd.Stage) -> dict[str, Usd.Prim]:
    return {
        prim.GetName(): prim
        for prim in stage.Traverse()
        if prim.HasAPI(UsdPhysics.RigidBodyAPI) and prim.GetName() in so101.BODY_NAMES
    }


def test_stage_units_and_default_prim(stage: Usd.Stage) -> None:
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().IsValid()


def test_articulation_root_is_the_base(stage: Usd.Stage) -> None:
    roots = [p for p in stage.Traverse() if p.HasAPI(UsdPhysics.ArticulationRootAPI)]
    assert [p.GetName() for p in roots] == ["base"]


def test_revolute_joints_match_mjcf_names_and_limits(stage: Usd.Stage, mj: mujoco.MjModel) -> None:
    joints = _revolute_joints(stage)
    assert sorted(joints) == sorted(so101.JOINT_NAMES)
    for name, joint in joints.items():
        lo, hi = mj.joint(name).range
        # USD angular limits are degrees, MJCF radians; the asset stores float32.
        assert joint.GetLowerLimitAttr().Get() == pytest.approx(math.degrees(lo), abs=1e-3), name
        assert joint.GetUpperLimitAttr().Get() == pytest.approx(math.degrees(hi), abs=1e-3), name
        assert joint.GetAxisAttr().Get() == UsdPhysics.Tokens.z, name
        # body1 is the body the joint moves, as in the MJCF.
        (body1,) = joint.GetBody1Rel().GetTargets()
        assert body1.name == mj.body(mj.joint(name).bodyid[0]).name, name


def test_bodies_masses_match_mjcf(stage: Usd.Stage, mj: mujoco.MjModel) -> None:
    bodies = _body_prims(stage)
    assert sorted(bodies) == sorted(so101.BODY_NAMES)
    for name, prim in bodies.items():
        mass = UsdPhysics.MassAPI(prim).GetMassAttr().Get()
        assert mass == pytest.approx(mj.body(name).mass[0], rel=1e-6), name


def test_body_frames_at_zero_match_mujoco_fk(stage: Usd.Stage, mj: mujoco.MjModel) -> None:
    data = mujoco.MjData(mj)
    mujoco.mj_kinematics(mj, data)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    for name, prim in _body_prims(stage).items():
        world = cache.GetLocalToWorldTransform(prim)
        np.testing.assert_allclose(world.ExtractTranslation(), data.body(name).xpos, atol=1e-6, err_msg=name)
        expected = np.empty(9)
        mujoco.mju_quat2Mat(expected, data.body(name).xquat)
        # Gf matrices are row-vector: the upper 3x3 is the transpose of MuJoCo's rotation matrix.
        rotation = np.array(world.ExtractRotationMatrix()).T
        np.testing.assert_allclose(rotation, expected.reshape(3, 3), atol=1e-6, err_msg=name)
        assert isinstance(world, Gf.Matrix4d)


def test_asset_is_text_but_the_mesh_library_and_ships_as_package_data() -> None:
    files = [p for p in ASSET_DIR.rglob("*") if p.is_file()]
    assert files, "no USD asset; run `make usd-asset`"
    binary = [p.relative_to(ASSET_DIR).as_posix() for p in files if p.suffix == ".usdc"]
    assert binary == ["Payload/GeometryLibrary.usdc"], (
        "other binary layers: run robots/tools/usd_text_layers.py"
    )
    # Under a megabyte in all (measured 0.92 MB): the meshes are the simplified visual set, stored once each.
    assert sum(p.stat().st_size for p in files) < 1_200_000
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    patterns = pyproject["tool"]["setuptools"]["package-data"]["twin_robots"]
    for path in files:
        rel = path.relative_to(ROOT / "robots").as_posix()
        assert any(fnmatch(rel, pattern) for pattern in patterns), f"{rel} would not be packaged"


def test_asset_holds_the_meshes_where_mujoco_draws_them(stage: Usd.Stage, mj: mujoco.MjModel) -> None:
    # Every visual mesh geom is a Mesh prim named like the geom, whose points at q = 0, placed by the asset's
    # transforms, are MuJoCo's vertices placed by forward kinematics; the triangles are the same.
    data = mujoco.MjData(mj)
    mujoco.mj_kinematics(mj, data)
    bodies = {name: mj.body(name).id for name in so101.BODY_NAMES}
    expected = {part.name: part for part in visual_geoms(mj, bodies)}
    rotation = np.empty(9)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    found = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh) and prim.GetName() in expected:
            found[prim.GetName()] = prim
    assert sorted(found) == sorted(expected)
    for name, prim in found.items():
        part = expected[name]
        assert prim.GetParent().GetName() == part.body, name
        mesh = UsdGeom.Mesh(prim)
        points = np.array(mesh.GetPointsAttr().Get(), dtype=float)
        world = np.array(cache.GetLocalToWorldTransform(prim))  # row-vector convention
        body = mj.body(part.body).id
        mujoco.mju_quat2Mat(rotation, part.quat)  # the geom's frame -> its body's frame
        in_body = part.vertices.astype(np.float64) @ rotation.reshape(3, 3).T + part.pos
        np.testing.assert_allclose(
            points @ world[:3, :3] + world[3, :3],
            in_body @ data.xmat[body].reshape(3, 3).T + data.xpos[body],
            atol=1e-6,
            err_msg=name,
        )
        counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
        indices = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        assert (counts == 3).all() and np.array_equal(indices, part.faces), name
        binding = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
        assert binding.GetPrim().GetName() == mj.mat(mj.geom(name).matid[0]).name, name
