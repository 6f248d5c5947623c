"""Offscreen PNG renders of the arm in a given pose (for the CLI, docs and checks without a display).

MuJoCo picks its OpenGL backend when it is first imported, from MUJOCO_GL: headless hosts need
MUJOCO_GL=egl (or osmesa) set before anything imports mujoco. `twin render` and the Makefile set it.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from pathlib import Path

import mujoco
import numpy as np

from twin.core.twin import DeviceTwin, TwinMode
from twin.robot.model import RobotModel

log = logging.getLogger(__name__)

DEFAULT_CAMERA = "overview"
# Free-camera view when the model has no overview camera: front-left and above, like the scene's default.
_FREE_AZIMUTH_DEG = 140.0
_FREE_ELEVATION_DEG = -25.0


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


def _free_camera(robot: RobotModel, data: mujoco.MjData) -> mujoco.MjvCamera:
    # Frame the arm's bodies in this pose: centre on their bounding box, back off so the box fits the fovy.
    ids = list(robot.body_ids.values()) or list(range(1, robot.model.nbody))
    points = data.xpos[ids]
    if robot.tcp_site_id is not None:
        points = np.vstack([points, data.site_xpos[robot.tcp_site_id]])
    lo = points.min(axis=0)
    hi = points.max(axis=0)
    radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 0.05) + 0.03  # margin for the link geometry
    fovy = np.deg2rad(float(robot.model.vis.global_.fovy))
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = (lo + hi) / 2.0
    camera.distance = radius / np.sin(fovy / 2.0)
    camera.azimuth = _FREE_AZIMUTH_DEG
    camera.elevation = _FREE_ELEVATION_DEG
    return camera


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


def _renderer(model: mujoco.MjModel, width: int, height: int) -> mujoco.Renderer:
    _check_gl_backend()
    try:
        return mujoco.Renderer(model, height=height, width=width)
    except Exception as exc:  # the GL backends raise assorted types (FatalError, GLFWError, ImportError)
        backend = os.environ.get("MUJOCO_GL", "<unset: glfw, needs a display>")
        raise RenderError(
            f"could not create an OpenGL context for rendering (MUJOCO_GL={backend}): {exc}. On a headless "
            "host set MUJOCO_GL=egl (or osmesa) in the environment before starting the process."
        ) from exc


def render_png(
    robot: RobotModel,
    joint_angles: Mapping[str, float],
    path: str | Path,
    *,
    width: int = 640,
    height: int = 480,
    camera: str | None = None,
    text: str | None = None,
) -> Path:
    """Render the arm with `joint_angles` (radians by joint name; missing joints at 0) to a PNG at `path`.

    Angles are clamped to the joint ranges, as the twin does. `camera` names a model camera; None uses
    "overview" when the model has one, else a free camera framing the arm. `text` is drawn in the top-left
    corner. Returns the written path. Raises RenderError when no GL context can be made or the camera is
    unknown.
    """
    from PIL import Image  # noqa: PLC0415 - keep PIL out of importers that never render

    if width <= 0 or height <= 0:
        raise RenderError(f"image size {width}x{height} is not positive; pass a width and height >= 1")
    model = robot.model
    if camera is not None and camera not in robot.camera_names:
        available = ", ".join(robot.camera_names) or "none"
        raise RenderError(
            f"camera {camera!r} is not in {robot.path} (cameras: {available}); pick one of those or omit it "
            "for the default view"
        )
    twin = DeviceTwin(robot, "render", TwinMode.KINEMATIC)
    twin.apply({name: joint_angles.get(name, 0.0) for name in robot.joint_names}, 0)
    data = twin.data
    mujoco.mj_forward(model, data)

    # The offscreen buffer is sized by the model; growing it only affects renderers created afterwards.
    vis = model.vis.global_
    vis.offwidth = max(vis.offwidth, width)
    vis.offheight = max(vis.offheight, height)

    name = camera
    if name is None and DEFAULT_CAMERA in robot.camera_names:
        name = DEFAULT_CAMERA
    view: str | mujoco.MjvCamera = name if name is not None else _free_camera(robot, data)
    with _renderer(model, width, height) as renderer:
        renderer.update_scene(data, camera=view)
        pixels = renderer.render()
    if text:
        pixels = _overlay_text(pixels, text)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(out, format="PNG")
    log.debug("rendered %s (%dx%d, camera %s)", out, width, height, name or "free")
    return out
