"""Render: what drawing the part meshes offscreen costs (model load, a 640x480 frame, the demo pictures).

The figures run in a child process with MUJOCO_GL=egl (MuJoCo binds its GL backend when it is first imported,
and a benchmark run may already have imported it), one renderer for all frames as `twin.output.render` uses.
Per frame: wall time (what a caller waits) and the process's CPU time (every llvmpipe thread; steadier than
wall time on a busy machine). The frames are drawn as the pictures are (`offscreen_renderer`: the key light's
shadow, no floor reflection); `scene_costs` times the framed view again with each combination of the two
passes (neither, the shadow only as the pictures, the reflection only, both as `twin view` draws), so what
each pass costs is measured, not remembered. The 1-minute load average before and after travels with the
figures: on a shared machine they are only comparable at similar load.

    python -m twin.bench.render [--frames 40] [--width 640] [--height 480] [--model MJCF]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

WARMUP_FRAMES = 5  # shader compilation and texture upload happen on the first frames


def _poses(count: int, ranges: dict[str, tuple[float, float]]) -> list[dict[str, float]]:
    rng = random.Random(101)
    return [{name: rng.uniform(lo, hi) for name, (lo, hi) in ranges.items()} for _ in range(count)]


def _percentiles(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {
        "p50": statistics.median(ordered),
        "p90": ordered[min(len(ordered) - 1, round(0.9 * (len(ordered) - 1)))],
        "min": ordered[0],
    }


def _gl_renderer() -> str:
    try:
        from OpenGL import GL  # noqa: PLC0415 - mujoco's EGL backend brings PyOpenGL

        return GL.glGetString(GL.GL_RENDERER).decode()
    except Exception:  # a missing binding or context only costs this label
        return "unknown"


def _time_frames(
    renderer: Any, robot: Any, data: Any, poses: list[dict[str, float]], *, view: str | None, aspect: float
) -> dict[str, Any]:
    """Wall and CPU milliseconds per frame (scene update, draw, readback) over `poses`, after warm-up.

    `view` is a camera name, or None to frame the arm in each pose as `twin render` does.
    """
    import mujoco  # noqa: PLC0415

    from twin.output.render import framing_camera  # noqa: PLC0415

    wall, cpu = [], []
    for i, pose in enumerate([poses[0]] * WARMUP_FRAMES + poses):
        for name, value in pose.items():
            data.qpos[robot.qpos_addr[name]] = value
        mujoco.mj_forward(robot.model, data)
        camera = view if view is not None else framing_camera(robot, [pose], aspect=aspect)
        t0, c0 = time.perf_counter(), time.process_time()
        renderer.update_scene(data, camera=camera)
        renderer.render()
        if i >= WARMUP_FRAMES:
            wall.append((time.perf_counter() - t0) * 1000)
            cpu.append((time.process_time() - c0) * 1000)
    return {"wall_ms": _percentiles(wall), "cpu_ms": _percentiles(cpu)}


def measure(
    *, frames: int = 40, width: int = 640, height: int = 480, model: str | None = None
) -> dict[str, Any]:
    """The figures, measured in this process (MUJOCO_GL must be set before mujoco is imported)."""

    from twin.robot.model import RobotModel  # noqa: PLC0415

    load_before = os.getloadavg()[0]
    loads = []
    for _ in range(3):
        started = time.perf_counter()
        robot = RobotModel.load(model)
        loads.append(time.perf_counter() - started)
    m = robot.model
    poses = _poses(frames, robot.joint_ranges)
    frame = _time_views(robot, poses, width, height)
    png_s, gif_s = _demo_pictures(robot, poses)
    return {
        "scenario": "render",
        "gl_renderer": frame["gl_renderer"],
        "model": str(robot.path),
        "meshes": int(m.nmesh),
        "mesh_faces": int(m.nmeshface),
        "geoms": int(m.ngeom),
        "model_load_s": statistics.median(loads),
        "frame_size": f"{width}x{height}",
        "frames": frames,
        # How the timed frames were drawn: the flags the pictures set, multisampling, the shadow map's size.
        "scene_flags": frame["scene_flags"],
        "msaa_samples": int(m.vis.quality.offsamples),
        "shadow_size": int(m.vis.quality.shadowsize),
        "frame": frame["per_view"],
        # The framed view again with each combination of the shadow and reflection passes.
        "scene_costs": frame["scene_costs"],
        "target_frame_ms": 150.0,
        # What `twin demo` spends on pictures: its PNG (640x480, renderer made per call) and 30-frame GIF.
        "demo_png_s": png_s,
        "demo_gif_30_frames_s": gif_s,
        "load_average_1m": {"before": load_before, "after": os.getloadavg()[0]},
    }


def _time_views(robot: Any, poses: list[dict[str, float]], width: int, height: int) -> dict[str, Any]:
    """Frames as the pictures draw them, per view; then the framed view with each combination of the shadow
    and reflection passes (absolute settings, whatever the pictures' own flags are)."""
    import mujoco  # noqa: PLC0415

    from twin.output.render import OFFSCREEN_SCENE_FLAGS, offscreen_renderer  # noqa: PLC0415

    m = robot.model
    data = mujoco.MjData(m)
    views: dict[str, str | None] = {"framed": None}
    if "overview" in robot.camera_names:
        views["overview"] = "overview"
    shadow, reflection = mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION
    pass_sets = {
        "neither": {shadow: False, reflection: False},
        "shadow_only": {shadow: True, reflection: False},
        "reflection_only": {shadow: False, reflection: True},
        "shadow_and_reflection": {shadow: True, reflection: True},
    }
    with offscreen_renderer(m, width, height) as renderer:
        out: dict[str, Any] = {
            "gl_renderer": _gl_renderer(),
            "scene_flags": {
                mujoco.mjtRndFlag(flag).name: bool(renderer.scene.flags[flag])
                for flag in {shadow, reflection, *OFFSCREEN_SCENE_FLAGS}
            },
            "per_view": {
                label: _time_frames(renderer, robot, data, poses, view=view, aspect=width / height)
                for label, view in views.items()
            },
            "scene_costs": {},
        }
        offscreen_flags = renderer.scene.flags.copy()
        for label, flags in pass_sets.items():
            renderer.scene.flags[:] = offscreen_flags
            for flag, enabled in flags.items():
                renderer.scene.flags[flag] = enabled
            out["scene_costs"][label] = _time_frames(
                renderer, robot, data, poses, view=None, aspect=width / height
            )
        renderer.scene.flags[:] = offscreen_flags
    return out


def _demo_pictures(robot: Any, poses: list[dict[str, float]]) -> tuple[float, float]:
    """Seconds for the demo's PNG (640x480, its renderer made per call) and its 30-frame GIF."""
    from twin.output.render import render_gif, render_png  # noqa: PLC0415

    with tempfile.TemporaryDirectory(prefix="twin-bench-render-") as tmp:
        started = time.perf_counter()
        render_png(robot, poses[0], Path(tmp) / "twin.png")
        png_s = time.perf_counter() - started
        started = time.perf_counter()
        render_gif(robot, poses[:30], Path(tmp) / "twin.gif")
        return png_s, time.perf_counter() - started


def run(*, frames: int = 40, width: int = 640, height: int = 480, model: str | None = None) -> dict[str, Any]:
    """Measure in a child process with an offscreen GL backend; returns the figures."""
    args = [sys.executable, "-m", "twin.bench.render", "--frames", str(frames)]
    args += ["--width", str(width), "--height", str(height)]
    if model:
        args += ["--model", model]
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env.setdefault("PYOPENGL_PLATFORM", env["MUJOCO_GL"])
    done = subprocess.run(args, capture_output=True, text=True, env=env, timeout=600, check=False)
    if done.returncode != 0:
        raise RuntimeError(
            f"the render benchmark failed (exit {done.returncode}): {done.stderr.strip()[-800:]}"
        )
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if not lines:
        raise RuntimeError(f"the render benchmark printed no figures: {done.stdout[-500:]!r}")
    return json.loads(lines[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--model", default=None)
    args = parser.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    figures = measure(frames=args.frames, width=args.width, height=args.height, model=args.model)
    sys.stdout.write(json.dumps(figures) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
