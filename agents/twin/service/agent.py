"""The agent service: MQTT telemetry in, one MuJoCo twin per device, health, HTTP out, optional USD recording.

Data path and threads:

    CRT event loop --on_message--> LatestValueMailbox (one slot per device, never blocks)
        --take_all--> worker thread: decode -> DeviceTwin.apply -> health -> recorder -> snapshots
    HTTP threads read the published snapshots and health under one short lock.

The CRT callback only stamps the receive times and drops the message in the mailbox: decoding there would
stall the client's event loop. The worker owns the decoder (not thread-safe: auto-units state), every
DeviceTwin and the recorder; other threads only see immutable TwinSnapshots and health dicts. Any exception
while handling one message is caught, logged (rate-limited) and counted: a bad message never stops the
service.

Ordering uses the edge timestamp (DeviceTwin.apply ignores anything not newer), liveness uses the agent's
monotonic receive time (twin.core.health). The two meet in one place: when a device keeps sending valid
messages that are all older than the last applied one for a while, its edge clock has jumped backwards (an
edge without NTP rebooting, say); waiting for the clock to catch up would freeze the twin for as long as the
jump, so the device's twin is rebuilt on the new timeline and the reset is counted and logged.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.core.health import DeviceStatus, FleetHealth
from twin.core.latency import LatencyHistogram
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, TelemetryRejected, Units
from twin.core.twin import DeviceTwin, TwinMode, TwinSnapshot
from twin.output.recorder import SessionRecorder

# This module is the heavy end of the agent (MuJoCo, awscrt, USD); `twin run` imports it only when it runs.
from twin.robot.calibration import load_calibration
from twin.robot.model import ModelError, RobotModel
from twin.service.config import AgentConfig, ConfigError
from twin.service.http_api import AgentHttpServer
from twin.service.logs import RateLimitedLog
from twin.transport.mailbox import LatestValueMailbox
from twin.transport.subscriber import (
    BrokerConfig,
    BrokerConfigError,
    TelemetrySubscriber,
    device_from_topic,
    topic_filters,
)

log = logging.getLogger(__name__)

# A device whose valid messages have all been older than its last applied one for this long (and this many
# messages) has had its edge clock jump backwards: rebuild its twin on the new timeline. Reordering and
# duplicates interleave with newer messages, which end a streak long before this.
CLOCK_RESET_AFTER_S = 2.0
CLOCK_RESET_MIN_MESSAGES = 5
# physics mode: at most this much simulated time per worker wake-up, so a stalled worker catches up smoothly
# instead of running seconds of simulation in one go.
MAX_PHYSICS_STEP_S = 0.1
# How often the worker wakes with nothing to do (kinematic mode): bounds the stop latency.
IDLE_WAKE_S = 0.2
TOO_MANY_DEVICES = "too_many_devices"
UNTRACKED_KEY = "\x00untracked"  # mailbox key for topics that carry no device id (cannot collide with one)


@dataclass(frozen=True, slots=True)
class _Inbound:
    topic: str
    payload: bytes
    recv_mono: float
    recv_wall: float


@dataclass
class _DeviceState:
    """Worker-private per-device bookkeeping next to its DeviceTwin."""

    twin: DeviceTwin
    stale_streak: int = 0
    stale_since: float = 0.0
    gripper_percent: float | None = None


class AgentService:
    """Wires config -> subscriber -> mailbox -> worker -> twins/health/recorder -> HTTP. See the module doc.

    Lifecycle: `start()` (returns once everything is running; the broker connection itself is asynchronous),
    `stop()` (idempotent; drains, flushes the recording, stops HTTP). `state()` and `healthz()` may be called
    from any thread.
    """

    def __init__(self, config: AgentConfig, *, clock: Any = time.monotonic) -> None:
        # Everything that can be wrong with the configuration is found here, before any thread or socket.
        self.config = config
        self._clock = clock
        t = config.telemetry
        try:
            self.broker_config = BrokerConfig(
                url=config.broker.url,
                region=config.broker.region,
                endpoint=config.broker.endpoint,
                client_id_prefix=config.broker.client_id_prefix,
                ca_file=config.broker.ca_file,
            )
        except BrokerConfigError as exc:
            raise ConfigError(f"[broker]: {exc}") from exc
        try:
            calibration = load_calibration(t.calibration) if t.calibration else None
        except ValueError as exc:
            raise ConfigError(f"telemetry.calibration = {t.calibration!r}: {exc}") from exc
        try:
            self._decoder_config = DecoderConfig(
                units=Units(t.units), calibration=calibration, max_payload_bytes=t.max_payload_bytes
            )
        except ValueError as exc:
            raise ConfigError(f"[telemetry]: {exc}") from exc
        self.mode = TwinMode(config.twin.mode)
        try:
            self.robot = RobotModel.load(config.twin.model or None)
            if self.mode is TwinMode.PHYSICS:
                self.robot.require_actuators()
        except ModelError as exc:
            raise ConfigError(f"twin.model = {config.twin.model!r}: {exc}") from exc
        self.topic_filters = topic_filters(t.topic_prefix, list(t.devices))
        self._decoder = TelemetryDecoder(self._decoder_config)

        configured = () if t.all_devices else t.devices
        self._fleet = FleetHealth(config.health, configured, clock=clock)
        self._devices: dict[str, _DeviceState] = {}
        self._snapshots: dict[str, TwinSnapshot] = {}
        self._units: dict[str, str] = {}
        self._lock = threading.Lock()
        self._reject_log = RateLimitedLog(log, interval_s=10.0, clock=clock)
        self._error_log = RateLimitedLog(log, interval_s=10.0, clock=clock)

        self._mailbox: LatestValueMailbox[_Inbound] = LatestValueMailbox(max_keys=max(64, 4 * t.max_devices))
        self._subscriber: Any = None
        self._http: Any = None
        self._recorder: SessionRecorder | None = None
        self._worker: threading.Thread | None = None
        self._started_mono: float | None = None
        self._started_wall: float | None = None
        self._running = threading.Event()
        self._stopped = False
        self._stop_lock = threading.Lock()
        self.batches = 0
        # Fleet-wide distributions since start (every applied message of every device), for `twin bench`
        # and capacity questions; the per-device windows in health answer "how is this arm doing now".
        self._internal_hist = LatencyHistogram()
        self._end_to_end_hist = LatencyHistogram()
        self.processed = 0
        self.errors = 0

    # -------------------------------------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Start the worker, the recorder, the HTTP server and the subscriber (in that order, so nothing a
        message triggers can meet a half-built service). Raises OSError if the HTTP address is taken."""
        if self._running.is_set():
            return
        self._started_mono = self._clock()
        self._started_wall = time.time()
        if self.config.twin.record_dir:
            self._recorder = self._open_recorder(Path(self.config.twin.record_dir))
        try:
            self._http = AgentHttpServer(
                self,
                self.config.http.host,
                self.config.http.port,
                stream_rate_hz=self.config.http.stream_rate_hz,
            )
        except OSError:
            if self._recorder is not None:
                self._recorder.close()
            raise
        self._running.set()
        self._worker = threading.Thread(target=self._work, name="twin-worker", daemon=True)
        self._worker.start()
        self._http.start()
        self._subscriber = TelemetrySubscriber(self.broker_config, self.topic_filters, self._on_message)
        self._subscriber.start()
        log.info(
            "agent started",
            extra={
                "broker": self.config.broker.url,
                "topics": self.topic_filters,
                "http": self._http.url,
                "mode": str(self.mode),
                "units": self.config.telemetry.units,
                "recording": str(self._recorder.path) if self._recorder else None,
            },
        )

    def _open_recorder(self, directory: Path) -> SessionRecorder:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        path = directory / f"session-{stamp}-{os.getpid()}.{self.config.twin.record_format}"
        return SessionRecorder(path, flush_interval_s=self.config.twin.record_flush_s)

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the subscriber, drain the mailbox, close the recording (final USD save), stop HTTP.

        Idempotent."""
        with self._stop_lock:
            if self._stopped:
                return
            self._stopped = True
        log.info("agent stopping")
        if self._subscriber is not None:
            try:
                self._subscriber.stop(timeout)
            except Exception:
                log.exception("subscriber stop failed")
        self._mailbox.close()
        if self._worker is not None:
            # The worker takes what is left, then sees the closed, empty mailbox and returns.
            self._worker.join(timeout)
            if self._worker.is_alive():
                log.error("twin worker did not finish within %.1f s", timeout)
        self._running.clear()
        if self._recorder is not None:
            try:
                self._recorder.close()
            except Exception:
                log.exception("closing the session recording failed")
        if self._http is not None:
            self._http.stop()
        log.info("agent stopped", extra={"processed": self.processed, "errors": self.errors})

    def __enter__(self) -> AgentService:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._running.is_set() and self._worker is not None and self._worker.is_alive()

    @property
    def http_url(self) -> str:
        if self._http is None:
            raise RuntimeError("the HTTP server starts with start()")
        return self._http.url

    @property
    def recording_path(self) -> Path | None:
        return self._recorder.path if self._recorder is not None else None

    def wait_subscribed(self, timeout: float) -> bool:
        return self._subscriber is not None and self._subscriber.wait_subscribed(timeout)

    # ---------------------------------------------------------------------------------- CRT callback thread

    def _on_message(self, topic: str, payload: bytes, recv_mono: float) -> None:
        device = device_from_topic(topic, self.config.telemetry.topic_prefix)
        self._mailbox.put(device or UNTRACKED_KEY, _Inbound(topic, payload, recv_mono, time.time()))

    # ------------------------------------------------------------------------------------------ worker

    def _work(self) -> None:
        physics = self.mode is TwinMode.PHYSICS
        wake = 1.0 / self.config.twin.physics_rate_hz if physics else IDLE_WAKE_S
        last_step = time.monotonic()
        while True:
            items = self._mailbox.take_all(wake)
            if not items and self._mailbox.closed:
                return
            dirty: set[str] = set()
            for key, item in items:
                device = self._process(key, item)
                if device is not None:
                    dirty.add(device)
            if physics:
                now = time.monotonic()
                elapsed = min(now - last_step, MAX_PHYSICS_STEP_S)
                last_step = now
                for device, ds in self._devices.items():
                    try:
                        ds.twin.step(elapsed)
                    except Exception:
                        self._count_error(device, "physics step failed")
                    dirty.add(device)
            self._publish(dirty, [k for k, _ in items])

    def _publish(self, dirty: set[str], keys: list[str]) -> None:
        snapshots = {}
        for device in dirty:
            ds = self._devices.get(device)
            if ds is not None:
                snapshots[device] = ds.twin.snapshot()
        overwritten = self._mailbox.overwritten
        with self._lock:
            self._snapshots.update(snapshots)
            for key in keys:
                health = self._fleet.get(key)
                if health is not None:
                    health.overwritten = overwritten.get(key, 0)
            if keys:
                self.batches += 1

    def _process(self, key: str, item: _Inbound) -> str | None:
        """Handle one message; returns the device whose twin changed, if any. Never raises."""
        topic_device = None if key == UNTRACKED_KEY else key
        try:
            self.processed += 1
            try:
                telemetry = self._decoder.decode(item.payload, topic_device=topic_device)
            except TelemetryRejected as exc:
                with self._lock:
                    health = self._fleet.get(topic_device) if topic_device else None
                    if health is not None:
                        health.record_received()
                    self._fleet.record_rejected(topic_device, exc.reason)
                self._reject_log.log(
                    (topic_device, str(exc.reason)),
                    logging.WARNING,
                    "telemetry rejected",
                    device=topic_device,
                    topic=item.topic,
                    reason=str(exc.reason),
                    detail=str(exc),
                )
                return None

            device = telemetry.device_id
            ds = self._devices.get(device)
            if ds is None:
                if len(self._devices) >= self.config.telemetry.max_devices:
                    with self._lock:
                        self._fleet.record_rejected(None, TOO_MANY_DEVICES)
                    self._reject_log.log(
                        TOO_MANY_DEVICES,
                        logging.WARNING,
                        "device ignored: telemetry.max_devices twins already exist; raise it if the fleet is "
                        "really this large",
                        device=device,
                        max_devices=self.config.telemetry.max_devices,
                    )
                    return None
                ds = self._new_device(device)
            ds.gripper_percent = telemetry.gripper_percent
            units = str(self._decoder.units_for(device))

            applied = ds.twin.apply(telemetry.angles_rad, telemetry.timestamp_ms)
            updated = time.monotonic()
            reset = False
            if applied:
                ds.stale_streak = 0
            else:
                if ds.stale_streak == 0:
                    ds.stale_since = item.recv_mono
                ds.stale_streak += 1
                if (
                    ds.stale_streak >= CLOCK_RESET_MIN_MESSAGES
                    and item.recv_mono - ds.stale_since >= CLOCK_RESET_AFTER_S
                ):
                    reset = True
                    previous = ds.twin.last_timestamp_ms
                    ds = self._new_device(device, replace=True)
                    applied = ds.twin.apply(telemetry.angles_rad, telemetry.timestamp_ms)
                    updated = time.monotonic()
                    log.warning(
                        "edge clock of %s jumped backwards; twin rebuilt on the new timeline",
                        device,
                        extra={"device": device, "last_ms": previous, "now_ms": telemetry.timestamp_ms},
                    )

            with self._lock:
                health = self._fleet.device(device)
                health.record_received()
                health.record_decoded(item.recv_mono, item.recv_wall, telemetry.timestamp_ms)
                if reset:
                    health.clock_resets += 1
                if applied:
                    health.record_applied(item.recv_mono, updated, telemetry.timestamp_ms)
                    self._internal_hist.add(updated - item.recv_mono)
                    # Twin-updated wall time minus the edge stamp: only meaningful when the clocks agree
                    # (same host in `twin bench`); in the field it includes the edge clock's offset.
                    self._end_to_end_hist.add(
                        item.recv_wall + (updated - item.recv_mono) - telemetry.timestamp_ms / 1000.0
                    )
                else:
                    health.record_ignored_stale()
                self._units[device] = units

            if applied and self._recorder is not None:
                self._recorder.record(device, item.recv_mono, ds.twin.body_poses())
            return device if applied else None
        except Exception:
            self._count_error(topic_device, "processing a message failed", topic=item.topic)
            return None

    def _new_device(self, device: str, *, replace: bool = False) -> _DeviceState:
        ds = _DeviceState(twin=DeviceTwin(self.robot, device, self.mode))
        self._devices[device] = ds
        if not replace:
            log.info("new device", extra={"device": device, "mode": str(self.mode)})
        return ds

    def _count_error(self, device: str | None, msg: str, **fields: Any) -> None:
        self.errors += 1
        with self._lock:
            health = self._fleet.get(device) if device else None
            if health is not None:
                health.record_error()
        # One traceback per interval; the rest are summarised as `suppressed` on the next line.
        self._error_log.log((device, msg), logging.ERROR, msg, exc_info=True, device=device, **fields)

    # ------------------------------------------------------------------------------------------ readers

    def state(self) -> dict[str, Any]:
        """The agent's state for /state, /metrics and /stream (docs/agent.md describes every field)."""
        sub = self._subscriber
        stats = sub.stats if sub is not None else None
        with self._lock:
            now = self._clock()
            health = self._fleet.snapshot(now)
            snapshots = dict(self._snapshots)
            units = dict(self._units)
            untracked = dict(self._fleet.untracked_rejected)
            batches = self.batches
            latency = {
                "internal_s": self._internal_hist.summary(),
                "end_to_end_s": self._end_to_end_hist.summary(),
            }
        devices: dict[str, Any] = {}
        for device, h in health.items():
            snap = snapshots.get(device)
            ds = self._devices.get(device)
            entry: dict[str, Any] = {"device_id": device, **h}
            entry["units"] = units.get(device, self.config.telemetry.units)
            entry["mode"] = str(self.mode)
            entry["timestamp_ms"] = snap.timestamp_ms if snap else None
            entry["joints_rad"] = dict(snap.joint_angles) if snap else None
            entry["targets_rad"] = dict(snap.targets) if snap else None
            entry["torques_nm"] = dict(snap.joint_torques) if snap else None
            entry["tcp_position_m"] = list(snap.tcp_position) if snap else None
            entry["gripper_percent"] = ds.gripper_percent if ds else None
            entry["counters"]["clamped"] = snap.clamped if snap else 0
            devices[device] = entry
        recorder = self._recorder
        return {
            "agent": {
                "running": self.running,
                "pid": os.getpid(),
                "started_at": self._started_wall,
                "uptime_s": (now - self._started_mono) if self._started_mono is not None else 0.0,
                "time": time.time(),
                "mode": str(self.mode),
                "units": self.config.telemetry.units,
                "devices": list(self.config.telemetry.devices),
                "topic_filters": list(self.topic_filters),
                "broker": {
                    "url": self.config.broker.url,
                    "client_id": sub.client_id if sub is not None else None,
                    "connected": bool(sub is not None and sub.connected),
                    "connection_successes": stats.connection_successes if stats else 0,
                    "connection_failures": stats.connection_failures if stats else 0,
                    "disconnections": stats.disconnects if stats else 0,
                    "subscribes": stats.subscribes_acked if stats else 0,
                    "messages": stats.messages_received if stats else 0,
                    "last_error": stats.last_error if stats else "",
                },
                "mailbox": {
                    "overwritten_total": self._mailbox.overwritten_total,
                    "refused_keys": self._mailbox.refused_keys,
                    "pending": len(self._mailbox),
                },
                "latency": latency,
                "worker": {
                    "alive": self._worker is not None and self._worker.is_alive(),
                    "batches": batches,
                    "processed": self.processed,
                    "errors": self.errors,
                },
                "recording": None
                if recorder is None
                else {
                    "path": str(recorder.path),
                    "samples_written": recorder.samples_written,
                    "flushes": recorder.flushes,
                    "flush_errors": recorder.flush_errors,
                },
            },
            "devices": devices,
            "untracked_rejected": untracked,
        }

    def healthz(self) -> tuple[bool, dict[str, Any]]:
        """Healthy = the service runs, the broker connection is up, and no configured device is OFFLINE.

        With devices = ["*"] no device is configured, so only the first two apply: a fleet agent stays healthy
        while individual arms come and go (their status is in /state and /metrics).
        """
        sub = self._subscriber
        connected = bool(sub is not None and sub.connected)
        running = self.running
        with self._lock:
            statuses = self._fleet.statuses()
            offline = self._fleet.offline_configured()
        reasons = []
        if not running:
            reasons.append("service not running")
        if not connected:
            reasons.append("broker connection down")
        reasons.extend(f"device {d} is OFFLINE" for d in offline)
        body = {
            "status": "ok" if not reasons else "unavailable",
            "running": running,
            "broker_connected": connected,
            "devices": {d: str(s) for d, s in statuses.items()},
            "reasons": reasons,
        }
        return not reasons, body

    def device_status(self, device: str) -> DeviceStatus | None:
        with self._lock:
            health = self._fleet.get(device)
            return health.status() if health is not None else None
