"""`twin view`: a MuJoCo passive viewer that follows the agent's live state.

Three parts, each with one job:
- `AgentFeed` (twin.viewer.feed, background thread) reads the agent's SSE `/stream`, falling back to polling
  `/state`, and retries forever while the agent is unreachable; it never touches MuJoCo.
- `FleetView` (twin.viewer.fleet, thread-safe) keeps, per device, the latest health figures and a smoothing
  estimator (`twin.core.smoothing`) fed with (edge timestamp, angles, local receive time).
- `TwinViewer` (here) owns the display loop, the MuJoCo way: at ~60 Hz it asks the estimator for the pose at
  the current instant, writes qpos under `handle.lock()`, runs forward kinematics, colours each joint by its
  worst servo alarm, updates the overlay text and calls `handle.sync()`. It ends when the window closes or
  `stop()` is called (SIGTERM in `twin view`).

docs/viewer.md describes the overlay, the keys and the smoothing.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from twin.core.smoothing import make_estimator
from twin.service.state import ServoState
from twin.viewer.config import ViewerConfig
from twin.viewer.feed import AgentFeed
from twin.viewer.fleet import LINK_CONNECTING, LINK_UNREACHABLE, DevicePicker, FleetView

log = logging.getLogger(__name__)

Clock = Callable[[], float]
# Ids on the overlay's Devices line: the shown arm and its neighbours. The whole list ran off the screen at
# fleet scale (the Device line says where the shown arm is in it).
DEVICES_SHOWN = 7
# Arms named on the Others line; the rest are counted.
OTHERS_NAMED = 3


def _fmt(value: float | None, unit: str, scale: float = 1.0, digits: int = 1) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f} {unit}"


def overlay_lines(
    config: ViewerConfig,
    fleet: FleetView,
    *,
    device: str | None,
    devices: list[str],
    now: float,
    fps: float,
) -> tuple[str, str]:
    """(labels, values) columns of the status overlay."""
    rows: list[tuple[str, str]] = []
    if fleet.link == LINK_UNREACHABLE:
        down_for = now - fleet.link_since
        rows.append(("Agent", f"agent unreachable ({fleet.link_error}); retrying [{down_for:.0f} s]"))
    elif fleet.bad_snapshots and not fleet.snapshots:
        # Answers, but not an agent's state (another service on that port): said where the eye is.
        rows.append(
            ("Agent", f"{config.agent_url}: {fleet.bad_snapshots} answers that are not a twin agent's state")
        )
    elif fleet.link == LINK_CONNECTING:
        rows.append(("Agent", f"connecting to {config.agent_url}"))
    else:
        rows.append(("Agent", f"{config.agent_url} ({fleet.link})"))
    if device is None:
        rows.append(("Device", "waiting for devices"))
    else:
        position = f" ({devices.index(device) + 1}/{len(devices)})" if device in devices else ""
        rows.append(("Device", f"{device}{position}"))
        info = fleet.info(device)
        if info is None:
            rows.append(("Status", "not listed by the agent: not heard from yet, or forgotten"))
        elif fleet.link == LINK_UNREACHABLE:
            # The agent's last word is not the arm's state now: shown as what it is, not as live figures.
            rows.append(("Status", f"unknown while the agent is out of reach (it said {info.status})"))
        else:
            age = None if info.age_s is None else info.age_s + max(0.0, now - info.received_s)
            # A device losing data is marked on the status line itself, where the eye already is.
            losing = f"  LOSING DATA ({info.recent_loss_ratio:.0%} recently)" if info.losing else ""
            rows.append(("Status", f"{info.status}{losing}"))
            rows.append(("Age", _fmt(age, "s", digits=2)))
            rows.append(("Rate", _fmt(info.rate_hz, "Hz")))
            rows.append(("Lost", f"{info.lost} messages (estimated from edge timestamp gaps)"))
            rows.append(
                (
                    "Latency",
                    f"p50 {_fmt(info.latency_p50_s, 'ms', 1000.0, 0)} / "
                    f"p99 {_fmt(info.latency_p99_s, 'ms', 1000.0, 0)} (edge clock)",
                )
            )
    if len(devices) > 1:
        attention = fleet.attention()
        rows.append(("Devices", device_window(devices, device, attention=attention)))
        others = "unknown while the agent is out of reach" if fleet.link == LINK_UNREACHABLE else None
        rows.append(("Others", others or others_line(devices, device, attention)))
        rows.append(("Keys", "Page Up / Page Down: previous / next device"))
    rows.append(("View", f"{fps:.0f} fps, smoothing {config.smoothing}"))
    return "\n".join(r[0] for r in rows), "\n".join(r[1] for r in rows)


def device_window(
    devices: list[str],
    device: str | None,
    width: int = DEVICES_SHOWN,
    *,
    attention: Mapping[str, str] | None = None,
) -> str:
    """The Devices line: up to `width` ids around the shown one (in brackets), each with why it wants a
    look (`arm-004 (CRITICAL)`), and how many are left out on each side."""
    marks = attention or {}
    i = devices.index(device) if device in devices else 0
    start = max(0, min(i - width // 2, len(devices) - width))
    shown = devices[start : start + width]
    parts = [(f"[{d}]" if d == device else d) + (f" ({marks[d]})" if d in marks else "") for d in shown]
    after = len(devices) - start - len(shown)
    if start:
        parts.insert(0, f"({start} before)")
    if after:
        parts.append(f"({after} after)")
    return "  ".join(parts)


def others_line(
    devices: list[str], device: str | None, attention: Mapping[str, str], named: int = OTHERS_NAMED
) -> str:
    """The Others line: the arms other than the shown one that want a look, worst first, up to `named` by
    name; the rest counted. An alarm on an arm out of view must not wait for someone to page to it."""
    listed = set(devices)
    others = sorted(
        ((d, mark) for d, mark in attention.items() if d != device and d in listed),
        key=lambda item: (-_urgency(item[1]), item[0]),
    )
    count = len(devices) - (device in listed)
    if not others:
        return "the other arm: ONLINE, no alarm" if count == 1 else f"all {count} others: ONLINE, no alarm"
    names = ", ".join(f"{d} {mark}" for d, mark in others[:named])
    more = f" (+{len(others) - named} more)" if len(others) > named else ""
    verb = "wants" if len(others) == 1 else "want"
    return f"{len(others)} of {count} {verb} a look: {names}{more}"


def _urgency(mark: str) -> int:
    """Orders the Others line: an unacknowledged critical alarm first, an arm out of touch next."""
    return 3 if "CRITICAL" in mark else 2 if "OFFLINE" in mark else 1 if mark.isupper() else 0


def servo_rows(servos: Mapping[str, ServoState] | None) -> list[tuple[str, str]]:
    """One overlay row per joint: temperature, load (and the model's), current, and its worst alarm."""
    if not servos:
        return []
    rows = []
    for joint, s in servos.items():
        model = "" if s.model_load_percent is None else f" (model {s.model_load_percent:.0f} %)"
        alarm = f"  [{s.alarm_severity} {s.alarm_state}]" if s.alarm_severity else ""
        # What the servo itself reports wrong (its status register), beside what the twin judged.
        errors = f"  servo error: {', '.join(s.errors)}" if s.errors else ""
        rows.append(
            (
                joint,
                f"{_fmt(s.temperature_c, 'C', digits=0)}  load {_fmt(s.load_percent, '%', digits=0)}{model}  "
                f"{_fmt(s.current_a, 'A', digits=2)}{alarm}{errors}",
            )
        )
    return rows


# The body each joint moves (so101 model): the part that takes the joint's alarm colour.
JOINT_BODIES = {
    "shoulder_pan": "shoulder",
    "shoulder_lift": "upper_arm",
    "elbow_flex": "lower_arm",
    "wrist_flex": "wrist",
    "wrist_roll": "gripper",
    "gripper": "moving_jaw",
}
# RGBA per (severity, state): ACTIVE and LATCHED want a person, so full colour; ACKNOWLEDGED is paler.
ALARM_COLOURS: dict[tuple[str, str], tuple[float, float, float, float]] = {
    ("critical", "ACTIVE"): (0.9, 0.1, 0.1, 1.0),
    ("critical", "LATCHED"): (0.9, 0.1, 0.1, 1.0),
    ("critical", "ACKNOWLEDGED"): (0.9, 0.55, 0.55, 1.0),
    ("warning", "ACTIVE"): (1.0, 0.65, 0.0, 1.0),
    ("warning", "LATCHED"): (1.0, 0.65, 0.0, 1.0),
    ("warning", "ACKNOWLEDGED"): (1.0, 0.85, 0.55, 1.0),
}


class JointTint:
    """Colours each joint's moving part by its worst servo alarm, and restores the model's own look after.

    A geom with a material draws the material's colour, so a tinted geom drops its material for as long as it
    is tinted. Call `apply` under the viewer's lock.
    """

    def __init__(self, model: Any, body_ids: Mapping[str, int]) -> None:
        self._model = model
        self._geoms: dict[str, list[int]] = {}
        for joint, body in JOINT_BODIES.items():
            bid = body_ids.get(body)
            if bid is None:
                continue
            start, count = int(model.body_geomadr[bid]), int(model.body_geomnum[bid])
            self._geoms[joint] = list(range(start, start + count))
        self._original = {
            g: (int(model.geom_matid[g]), tuple(model.geom_rgba[g]))
            for ids in self._geoms.values()
            for g in ids
        }
        self.tinted: dict[str, tuple[float, float, float, float]] = {}

    def apply(self, servos: Mapping[str, ServoState] | None) -> None:
        wanted: dict[str, tuple[float, float, float, float]] = {}
        for joint, s in (servos or {}).items():
            colour = ALARM_COLOURS.get((s.alarm_severity or "", s.alarm_state or ""))
            if colour is not None and joint in self._geoms:
                wanted[joint] = colour
        if wanted == self.tinted:
            return
        model = self._model
        for joint, ids in self._geoms.items():
            colour = wanted.get(joint)
            for g in ids:
                if colour is None:
                    model.geom_matid[g], model.geom_rgba[g] = self._original[g]
                else:
                    model.geom_matid[g] = -1
                    model.geom_rgba[g] = colour
        self.tinted = wanted


class ViewerError(RuntimeError):
    """The viewer cannot start (no display, bad model); the message says what to do."""


class TwinViewer:
    """The display loop. `run()` blocks until the window closes or `stop()` is called."""

    def __init__(self, config: ViewerConfig, clock: Clock = time.monotonic) -> None:
        self.config = config
        self._clock = clock
        self._stop = threading.Event()
        self.fleet = FleetView(lambda: make_estimator(config.smoothing))
        self.picker = DevicePicker(config.device)
        # The feed asks the agent for the device the picker shows, so the agent builds one arm per frame.
        self.feed = AgentFeed(config, self.fleet, clock, wanted=lambda: self.picker.selected)
        self.frames = 0

    def stop(self) -> None:
        """Ask the loop to end (safe from a signal handler or another thread)."""
        self._stop.set()

    def run(self) -> int:
        import mujoco  # noqa: PLC0415 - heavy; `twin --help` must not load it
        import mujoco.viewer  # noqa: PLC0415

        from twin.robot.model import RobotModel  # noqa: PLC0415 - pulls in mujoco

        make_estimator(self.config.smoothing)  # validate before opening a window
        check_display()
        robot = RobotModel.load(self.config.model_path)
        model = robot.model
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)

        try:
            handle = mujoco.viewer.launch_passive(
                model,
                data,
                key_callback=self.picker.on_key,
                show_left_ui=self.config.show_ui,
                show_right_ui=self.config.show_ui,
            )
        except Exception as exc:  # GLFW reports a missing display as a generic FatalError
            raise ViewerError(
                f"cannot open the viewer window ({exc}). `twin view` needs a desktop session: run it in the "
                "DCV console session or set DISPLAY (e.g. DISPLAY=:0); for images without a display use "
                "`twin demo` or `twin render`."
            ) from exc
        self.feed.start()
        try:
            with handle.lock():
                self._frame_camera(mujoco, robot, handle)
            self._loop(mujoco, robot, data, handle)
        finally:
            self.feed.stop()
            handle.close()
            _join_viewer_thread()
        log.info("viewer closed after %d frames", self.frames)
        return 0

    def _frame_camera(self, mujoco: Any, robot: Any, handle: Any) -> None:
        from twin.output.render import framing_camera, reach_poses  # noqa: PLC0415 - pulls in mujoco

        model = robot.model
        cam = handle.cam
        if self.config.camera:
            cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, self.config.camera)
            if cam_id < 0:
                names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
                raise ViewerError(
                    f"--camera {self.config.camera!r} is not in the model; "
                    f"cameras: {', '.join(names) or 'none'}"
                )
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = cam_id
            return
        # Free camera fitted to the arm's usual reach (stretched out over the pan range, upright, folded), not
        # the scene's default that shows the whole floor, so any ordinary pose stays in view without the arm
        # looking small; the mouse can still orbit and zoom. Desktop windows are wide: fit for 16:9.
        framed = framing_camera(robot, reach_poses(robot), aspect=16 / 9)
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = framed.lookat
        cam.distance = framed.distance
        cam.azimuth = framed.azimuth
        cam.elevation = framed.elevation

    def _loop(self, mujoco: Any, robot: Any, data: Any, handle: Any) -> None:
        model, addr, ranges = robot.model, robot.qpos_addr, robot.joint_ranges
        tint = JointTint(model, robot.body_ids)
        period = 1.0 / self.config.fps
        next_frame = self._clock()
        fps = 0.0
        fps_window_start, fps_frames = next_frame, 0
        while handle.is_running() and not self._stop.is_set():
            now = self._clock()
            devices = self.fleet.devices()
            device = self.picker.current(devices)
            pose = self.fleet.pose(device, now) if device is not None else None
            info = self.fleet.info(device) if device is not None else None
            with handle.lock():
                tint.apply(info.servos if info is not None else None)
                if pose is not None:
                    for name, value in pose.items():
                        if name in addr:
                            lo, hi = ranges[name]
                            data.qpos[addr[name]] = min(max(value, lo), hi)
                    # qvel stays zero, so forward dynamics does no physics work worth mentioning, and it
                    # keeps every derived quantity the renderer may read (cameras, lights, COM) consistent.
                    mujoco.mj_forward(model, data)
            labels, values = overlay_lines(
                self.config, self.fleet, device=device, devices=devices, now=now, fps=fps
            )
            font = mujoco.mjtFontScale.mjFONTSCALE_150
            texts = [(font, mujoco.mjtGridPos.mjGRID_TOPLEFT, labels, values)]
            servos = servo_rows(info.servos if info is not None else None)
            if servos:
                # Bottom right: clear of the status block and of the arm (framed left of centre).
                texts.append(
                    (
                        font,
                        mujoco.mjtGridPos.mjGRID_BOTTOMRIGHT,
                        "\n".join(r[0] for r in servos),
                        "\n".join(r[1] for r in servos),
                    )
                )
            handle.set_texts(texts if len(texts) > 1 else texts[0])
            handle.sync()
            self.frames += 1
            fps_frames += 1
            if now - fps_window_start >= 1.0:
                fps = fps_frames / (now - fps_window_start)
                fps_window_start, fps_frames = now, 0
            next_frame += period
            delay = next_frame - self._clock()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_frame = self._clock()  # fell behind (slow GPU / busy host): do not try to catch up


def check_display(environ: Mapping[str, str] | None = None) -> None:
    """Fail early, with the fix, when there is no display to open a window on.

    mujoco.viewer initialises GLFW on its own thread; when that fails it prints a bare "could not initialize
    GLFW" and the process dies, so the obvious cases are checked first.
    """
    env = os.environ if environ is None else environ
    if sys.platform != "linux" or env.get("WAYLAND_DISPLAY"):
        return
    display = env.get("DISPLAY", "")
    hint = (
        "`twin view` needs a desktop session: run it in the DCV console session or set DISPLAY (e.g. "
        "DISPLAY=:0); for images without a display use `twin demo` or `twin render`."
    )
    if not display:
        raise ViewerError(f"no display: DISPLAY is not set. {hint}")
    host, _, number = display.rpartition(":")
    number = number.split(".")[0]
    if host in ("", "unix") and number.isdigit() and not Path(f"/tmp/.X11-unix/X{number}").exists():
        raise ViewerError(f"no X server on DISPLAY={display} (no /tmp/.X11-unix/X{number}). {hint}")


def _join_viewer_thread(timeout: float = 5.0) -> None:
    """Wait for mujoco.viewer's render thread to tear down its window and GL context.

    The passive viewer runs in a daemon thread; if the interpreter exits while that thread still destroys the
    window, GLX fails (BadDrawable) and the process can crash on the way out.
    """
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and "_launch_internal" in thread.name:
            thread.join(timeout)
