"""The arm's visual meshes per body, in body coordinates, from a compiled MuJoCo model.

For anything that draws the twin outside MuJoCo (a Rerun or web viewer, a mesh export): each body's part
meshes as vertices and triangles in that body's frame, so placing them needs only the body's world pose
(`RobotModel.body_poses`). MuJoCo moves a mesh's vertices to its inertial frame when it compiles the model
and folds the inverse into the geom's pos/quat, so the compiled `mesh_vert` must be taken together with the
compiled `geom_pos`/`geom_quat`, never with the numbers written in the MJCF.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from twin.robot import so101


@dataclass(frozen=True)
class VisualMesh:
    """One mesh geom: `vertices` (N, 3) float64 in the body frame (metres), `faces` (M, 3) int32 indices into
    them, counter-clockwise seen from outside; `rgba` (4,) its material colour."""

    name: str
    body: str
    mesh: str
    vertices: np.ndarray
    faces: np.ndarray
    rgba: np.ndarray


def _geom_rgba(model: mujoco.MjModel, geom: int) -> np.ndarray:
    mat = int(model.geom_matid[geom])
    return (model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[geom]).astype(np.float64).copy()


def visual_meshes(model: mujoco.MjModel, group: int = so101.VISUAL_GROUP) -> dict[str, list[VisualMesh]]:
    """Mesh geoms of `group` by body name (bodies without any are left out), in model order."""
    out: dict[str, list[VisualMesh]] = {}
    rotation = np.empty(9)
    for geom in range(model.ngeom):
        if model.geom_type[geom] != mujoco.mjtGeom.mjGEOM_MESH or model.geom_group[geom] != group:
            continue
        mesh = int(model.geom_dataid[geom])
        v0, nv = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        f0, nf = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        mujoco.mju_quat2Mat(rotation, model.geom_quat[geom])
        vertices = model.mesh_vert[v0 : v0 + nv].astype(np.float64) @ rotation.reshape(3, 3).T
        vertices += model.geom_pos[geom]
        body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[geom])) or ""
        out.setdefault(body, []).append(
            VisualMesh(
                name=mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom) or f"geom{geom}",
                body=body,
                mesh=mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_MESH, mesh) or f"mesh{mesh}",
                vertices=vertices,
                faces=model.mesh_face[f0 : f0 + nf].astype(np.int32),
                rgba=_geom_rgba(model, geom),
            )
        )
    return out
