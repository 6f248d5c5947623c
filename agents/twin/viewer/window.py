"""`twin view`: a MuJoCo passive viewer that follows the agent's live state.

Three parts, each with one job:
- `AgentFeed` (background thread) reads the agent's SSE `/stream`, falling back to polling `/state` when the
  stream is unavailable, and retries forever while the agent is unreachable; it never touches MuJoCo.
- `FleetView` (thread-safe) keeps, per device, the latest health figures and a smoothing estimator
  (`twin.core.smoothing`) fed with (edge timestamp, angles, local receive time).
- `TwinViewer` owns the display loop, the MuJoCo way: at ~60 Hz it asks the estimator for the pose at the
  current instant, writes qpos under `handle.lock()`, runs forward kinematics, updates the overlay text and
  calls `handle.sync()`. It ends when the window closes or `stop()` is called (SIGTERM in `twin view`).

docs/viewer.md describes the overlay, the keys and the smoothing.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import logging
import math
import os
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.core.smoothing import PoseEstimator, make_estimator

log = logging.getLogger(__name__)

Clock = Callable[[], float]

# GLFW key codes (stable across GLFW 3.x). The simulate UI already binds letters (visual flags), digits (geom
# groups: group 2 is the arm itself), arrows (stepping) and [ ] (cameras); Page Up/Down only select a parent
# body when a body is picked, so they are free for the device picker.
KEY_PAGE_UP = 266
KEY_PAGE_DOWN = 267

LINK_CONNECTING = "connecting"
LINK_STREAM = "stream"
LINK_POLLING = "polling"
LINK_UNREACHABLE = "unreachable"


@dataclass(frozen=True)
class ViewerConfig:
    """Settings of `twin view` (one object, built by the command from its flags)."""

    agent_url: str = "http://127.0.0.1:8080"
    device: str | None = None
    model_path: str | Path | None = None
    fps: float = 60.0
    smoothing: str = "predict"
    show_ui: bool = False
    camera: str | None = None
    # A stream that stays silent this long is dead (the agent streams at tens of Hz).
    read_timeout_s: float = 3.0
    retry_s: float = 0.5
    max_retry_s: float = 5.0
    poll_hz: float = 20.0
    # While polling because the stream failed, the stream is retried this often.
    stream_retry_s: float = 15.0

    def __post_init__(self) -> None:
        if not self.agent_url.startswith(("http://", "https://")):
            raise ValueError(f"--agent {self.agent_url!r} must be an http(s) URL, e.g. http://127.0.0.1:8080")
        if not 1.0 <= self.fps <= 240.0:
            raise ValueError(f"--fps {self.fps} must be between 1 and 240")


# ---------------------------------------------------------------------------------------------- state store


@dataclass
class DeviceInfo:
    """What the overlay shows for one device (figures as the agent published them)."""

    status: str = "UNKNOWN"
    age_s: float | None = None
    rate_hz: float | None = None
    latency_p50_s: float | None = None
    latency_p99_s: float | None = None
    internal_p99_s: float | None = None
    last_timestamp_ms: int | None = None
    received_s: float = 0.0  # local monotonic time the snapshot arrived


def _num(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


class FleetView:
    """Latest figures and a pose estimator per device; shared by the feed thread and the display loop."""

    def __init__(
        self, estimator_factory: Callable[[], PoseEstimator] = lambda: make_estimator("predict")
    ) -> None:
        self._lock = threading.Lock()
        self._factory = estimator_factory
        self._info: dict[str, DeviceInfo] = {}
        self._estimators: dict[str, PoseEstimator] = {}
        self.link = LINK_CONNECTING
        self.link_error: str | None = None
        self.link_since: float = time.monotonic()
        self.snapshots = 0
        self.bad_snapshots = 0

    def set_link(self, link: str, error: str | None = None, now: float | None = None) -> None:
        with self._lock:
            if link != self.link:
                self.link_since = time.monotonic() if now is None else now
                log.info("agent link: %s%s", link, f" ({error})" if error else "")
            self.link = link
            self.link_error = error

    def update(self, state: Any, received_s: float) -> int:
        """Take one agent state document (GET /state shape); returns the number of devices in it."""
        devices = state.get("devices") if isinstance(state, dict) else None
        if not isinstance(devices, dict):
            with self._lock:
                self.bad_snapshots += 1
            log.warning("agent state has no 'devices' object; is --agent pointing at a twin agent?")
            return 0
        with self._lock:
            self.snapshots += 1
            for device_id, d in devices.items():
                if not isinstance(d, dict):
                    continue
                info = self._info.setdefault(str(device_id), DeviceInfo())
                edge = d.get("edge_clock_latency_s") or {}
                internal = d.get("internal_latency_s") or {}
                info.status = str(d.get("status", "UNKNOWN"))
                info.age_s = _num(d.get("age_s"))
                info.rate_hz = _num(d.get("rate_hz"))
                info.latency_p50_s = _num(edge.get("p50")) if isinstance(edge, dict) else None
                info.latency_p99_s = _num(edge.get("p99")) if isinstance(edge, dict) else None
                info.internal_p99_s = _num(internal.get("p99")) if isinstance(internal, dict) else None
                info.received_s = received_s
                # timestamp_ms belongs to the same twin snapshot as joints_rad; last_timestamp_ms (health) is
                # the fallback for agents that publish only that.
                stamp = d.get("timestamp_ms", d.get("last_timestamp_ms"))
                joints = d.get("joints_rad")
                if isinstance(stamp, int) and not isinstance(stamp, bool) and isinstance(joints, dict):
                    info.last_timestamp_ms = stamp
                    estimator = self._estimators.get(str(device_id))
                    if estimator is None:
                        estimator = self._estimators[str(device_id)] = self._factory()
                    # The stream repeats the same sample until the agent applies a newer one; the estimator
                    # drops duplicates by timestamp, so only genuine new samples move it.
                    estimator.add(stamp, joints, received_s)
            return len(devices)

    def devices(self) -> list[str]:
        with self._lock:
            return sorted(self._info)

    def info(self, device_id: str) -> DeviceInfo | None:
        with self._lock:
            info = self._info.get(device_id)
            return None if info is None else DeviceInfo(**vars(info))

    def pose(self, device_id: str, now_s: float) -> dict[str, float] | None:
        with self._lock:
            estimator = self._estimators.get(device_id)
            return None if estimator is None else estimator.pose_at(now_s)


# ---------------------------------------------------------------------------------------------- agent feed


def iter_sse_data(lines: Iterable[bytes]) -> Iterator[str]:
    """The `data` payload of each Server-Sent Event in a line stream (multi-line data joined by newlines)."""
    data: list[str] = []
    for raw in lines:
        line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
        if not line:
            if data:
                yield "\n".join(data)
                data = []
            continue
        if line.startswith(":"):
            continue  # comment / keep-alive
        field, _, value = line.partition(":")
        if field == "data":
            data.append(value.removeprefix(" "))


def describe_error(exc: BaseException) -> str:
    """A short human reason for a connection problem (the overlay has one line for it)."""
    reason = getattr(exc, "reason", None)
    if isinstance(exc, urllib.error.HTTPError):
        return f"HTTP {exc.code} {exc.reason}"
    if isinstance(reason, BaseException):
        exc = reason
    elif isinstance(reason, str):
        return reason
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, TimeoutError):
        return "timed out"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


class AgentFeed:
    """Background reader of the agent's live state into a FleetView; retries forever, never raises."""

    def __init__(self, config: ViewerConfig, fleet: FleetView, clock: Clock = time.monotonic) -> None:
        self.config = config
        self.fleet = fleet
        self._clock = clock
        self._base = config.agent_url.rstrip("/")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._response: http.client.HTTPResponse | None = None

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="twin-view-feed", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        response = self._response
        if response is not None:
            with contextlib.suppress(Exception):
                response.close()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def _run(self) -> None:
        backoff = self.config.retry_s
        while not self._stop.is_set():
            try:
                self._read_stream()
                backoff = self.config.retry_s
                continue  # the agent closed the stream (restart?): reconnect at once
            except (OSError, http.client.HTTPException, ValueError) as exc:
                stream_error = describe_error(exc)
            if self._stop.is_set():
                break
            try:
                self._poll(stream_error)
                backoff = self.config.retry_s
            except (OSError, http.client.HTTPException, ValueError) as exc:
                self.fleet.set_link(LINK_UNREACHABLE, describe_error(exc))
                self._stop.wait(backoff)
                backoff = min(backoff * 2.0, self.config.max_retry_s)
        log.debug("agent feed stopped")

    def _open(self, path: str) -> http.client.HTTPResponse:
        request = urllib.request.Request(self._base + path, headers={"Accept": "text/event-stream"})
        return urllib.request.urlopen(request, timeout=self.config.read_timeout_s)

    def _read_stream(self) -> None:
        response = self._open("/stream")
        self._response = response
        try:
            content_type = response.headers.get("Content-Type", "")
            if "text/event-stream" not in content_type:
                raise ValueError(f"/stream answered {content_type or 'no content type'}, not an SSE stream")
            for data in iter_sse_data(response):
                if self._stop.is_set():
                    return
                state = json.loads(data)
                self.fleet.update(state, self._clock())
                if self.fleet.link != LINK_STREAM:
                    self.fleet.set_link(LINK_STREAM)
        finally:
            self._response = None
            response.close()

    def _poll(self, stream_error: str) -> None:
        """Poll /state until it is time to try the stream again; raises when the agent is unreachable."""
        deadline = self._clock() + self.config.stream_retry_s
        interval = 1.0 / self.config.poll_hz
        while not self._stop.is_set() and self._clock() < deadline:
            with self._open("/state") as response:
                state = json.loads(response.read())
            self.fleet.update(state, self._clock())
            if self.fleet.link != LINK_POLLING:
                self.fleet.set_link(LINK_POLLING, f"stream: {stream_error}")
            self._stop.wait(interval)


# ---------------------------------------------------------------------------------------------- overlay


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
            rows.append(("Status", "not reported by the agent yet"))
        else:
            age = None if info.age_s is None else info.age_s + max(0.0, now - info.received_s)
            rows.append(("Status", info.status))
            rows.append(("Age", _fmt(age, "s", digits=2)))
            rows.append(("Rate", _fmt(info.rate_hz, "Hz")))
            rows.append(
                (
                    "Latency",
                    f"p50 {_fmt(info.latency_p50_s, 'ms', 1000.0, 0)} / "
                    f"p99 {_fmt(info.latency_p99_s, 'ms', 1000.0, 0)} (edge clock)",
                )
            )
    if len(devices) > 1:
        rows.append(("Devices", "  ".join(f"[{d}]" if d == device else d for d in devices)))
        rows.append(("Keys", "Page Up / Page Down: previous / next device"))
    rows.append(("View", f"{fps:.0f} fps, smoothing {config.smoothing}"))
    return "\n".join(r[0] for r in rows), "\n".join(r[1] for r in rows)


class DevicePicker:
    """Which device the viewer follows: the configured one, else the first; Page Up/Down cycle."""

    def __init__(self, preferred: str | None = None) -> None:
        self._lock = threading.Lock()
        self._selected = preferred
        self._step = 0

    def on_key(self, key: int) -> None:
        # Called on the viewer's render thread: record the request only, the display loop applies it.
        with self._lock:
            if key == KEY_PAGE_DOWN:
                self._step += 1
            elif key == KEY_PAGE_UP:
                self._step -= 1

    def current(self, devices: list[str]) -> str | None:
        with self._lock:
            if devices and (self._selected is None or (self._step and self._selected not in devices)):
                self._selected = devices[0]
            if self._step and devices:
                i = devices.index(self._selected) if self._selected in devices else 0
                self._selected = devices[(i + self._step) % len(devices)]
            self._step = 0
            return self._selected


# ---------------------------------------------------------------------------------------------- viewer


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
        self.feed = AgentFeed(config, self.fleet, clock)
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
                "`twin demo` or twin.output.render."
            ) from exc
        self.feed.start()
        try:
            with handle.lock():
                self._frame_camera(mujoco, model, handle)
            self._loop(mujoco, robot, data, handle)
        finally:
            self.feed.stop()
            handle.close()
            _join_viewer_thread()
        log.info("viewer closed after %d frames", self.frames)
        return 0

    def _frame_camera(self, mujoco: Any, model: Any, handle: Any) -> None:
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
        # Free camera framed on the arm's workspace (about 0.45 m reach), not the scene's default that shows
        # the whole floor; the mouse can still orbit and zoom.
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = (0.12, 0.0, 0.18)
        # Far enough that the arm stretched straight up (about 0.5 m) stays in a small window.
        cam.distance = 1.1
        cam.azimuth = 140.0
        cam.elevation = -22.0

    def _loop(self, mujoco: Any, robot: Any, data: Any, handle: Any) -> None:
        model, addr, ranges = robot.model, robot.qpos_addr, robot.joint_ranges
        period = 1.0 / self.config.fps
        next_frame = self._clock()
        fps = 0.0
        fps_window_start, fps_frames = next_frame, 0
        while handle.is_running() and not self._stop.is_set():
            now = self._clock()
            devices = self.fleet.devices()
            device = self.picker.current(devices)
            pose = self.fleet.pose(device, now) if device is not None else None
            with handle.lock():
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
            handle.set_texts(
                (mujoco.mjtFontScale.mjFONTSCALE_150, mujoco.mjtGridPos.mjGRID_TOPLEFT, labels, values)
            )
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
        "DISPLAY=:0); for images without a display use `twin demo` or twin.output.render."
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
