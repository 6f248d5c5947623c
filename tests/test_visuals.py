"""twin.robot.visuals: what MuJoCo draws, as triangles in body frames.

Oracles: the primitives' closed-form volumes and extents, MuJoCo's own world placement of each geom
(geom_xpos / geom_xmat after mj_kinematics), and small inline models whose numbers are written by hand.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
from twin.robot import so101
from twin.robot.model import RobotModel
from twin.robot.visuals import (
    box,
    capsule,
    cluster_vertices,
    cylinder,
    ellipsoid,
    fit_face_budget,
    geom_rgba,
    vertex_normals,
    visual_geoms,
)


def _volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _outward(v: np.ndarray, f: np.ndarray, n: np.ndarray) -> float:
    """Share of faces whose winding agrees with their vertices' normals."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    face_n = np.cross(b - a, c - a)
    return float((np.einsum("ij,ij->i", face_n, n[f].sum(axis=1)) > 0).mean())


def _is_closed(v: np.ndarray, f: np.ndarray) -> bool:
    """Every edge is shared by exactly two faces, once in each direction (vertices at one position, as at a
    flat-shaded crease, count as one)."""
    _, same = np.unique(np.round(v, 12), axis=0, return_inverse=True)
    f = same.ravel()[f]
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    directed = {tuple(e) for e in edges.tolist()}
    return len(directed) == len(edges) and all((b, a) in directed for a, b in directed)


@pytest.mark.parametrize(
    ("shape", "expected_volume", "extent", "rel"),
    [
        (box((0.1, 0.2, 0.3)), 8 * 0.1 * 0.2 * 0.3, (0.1, 0.2, 0.3), 1e-12),
        # A 24 x 12 tessellation is inscribed in the true surface: a little under the exact volume.
        (ellipsoid((0.1, 0.2, 0.3)), 4 / 3 * math.pi * 0.1 * 0.2 * 0.3, (0.1, 0.2, 0.3), 0.05),
        (cylinder(0.1, 0.2), math.pi * 0.1**2 * 0.4, (0.1, 0.1, 0.2), 0.02),
        (capsule(0.1, 0.2), math.pi * 0.1**2 * 0.4 + 4 / 3 * math.pi * 0.1**3, (0.1, 0.1, 0.3), 0.03),
    ],
    ids=["box", "ellipsoid", "cylinder", "capsule"],
)
def test_primitives_are_closed_outward_and_the_right_size(shape, expected_volume, extent, rel) -> None:
    v, f, n = shape
    assert _is_closed(v, f)
    assert _outward(v, f, n) == 1.0
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    volume = _volume(v, f)
    assert volume <= expected_volume * (1 + 1e-9)
    assert volume == pytest.approx(expected_volume, rel=rel)
    np.testing.assert_allclose(np.abs(v).max(axis=0), extent, rtol=1e-9)


def test_vertex_normals_of_a_tetrahedron_point_away_from_its_centre() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    n = vertex_normals(v, f)
    centre = v.mean(axis=0)
    assert (np.einsum("ij,ij->i", n, v - centre) > 0).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)


INLINE = """
<mujoco>
  <asset>
    <material name="red" rgba="1 0 0 1"/>
    <mesh name="tet" vertex="0 0 0  0.02 0 0  0 0.02 0  0 0 0.02"/>
  </asset>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <body name="base">
      <geom name="plate" type="box" size="0.05 0.04 0.01" pos="0 0 0.01" material="red"/>
      <geom name="tinted" type="box" size="0.01 0.01 0.01" material="red" rgba="0 0 1 1"/>
      <geom name="hidden" type="box" size="0.01 0.01 0.01" group="3"/>
      <geom name="clear" type="sphere" size="0.01" rgba="1 1 1 0"/>
      <body name="link" pos="0 0 0.1" euler="0 0 90">
        <joint name="j" type="hinge" axis="0 0 1"/>
        <geom name="rod" type="capsule" fromto="0 0 0 0.2 0 0" size="0.01"/>
        <body name="mount" pos="0.2 0 0" euler="90 0 0">
          <geom name="tip" type="mesh" mesh="tet" pos="0.01 0 0"/>
        </body>
        <body name="swinging" pos="0.1 0 0">
          <joint name="k" type="hinge" axis="0 1 0"/>
          <geom name="flap" type="box" size="0.01 0.01 0.01"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_visual_geoms_of_an_inline_model() -> None:
    model = mujoco.MjModel.from_xml_string(INLINE)
    bodies = {"base": model.body("base").id, "link": model.body("link").id}
    geoms = visual_geoms(model, bodies)
    by_name = {g.name: g for g in geoms}
    # The floor is the world's, `hidden` is in collision group 3, `clear` is invisible, `flap` hangs on a
    # joint no tracked body carries.
    assert set(by_name) == {"plate", "tinted", "rod", "tip"}
    assert by_name["plate"].rgba == (1.0, 0.0, 0.0, 1.0)  # material colour
    assert by_name["tinted"].rgba == (0.0, 0.0, 1.0, 1.0)  # an explicit rgba wins over the material
    assert by_name["rod"].rgba == (0.5, 0.5, 0.5, 1.0)  # MuJoCo's default
    # The welded `mount` body is carried by `link`, its nearest tracked ancestor.
    assert by_name["tip"].body == "link"
    assert by_name["tip"].kind == "mesh"
    assert by_name["tip"].face_count == 4
    assert by_name["rod"].kind == "capsule"
    # Poses in the body frame, by hand: the capsule from (0,0,0) to (0.2,0,0) is centred at x = 0.1 and its
    # z axis lies along the body's x (either way: a capsule is symmetric).
    np.testing.assert_allclose(by_name["rod"].pos, [0.1, 0.0, 0.0], atol=1e-12)
    z_axis = np.zeros(9)
    mujoco.mju_quat2Mat(z_axis, by_name["rod"].quat)
    np.testing.assert_allclose(np.abs(z_axis.reshape(3, 3)[:, 2]), [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(by_name["plate"].pos, [0.0, 0.0, 0.01], atol=1e-12)


def _world(model, data, geom) -> np.ndarray:
    """A visual geom's vertices in the world, posed from its body's MuJoCo pose."""
    bid = model.body(geom.body).id
    rb = data.xmat[bid].reshape(3, 3)
    rg = np.zeros(9)
    mujoco.mju_quat2Mat(rg, geom.quat)
    local = geom.vertices.astype(np.float64) @ rg.reshape(3, 3).T + geom.pos
    return local @ rb.T + data.xpos[bid]


def test_every_so101_visual_geom_sits_where_mujoco_draws_it() -> None:
    robot = RobotModel.load()
    model = robot.model
    geoms = visual_geoms(model, robot.body_ids)
    assert geoms, "the bundled SO-101 has visual geoms"
    assert {g.body for g in geoms} <= set(so101.BODY_NAMES)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(14)
    for _ in range(3):
        for name, (lo, hi) in robot.joint_ranges.items():
            data.qpos[robot.qpos_addr[name]] = rng.uniform(lo, hi)
        mujoco.mj_kinematics(model, data)
        for g in geoms:
            # MuJoCo's own world placement of the geom, applied to the same local triangles.
            expected = g.vertices.astype(np.float64) @ data.geom_xmat[g.geom_id].reshape(3, 3).T
            expected += data.geom_xpos[g.geom_id]
            np.testing.assert_allclose(_world(model, data, g), expected, atol=1e-6)
            # And the triangles fill the geom's own bounding box (geom_aabb: centre, half sizes).
            centre, half = model.geom_aabb[g.geom_id, :3], model.geom_aabb[g.geom_id, 3:]
            lo, hi = g.vertices.min(axis=0), g.vertices.max(axis=0)
            assert (lo >= centre - half - 1e-6).all() and (hi <= centre + half + 1e-6).all()
            np.testing.assert_allclose(hi - lo, 2 * half, rtol=0.05)
            assert geom_rgba(model, g.geom_id) == g.rgba


def test_clustering_keeps_the_shape_within_a_cell_and_meets_a_budget() -> None:
    # A finely tessellated ellipsoid stands in for a CAD mesh.
    v, f, _ = ellipsoid((0.05, 0.03, 0.02))
    cell = 0.004
    cv, cf = cluster_vertices(v, f, cell)
    assert len(cf) < len(f)
    assert cf.max() < len(cv)
    # Every clustered vertex is the mean of vertices within one cell of it.
    nearest = np.min(np.linalg.norm(cv[:, None, :] - v[None, :, :], axis=2), axis=1)
    assert nearest.max() <= cell * math.sqrt(3)
    # No degenerate or repeated triangles.
    assert ((cf[:, 0] != cf[:, 1]) & (cf[:, 1] != cf[:, 2]) & (cf[:, 0] != cf[:, 2])).all()
    assert len(np.unique(np.sort(cf, axis=1), axis=0)) == len(cf)


def test_fit_face_budget_thins_meshes_and_leaves_primitives() -> None:
    xml = INLINE.replace(
        '<mesh name="tet" vertex="0 0 0  0.02 0 0  0 0.02 0  0 0 0.02"/>',
        '<mesh name="tet" builtin="sphere" params="3" scale="0.03 0.03 0.03"/>',
    )
    model = mujoco.MjModel.from_xml_string(xml)
    bodies = {"base": model.body("base").id, "link": model.body("link").id}
    geoms = visual_geoms(model, bodies)
    mesh = next(g for g in geoms if g.kind == "mesh")
    primitives = sum(g.face_count for g in geoms if g.kind != "mesh")
    assert mesh.face_count > 400
    budget = primitives + 300
    thinned, cell = fit_face_budget(geoms, budget)
    assert cell is not None
    assert sum(g.face_count for g in thinned) <= budget
    assert [g.name for g in thinned] == [g.name for g in geoms]
    for before, after in zip(geoms, thinned, strict=True):
        if before.kind != "mesh":
            assert after is before
    same, none = fit_face_budget(geoms, 10**6)
    assert none is None and same == geoms
