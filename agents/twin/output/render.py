"""Offscreen PNG renders of the arm in a given pose (for the CLI, docs and checks without a display).

MuJoCo picks its OpenGL backend when it is first imported, from MUJOCO_GL: headless hosts need
MUJOCO_GL=egl (or osmesa) set before anything imports mujoco. `twin render` and the Makefile set it.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType

import mujoco
import numpy as np

from twin.core.modes import TwinMode
from twin.core.twin import DeviceTwin
from twin.robot import so101
from twin.robot.model import RobotModel

log = logging.getLogger(__name__)

# The default view: from the front-left and above (MuJoCo free-camera degrees), the arm fitted into the image.
FRAMING_AZIMUTH_DEG = 140.0
FRAMING_ELEVATION_DEG = -22.0
FRAMING_MARGIN = 0.08

# Scene render flags that offscreen pictures change from MuJoCo's defaults. Where pictures are made (the CLI,
# the demo, CI) there is no GPU and llvmpipe draws on the CPU. The floor's reflection, a mirrored pass of the
# whole arm for a faint image under the base, is off. The key light's shadow (a depth pass over every triangle
# plus a second full colour pass lit by that light alone) costs more but stays: it is the cue for how high the
# gripper is above the floor, and without it the arm looks as if it floats. At 640x480 with the part meshes a
# frame takes about 102 ms of CPU with the shadow, 125 with the reflection too and 42 with neither (p50,
# docs/robot-model.md); llvmpipe spreads it over both cores, about 60 ms wall on a quiet machine, inside the
# 150 ms target. Multisampling stays: without it llvmpipe saves another 26 ms, but every edge and grid line
# turns to stairs. `twin view` keeps MuJoCo's defaults: its desktop has a GPU.
OFFSCREEN_SCENE_FLAGS: Mapping[mujoco.mjtRndFlag, bool] = MappingProxyType(
    {
        mujoco.mjtRndFlag.mjRND_REFLECTION: False,
    }
)


class RenderError(RuntimeError):
    """Rendering failed (no OpenGL context, unknown camera ...); the message says what to change."""


def _check_gl_backend() -> None:
    # GLFW/GLX without a display aborts the whole process inside MuJoCo instead of raising, so refuse first.
    if sys.platform != "linux" or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return
    try:
        from mujoco.rendering.classic import gl_context  # noqa: PLC0415 - only to read the bound backend

        bound = str(getattr(gl_context, "_MUJOCO_GL", os.environ.get("MUJOCO_GL", "")))
    except ImportError:
        bound = os.environ.get("MUJOCO_GL", "")
    if bound.lower() not in ("egl", "osmesa"):
        raise RenderError(
            f"MuJoCo was imported with MUJOCO_GL={bound or '<unset>'} (GLFW, needs a display) and no DISPLAY "
            "is set. Set MUJOCO_GL=egl (or osmesa) in the environment before the process starts."
        )


def _arm_geoms(robot: RobotModel) -> np.ndarray:
    """Geoms drawn by default (groups 0-2) on the arm's bodies: what a framed picture must hold."""
    model = robot.model
    bodies = list(robot.body_ids.values()) or list(range(1, model.nbody))
    geoms = [
        g
        for g in range(model.ngeom)
        if int(model.geom_bodyid[g]) in bodies
        and model.geom_group[g] <= so101.VISUAL_GROUP
        and model.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE
    ]
    return np.asarray(geoms, dtype=int)


def _geom_points(model: mujoco.MjModel, data: mujoco.MjData, geoms: np.ndarray) -> np.ndarray:
    """World points that bound what the geoms draw: a mesh's vertices, other geoms' bounding-box corners."""
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    chunks = []
    for g in geoms:
        rotation = data.geom_xmat[g].reshape(3, 3)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            mesh = model.geom_dataid[g]
            start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            local = model.mesh_vert[start : start + count]
        else:
            aabb = model.geom_aabb[g]  # centre then half-sizes, in the geom's frame
            local = aabb[:3] + signs * aabb[3:]
        chunks.append(local @ rotation.T + data.geom_xpos[g])
    return np.vstack(chunks)


def reach_poses(robot: RobotModel) -> list[dict[str, float]]:
    """Poses that span where the arm usually is: stretched forward straight ahead and at both pan limits,
    raised upright, and LeRobot's folded rest pose. Framing them all keeps any ordinary pose in view."""
    pan_lo, pan_hi = robot.joint_ranges.get(so101.JOINT_NAMES[0], (0.0, 0.0))
    upright = {"shoulder_lift": 0.0, "elbow_flex": -1.57}
    rest = {"shoulder_lift": -1.726, "elbow_flex": 1.698, "wrist_flex": 1.112}
    return [{}, {"shoulder_pan": pan_lo}, {"shoulder_pan": pan_hi}, upright, rest]


def framing_camera(
    robot: RobotModel,
    poses: Iterable[Mapping[str, float]],
    *,
    aspect: float = 4 / 3,
    azimuth: float = FRAMING_AZIMUTH_DEG,
    elevation: float = FRAMING_ELEVATION_DEG,
    margin: float = FRAMING_MARGIN,
) -> mujoco.MjvCamera:
    """A free camera that shows the arm in every pose of `poses` as large as the image allows.

    The view direction is fixed (azimuth/elevation, degrees, MuJoCo's free-camera convention) so pictures of
    different poses compare; the look-at point and distance fit the arm's visible geoms (mesh vertices, other
    geoms' bounding boxes) in all poses into the field of view (`aspect` = width / height) with `margin` (a
    fraction of the half width/height) to spare. Angles are clamped to the joint ranges; missing joints sit
    at 0.
    """
    cloud = _visible_points(robot, poses)
    az, el = np.deg2rad(azimuth), np.deg2rad(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    tan_v = np.tan(np.deg2rad(float(robot.model.vis.global_.fovy)) / 2.0) * (1.0 - margin)
    centre, distance = _fit_view(cloud, (forward, right, up), tan_h=tan_v * aspect, tan_v=tan_v)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = centre
    camera.distance = distance
    camera.azimuth = azimuth
    camera.elevation = elevation
    return camera


def _visible_points(robot: RobotModel, poses: Iterable[Mapping[str, float]]) -> np.ndarray:
    """The arm's visible geometry in world coordinates over all `poses` (mesh vertices, other geoms' bounding
    boxes; body origins when the model has no arm geoms), angles clamped to the joint ranges."""
    model = robot.model
    data = mujoco.MjData(model)
    geoms = _arm_geoms(robot)
    points = []
    for pose in poses:
        data.qpos[:] = model.qpos0
        for name, value in pose.items():
            if name in robot.qpos_addr:
                lo, hi = robot.joint_ranges[name]
                data.qpos[robot.qpos_addr[name]] = min(max(float(value), lo), hi)
        mujoco.mj_kinematics(model, data)
        points.append(_geom_points(model, data, geoms) if geoms.size else data.xpos[1:].copy())
    if not points:
        raise RenderError("no poses to frame; pass at least one pose (an empty dict is the zero pose)")
    return np.vstack(points)


def _fit_view(
    cloud: np.ndarray, axes: tuple[np.ndarray, np.ndarray, np.ndarray], *, tan_h: float, tan_v: float
) -> tuple[np.ndarray, float]:
    """The look-at point and distance that put every point of `cloud` inside the view along `axes` (forward,
    right, up), whose half-angles have these tangents."""
    forward, right, up = axes
    centre = cloud.mean(axis=0)
    distance = 0.0
    # Centring depends on the distance (perspective spreads near points wider) and the distance on the centre:
    # a few rounds of each settle to well under a pixel.
    for _ in range(4):
        rel = cloud - centre
        x, y, depth = rel @ right, rel @ up, rel @ forward
        if distance > 0.0:
            scale = distance / np.maximum(distance + depth, 1e-6)  # perspective: nearer points spread wider
            x, y = x * scale, y * scale
        centre = centre + right * (x.max() + x.min()) / 2.0 + up * (y.max() + y.min()) / 2.0
        rel = cloud - centre
        x, y, depth = np.abs(rel @ right), np.abs(rel @ up), rel @ forward
        # A point at depth d beyond the look-at point is inside the view when |x| <= tan_h * (distance + d).
        distance = float(max((x / tan_h - depth).max(), (y / tan_v - depth).max(), 0.05))
    return centre, distance


def _overlay_text(pixels: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw, ImageFont  # noqa: PLC0415 - only needed with an overlay

    image = Image.fromarray(pixels)
    draw = ImageDraw.Draw(image)
    size = max(12, image.height // 32)
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has only the fixed bitmap font
        font = ImageFont.load_default()
    left, top, right, bottom = draw.textbbox((8, 8), text, font=font)
    # A dark band keeps the text legible over the light sky and the yellow arm alike.
    draw.rectangle((left - 4, top - 4, right + 4, bottom + 4), fill=(0, 0, 0))
    draw.text((8, 8), text, fill=(255, 255, 255), font=font)
    return np.asarray(image)


def offscreen_renderer(model: mujoco.MjModel, width: int, height: int) -> mujoco.Renderer:
    """A renderer for offscreen pictures of `width` x `height`, drawing with OFFSCREEN_SCENE_FLAGS.

    Grows the model's offscreen buffer when the picture is larger (it only affects renderers made afterwards).
    Raises RenderError when no OpenGL context can be made; the caller closes the renderer (`with ...`).
    """
    _check_gl_backend()
    vis = model.vis.global_
    vis.offwidth = max(vis.offwidth, width)
    vis.offheight = max(vis.offheight, height)
    try:
        renderer = mujoco.Renderer(model, height=height, width=width)
    except Exception as exc:  # the GL backends raise assorted types (FatalError, GLFWError, ImportError)
        backend = os.environ.get("MUJOCO_GL", "<unset: glfw, needs a display>")
        raise RenderError(
            f"could not create an OpenGL context for rendering (MUJOCO_GL={backend}): {exc}. On a headless "
            "host set MUJOCO_GL=egl (or osmesa) in the environment before starting the process."
        ) from exc
    # The scene keeps its flags across update_scene calls, so setting them once holds for every frame.
    for flag, enabled in OFFSCREEN_SCENE_FLAGS.items():
        renderer.scene.flags[flag] = enabled
    return renderer


def render_png(
    robot: RobotModel,
    joint_angles: Mapping[str, float],
    path: str | Path,
    *,
    width: int = 640,
    height: int = 480,
    camera: str | mujoco.MjvCamera | None = None,
    text: str | None = None,
) -> Path:
    """Render the arm with `joint_angles` (radians by joint name; missing joints at 0) to a PNG at `path`.

    Angles are clamped to the joint ranges, as the twin does. `camera` names a model camera (the bundled
    scene's "overview" keeps the whole reach over the pan range in view) or is a free camera (e.g. one
    `framing_camera` made for several poses); None frames the arm in this pose. `text` is drawn in the
    top-left corner. Drawn with the key light's shadow but without the floor's reflection
    (OFFSCREEN_SCENE_FLAGS). Returns the written path. Raises RenderError when no GL context can be made or
    the camera is unknown.
    """
    from PIL import Image  # noqa: PLC0415 - keep PIL out of importers that never render

    if width <= 0 or height <= 0:
        raise RenderError(f"image size {width}x{height} is not positive; pass a width and height >= 1")
    model = robot.model
    if isinstance(camera, str) and camera not in robot.camera_names:
        available = ", ".join(robot.camera_names) or "none"
        raise RenderError(
            f"camera {camera!r} is not in {robot.path} (cameras: {available}); pick one of those or omit it "
            "for the default view"
        )
    twin = DeviceTwin(robot, "render", TwinMode.KINEMATIC)
    twin.apply({name: joint_angles.get(name, 0.0) for name in robot.joint_names}, 0)
    data = twin.data
    mujoco.mj_forward(model, data)

    view: str | mujoco.MjvCamera = (
        camera if camera is not None else framing_camera(robot, [joint_angles], aspect=width / height)
    )
    with offscreen_renderer(model, width, height) as renderer:
        renderer.update_scene(data, camera=view)
        pixels = renderer.render()
    if text:
        pixels = _overlay_text(pixels, text)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(out, format="PNG")
    log.debug(
        "rendered %s (%dx%d, camera %s)", out, width, height, camera if isinstance(camera, str) else "free"
    )
    return out


def render_gif(
    robot: RobotModel,
    frames: Sequence[Mapping[str, float]],
    path: str | Path,
    *,
    width: int = 320,
    height: int = 240,
    camera: str | mujoco.MjvCamera | None = None,
    frame_ms: int = 100,
) -> Path:
    """An animated GIF of `frames` (joint angles in radians by name, clamped to the ranges), one offscreen
    renderer for all of them. None frames every pose at once (`framing_camera`), so the view holds still while
    the arm moves; a model camera name or a free camera may be given instead. Returns the written path; raises
    RenderError when there are no frames, no GL context or an unknown camera.
    """
    from PIL import Image  # noqa: PLC0415 - keep PIL out of importers that never render

    if not frames:
        raise RenderError("no frames to animate; pass at least one pose")
    if width <= 0 or height <= 0:
        raise RenderError(f"image size {width}x{height} is not positive; pass a width and height >= 1")
    if isinstance(camera, str) and camera not in robot.camera_names:
        available = ", ".join(robot.camera_names) or "none"
        raise RenderError(f"camera {camera!r} is not in {robot.path} (cameras: {available})")
    model = robot.model
    view = camera if camera is not None else framing_camera(robot, frames, aspect=width / height)
    data = mujoco.MjData(model)
    images = []
    with offscreen_renderer(model, width, height) as renderer:
        for angles in frames:
            data.qpos[:] = model.qpos0
            for name, value in angles.items():
                if name in robot.qpos_addr:
                    lo, hi = robot.joint_ranges[name]
                    data.qpos[robot.qpos_addr[name]] = min(max(float(value), lo), hi)
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=view)
            images.append(Image.fromarray(renderer.render()))
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(out, save_all=True, append_images=images[1:], duration=frame_ms, loop=0)
    return out
