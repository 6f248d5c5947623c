"""The arm's visual geometry as triangle meshes, read from the compiled MuJoCo model.

Viewers outside MuJoCo (Rerun, and any other that draws triangles) need what MuJoCo draws: every visual geom
of every body, as triangles in the frame of the body that moves it, in the geom's colour. This module reads
that generically from an `MjModel`, so it shows the primitive model of today and mesh models alike:

- mesh geoms come from `mesh_vert` / `mesh_face` (MuJoCo has already moved the vertices into the mesh frame
  and folded the offset into the geom's pose);
- boxes, spheres, ellipsoids, cylinders and capsules are tessellated here;
- planes, height fields and SDFs are not part of an arm and are left out (logged at debug level).

A geom is visual when MuJoCo draws it by default: its group is one of 0..2 (the `geomgroup` flags MuJoCo's
viewer starts with) and it is not fully transparent; collision geoms live in group 3 by convention
(TheRobotStudio's and the menagerie's SO-101, and ours). A geom on a body the caller does not track (say a
camera mount welded to the gripper) is carried by its nearest tracked ancestor, provided no joint lies between
them; otherwise it cannot be posed from the tracked bodies and is left out with a warning.

Large meshes can be thinned to a face budget by vertex clustering (`fit_face_budget`): a fleet view of a
hundred arms cannot hold or draw a hundred copies of a 400,000-face CAD model, and at a millimetre the
clustered shape is indistinguishable at viewing distance.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import mujoco
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

# MuJoCo's viewer shows geom groups 0, 1 and 2 and hides 3..5 (mjvOption.geomgroup defaults).
VISIBLE_GROUPS: frozenset[int] = frozenset({0, 1, 2})
# The geom rgba MuJoCo uses when none is given; a material's colour applies only while the geom keeps it
# (MuJoCo XML reference, geom/material: a non-default rgba takes precedence over the material's).
DEFAULT_GEOM_RGBA = (0.5, 0.5, 0.5, 1.0)
# Tessellation of curved primitives: fine enough for a smooth silhouette at arm scale, small in triangles.
SLICES = 24
STACKS = 12
# Cell sizes tried by fit_face_budget, in metres: 0.5 mm up to 16 mm, each step x sqrt(2).
_CELLS_M = tuple(0.0005 * math.sqrt(2.0) ** k for k in range(11))


@dataclass(frozen=True, eq=False)
class VisualGeom:
    """One visual geom as triangles in its own frame, with its pose in the carrying body's frame."""

    name: str
    body: str  # the tracked body that moves it
    geom_id: int
    kind: str  # mesh, box, sphere, ellipsoid, cylinder, capsule
    vertices: np.ndarray  # (V, 3) float32, geom frame, metres
    faces: np.ndarray  # (F, 3) uint32, counter-clockwise seen from outside
    normals: np.ndarray  # (V, 3) float32, unit
    pos: np.ndarray  # (3,) geom origin in the body frame
    quat: np.ndarray  # (4,) geom orientation in the body frame, MuJoCo order (w, x, y, z)
    rgba: tuple[float, float, float, float]
    mesh_id: int = -1  # source mesh for mesh geoms (several geoms may share one mesh)

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])


def geom_rgba(model: mujoco.MjModel, geom: int) -> tuple[float, float, float, float]:
    """The colour MuJoCo draws a geom in: its own rgba if set, else its material's."""
    r, g, b, a = (float(v) for v in model.geom_rgba[geom])
    mat = int(model.geom_matid[geom])
    if mat >= 0 and np.allclose((r, g, b, a), DEFAULT_GEOM_RGBA):
        r, g, b, a = (float(v) for v in model.mat_rgba[mat])
    return r, g, b, a


def visual_geoms(model: mujoco.MjModel, bodies: Mapping[str, int]) -> list[VisualGeom]:
    """Every visual geom carried by one of `bodies` (name -> body id), in model order."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    carrier_of = _carriers(model, bodies)
    names = {bid: name for name, bid in bodies.items()}
    out: list[VisualGeom] = []
    for g in range(model.ngeom):
        if int(model.geom_group[g]) not in VISIBLE_GROUPS:
            continue
        rgba = geom_rgba(model, g)
        if rgba[3] <= 0.0:
            continue
        body = int(model.geom_bodyid[g])
        if body == 0:  # the world: floor and scenery, not the arm
            continue
        carrier = carrier_of.get(body)
        gname = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom_{g}"
        if carrier is None:
            log.warning(
                "visual geom %s is on body %s, which is neither tracked nor welded to a tracked body; "
                "it is left out of the meshes",
                gname,
                mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body),
            )
            continue
        shape = _triangles(model, g)
        if shape is None:
            continue
        kind, vertices, faces, normals = shape
        pos, quat = _pose_in(data, carrier, g)
        out.append(
            VisualGeom(
                name=gname,
                body=names[carrier],
                geom_id=g,
                kind=kind,
                vertices=vertices.astype(np.float32),
                faces=faces.astype(np.uint32),
                normals=normals.astype(np.float32),
                pos=pos,
                quat=quat,
                rgba=rgba,
                mesh_id=int(model.geom_dataid[g]) if kind == "mesh" else -1,
            )
        )
    return out


def _carriers(model: mujoco.MjModel, bodies: Mapping[str, int]) -> dict[int, int]:
    """Body id -> the tracked body whose pose carries it rigidly (itself, or an ancestor with no joint
    between). Bodies welded to the world without a tracked ancestor are carried by no one."""
    tracked = set(bodies.values())
    out: dict[int, int] = {}
    for b in range(1, model.nbody):
        cur = b
        while cur not in tracked:
            if model.body_jntnum[cur] > 0 or cur == 0:
                break
            cur = int(model.body_parentid[cur])
        if cur in tracked:
            out[b] = cur
    return out


def _pose_in(data: mujoco.MjData, body: int, geom: int) -> tuple[np.ndarray, np.ndarray]:
    """The geom's pose in the body's frame, from the model's reference pose (rigid, so any pose gives it)."""
    rb = data.xmat[body].reshape(3, 3)
    rg = data.geom_xmat[geom].reshape(3, 3)
    pos = rb.T @ (data.geom_xpos[geom] - data.xpos[body])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (rb.T @ rg).ravel())
    return pos, quat


def _triangles(model: mujoco.MjModel, g: int) -> tuple[str, np.ndarray, np.ndarray, np.ndarray] | None:
    gtype = int(model.geom_type[g])
    size = model.geom_size[g]
    if gtype == mujoco.mjtGeom.mjGEOM_MESH:
        mesh = int(model.geom_dataid[g])
        va, vn = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        fa, fn = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        vertices = np.array(model.mesh_vert[va : va + vn], dtype=np.float64)
        faces = np.array(model.mesh_face[fa : fa + fn], dtype=np.int64)
        return "mesh", vertices, faces, vertex_normals(vertices, faces)
    if gtype == mujoco.mjtGeom.mjGEOM_BOX:
        return ("box", *box(size))
    if gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
        return ("sphere", *ellipsoid((size[0], size[0], size[0])))
    if gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        return ("ellipsoid", *ellipsoid(size))
    if gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return ("cylinder", *cylinder(size[0], size[1]))
    if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return ("capsule", *capsule(size[0], size[1]))
    log.debug("geom %d of type %s is not drawn as a mesh", g, mujoco.mjtGeom(gtype).name)
    return None


# --- tessellation (all in the geom frame; MuJoCo's primitives are centred and aligned with z) -------------


def box(half: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """24 vertices (4 per side, so each side shades flat) and 12 triangles."""
    hx, hy, hz = (float(v) for v in half[:3])
    vertices: list[FloatArray] = []
    faces: list[tuple[int, int, int]] = []
    normals: list[FloatArray] = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            u = np.zeros(3)
            v = np.zeros(3)
            u[(axis + 1) % 3] = 1.0
            v[(axis + 2) % 3] = 1.0
            if sign < 0:
                u, v = v, u  # keep counter-clockwise seen from outside
            base = len(vertices)
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                vertices.append(n + a * u + b * v)
                normals.append(n)
            faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    verts = np.array(vertices) * np.array([hx, hy, hz])
    return verts, np.array(faces), np.array(normals)


def ellipsoid(radii: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A UV sphere scaled by the radii; normals follow the scaled surface."""
    r = np.array([float(v) for v in radii[:3]])
    profile = []
    for k in range(STACKS + 1):
        theta = math.pi * k / STACKS
        s, c = math.sin(theta), math.cos(theta)
        profile.append((0.0 if k in (0, STACKS) else s, c, s, c))
    unit, faces, _ = lathe(profile)
    normals = unit / r
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return unit * r, faces, normals


def cylinder(radius: float, half_length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Side and two flat caps; the rims are doubled so the caps shade flat."""
    r, h = float(radius), float(half_length)
    top, side, bottom = (0.0, 1.0), (1.0, 0.0), (0.0, -1.0)
    return lathe(
        [(0.0, h, *top), (r, h, *top), (r, h, *side), (r, -h, *side), (r, -h, *bottom), (0.0, -h, *bottom)]
    )


def capsule(radius: float, half_length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two hemispheres of the radius joined by a straight side of twice the half length."""
    r, h = float(radius), float(half_length)
    half = max(2, STACKS // 2)
    profile = []
    for k in range(half + 1):  # top pole down to the upper equator
        theta = 0.5 * math.pi * k / half
        s, c = math.sin(theta), math.cos(theta)
        profile.append((0.0 if k == 0 else r * s, h + r * c, s, c))
    for k in range(half + 1):  # lower equator down to the bottom pole
        theta = 0.5 * math.pi + 0.5 * math.pi * k / half
        s, c = math.sin(theta), math.cos(theta)
        profile.append((0.0 if k == half else r * s, -h + r * c, s, c))
    return lathe(profile)


def lathe(
    profile: Sequence[tuple[float, float, float, float]], slices: int = SLICES
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A surface of revolution about z from a profile running top to bottom.

    Each profile entry is (radius, z, radial normal, z normal); radius 0 makes one pole vertex, anything
    else a ring of `slices` vertices. Consecutive entries are joined by quads or fans, counter-clockwise
    seen from outside, so outward normals and winding agree; an entry repeated with another normal makes a
    sharp edge (a cylinder's rim).
    """
    ang = np.linspace(0.0, 2.0 * math.pi, slices, endpoint=False)
    cos, sin = np.cos(ang), np.sin(ang)
    vertices: list[np.ndarray] = []
    normals: list[np.ndarray] = []
    starts: list[tuple[int, bool]] = []  # (first vertex index, is pole)
    count = 0
    for radius, z, nr, nz in profile:
        n = np.array([nr, nz])
        n = n / np.linalg.norm(n)
        if radius == 0.0:
            vertices.append(np.array([[0.0, 0.0, z]]))
            normals.append(np.array([[0.0, 0.0, math.copysign(1.0, nz)]]))
            starts.append((count, True))
            count += 1
        else:
            vertices.append(np.stack([radius * cos, radius * sin, np.full(slices, z)], axis=1))
            normals.append(np.stack([n[0] * cos, n[0] * sin, np.full(slices, n[1])], axis=1))
            starts.append((count, False))
            count += slices
    faces: list[tuple[int, int, int]] = []
    for k, ((a0, a_pole), (b0, b_pole)) in enumerate(itertools.pairwise(starts)):
        if profile[k][:2] == profile[k + 1][:2]:
            continue  # the same ring twice with two normals: a crease, not a strip
        for i in range(slices):
            j = (i + 1) % slices
            if a_pole and not b_pole:
                faces.append((a0, b0 + i, b0 + j))
            elif b_pole and not a_pole:
                faces.append((b0, a0 + j, a0 + i))
            elif not a_pole and not b_pole:
                faces += [(a0 + i, b0 + i, b0 + j), (a0 + i, b0 + j, a0 + j)]
    return np.vstack(vertices), np.array(faces, dtype=np.int64), np.vstack(normals)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit; a vertex on no face gets +z)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], cross)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out: FloatArray = np.divide(acc, norm, out=np.tile([0.0, 0.0, 1.0], (len(v), 1)), where=norm > 0)
    return out


# --- face budget --------------------------------------------------------------------------------------------


def cluster_vertices(vertices: np.ndarray, faces: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering (Rossignac and Borrel): snap vertices to a grid of `cell_m`, merge each cell into
    its mean, and drop the triangles that collapse. Fast and robust on the unwelded triangle soup STL files
    are, and the error is bounded by the cell size."""
    v = np.asarray(vertices, dtype=np.float64)
    cells = np.floor(v / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    # One integer key per cell: a 1-D unique is many times faster than np.unique(axis=0) on rows.
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    merged = np.zeros((counts.size, 3))
    np.add.at(merged, inverse, v)
    merged /= counts[:, None]
    f = inverse[np.asarray(faces, dtype=np.int64)]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    # Two triangles that collapse onto the same three cells would draw twice; keep the first.
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    used = np.unique(f)
    remap = np.full(counts.size, -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return merged[used], remap[f]


def fit_face_budget(geoms: Sequence[VisualGeom], max_faces: int) -> tuple[list[VisualGeom], float | None]:
    """The geoms with their meshes clustered at the finest cell that brings the total under `max_faces`.

    Primitives are small and kept as they are. Returns the geoms and the cell size used (None when the
    meshes already fit). When even the coarsest cell does not fit, that coarsest result is returned."""
    total = sum(g.face_count for g in geoms)
    if total <= max_faces:
        return list(geoms), None
    meshes = {g.mesh_id: (g.vertices, g.faces) for g in geoms if g.kind == "mesh"}
    if not meshes:
        return list(geoms), None
    fixed = sum(g.face_count for g in geoms if g.kind != "mesh")
    uses: dict[int, int] = {}
    for g in geoms:
        if g.kind == "mesh":
            uses[g.mesh_id] = uses.get(g.mesh_id, 0) + 1
    result: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    cell = _CELLS_M[-1]
    for cell in _CELLS_M:
        result = {mid: cluster_vertices(v, f, cell) for mid, (v, f) in meshes.items()}
        if fixed + sum(len(f) * uses[mid] for mid, (_, f) in result.items()) <= max_faces:
            break
    out = []
    for g in geoms:
        if g.kind != "mesh":
            out.append(g)
            continue
        v, f = result[g.mesh_id]
        out.append(
            replace(
                g,
                vertices=v.astype(np.float32),
                faces=f.astype(np.uint32),
                normals=vertex_normals(v, f).astype(np.float32),
            )
        )
    log.info(
        "visual meshes thinned from %d to %d faces (vertex clustering at %.1f mm) to fit %d per arm",
        total,
        sum(g.face_count for g in out),
        cell * 1000.0,
        max_faces,
    )
    return out, cell
