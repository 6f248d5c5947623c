"""Edge simulator: publishes exactly what the SO-101 edge component publishes, plus injectable faults.

The payloads and the motion (the edge's own mock mode) come from `twin.edge.payload`. Faults (drop,
duplicate, reorder, clock skew, malformed payloads) reproduce what a real fleet does to a consumer; servo
faults (heat, overload, contact: twin.edge.servo_faults) what a real arm does to its servos.
Publishing goes through the same awscrt client builder as the subscriber.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import random
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from awscrt import mqtt5

from twin.core.topics import DEFAULT_TOPIC_PREFIX, check_topic_prefix, telemetry_topic
from twin.edge.payload import (
    MALFORMED_KINDS,
    VARIANTS,
    device_ids,
    encode,
    make_malformed,
    make_payload,
    physical_readings,
)
from twin.edge.servo_faults import ModelLoads, ServoFault
from twin.edge.servo_physics import SERVO_MODES, PhysicalServoConfig

__all__ = ["EdgeSimConfig", "EdgeSimReport", "EdgeSimulator", "FaultConfig", "device_ids"]
from twin.transport.broker import BrokerConfig, connect_hint, crt_error_text, new_client_id
from twin.transport.client import build_mqtt5_client

log = logging.getLogger(__name__)

# IoT Core: at most 100 publishes/s per connection, excess discarded (docs/aws-facts.md, "IoT Core quotas").
IOT_PUBLISHES_PER_CONNECTION = 100
# A skip steps the physical servos' thermal models through at most this many readings in all (about 60 us
# each): every skipped tick of a few arms, a coarser grid for many (EdgeSimulator._skip).
MAX_SKIPPED_READINGS = 600


@dataclass
class FaultConfig:
    """Per-message probabilities (0..1) and a clock offset in milliseconds."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    malformed: float = 0.0
    clock_skew_ms: int = 0

    def __post_init__(self) -> None:
        for name in ("drop", "duplicate", "reorder", "malformed"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"fault probability --{name} {value} must be between 0 and 1")


@dataclass
class EdgeSimConfig:
    broker: BrokerConfig
    devices: list[str] = field(default_factory=lambda: ["arm-001"])
    variant: str = "ticks"
    rate_hz: float = 10.0
    seconds: float | None = None  # None: until the stop event
    topic_prefix: str = DEFAULT_TOPIC_PREFIX
    faults: FaultConfig = field(default_factory=FaultConfig)
    seed: int | None = None
    load_sign: bool = False
    servo_faults: tuple[ServoFault, ...] = ()
    model_loads: bool = False
    # "mock": the edge mock mode's uniform noise (what the real edge sends); "physical": readings from the
    # motion (twin.edge.servo_physics), with `physical`'s settings, or a device's own in `physical_by_device`.
    servos: str = "mock"
    physical: PhysicalServoConfig = field(default_factory=PhysicalServoConfig)
    physical_by_device: Mapping[str, PhysicalServoConfig] = field(default_factory=dict)
    connect_timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"variant {self.variant!r} is not one of {', '.join(VARIANTS)}")
        if not self.devices:
            raise ValueError("no devices: give --devices N or --device ID")
        check_topic_prefix(self.topic_prefix)
        for device in self.devices:
            telemetry_topic(self.topic_prefix, device)  # raises with the rule on '/', '+', '#', ...
        if not 0 < self.rate_hz <= 10_000:
            raise ValueError(f"rate {self.rate_hz} Hz must be in (0, 10000]")
        if self.seconds is not None and self.seconds <= 0:
            raise ValueError(f"seconds {self.seconds} must be positive (omit it to run until stopped)")
        if self.servos not in SERVO_MODES:
            raise ValueError(f"servos {self.servos!r} is not one of {', '.join(SERVO_MODES)}")
        if self.servos == "physical" and self.model_loads:
            raise ValueError(
                "--model-loads and --servos physical: give one; physical servos already report the model's "
                "loads (with the motion's)"
            )
        unknown = sorted(set(self.physical_by_device) - set(self.devices))
        if unknown:
            raise ValueError(f"physical servo settings for devices not simulated: {', '.join(unknown)}")


def clock_skews_ms(devices: list[str], skew_ms: int) -> dict[str, int]:
    """Spread the skew so devices also disagree with each other: the last device is off by the full amount."""
    n = len(devices)
    return {device: round(skew_ms * (i + 1) / n) for i, device in enumerate(devices)}


@dataclass
class EdgeSimReport:
    ticks: int = 0
    generated: int = 0  # messages built (one per device per tick)
    published: int = 0  # publish calls made, duplicates included
    publish_failures: int = 0
    dropped: int = 0
    duplicated: int = 0
    reordered: int = 0
    skipped_ticks: int = 0  # the machine fell more than a second behind schedule
    malformed: dict[str, int] = field(default_factory=dict)
    per_device: dict[str, int] = field(default_factory=dict)
    elapsed_s: float = 0.0

    @property
    def malformed_total(self) -> int:
        return sum(self.malformed.values())

    def as_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["malformed_total"] = self.malformed_total
        return data


def _physical_arms(config: EdgeSimConfig) -> dict[str, Any]:
    """A PhysicalArm per device; arms with the same payload share one model (MuJoCo loads here, once)."""
    from twin.edge.servo_physics import ArmDynamics, PhysicalArm, payload_model  # noqa: PLC0415

    dynamics: dict[float, ArmDynamics] = {}
    arms: dict[str, Any] = {}
    for device in config.devices:
        settings = config.physical_by_device.get(device, config.physical)
        if settings.payload_kg not in dynamics:
            dynamics[settings.payload_kg] = ArmDynamics(payload_model(settings.payload_kg))
        arms[device] = PhysicalArm(settings, dynamics[settings.payload_kg])
    return arms


def _not_connected(config: EdgeSimConfig, failure: str) -> str:
    """Why the simulator gives up: where it tried, for how long, and the last error with what to check."""
    why = (
        f": {failure}"
        if failure
        else " (no answer at all: is the broker running and the URL's host and port right?)"
    )
    return (
        f"edge-sim could not connect to {config.broker.where()} within {config.connect_timeout_s:.0f} s{why}"
    )


class _Connection:
    """One MQTT5 client plus the bookkeeping the simulator needs, filled in from CRT callbacks."""

    def __init__(self, config: BrokerConfig, report: EdgeSimReport, lock: threading.Lock) -> None:
        self.client_id = new_client_id(config.client_id_prefix)
        self._config = config
        # The last failed connect's error and what to check (connect_hint), for the give-up message: the
        # log's lines may have scrolled away by then.
        self.failure = ""
        self.connected = threading.Event()
        self.stopped = threading.Event()
        self._report = report
        self._lock = lock
        self.outstanding = 0
        self.client = build_mqtt5_client(
            config,
            self.client_id,
            on_connection_success=self._on_success,
            on_connection_failure=self._on_failure,
            on_disconnection=self._on_disconnection,
            on_stopped=lambda _data: self.stopped.set(),
        )

    def _on_success(self, _data: Any) -> None:
        log.info("edge-sim %s connected", self.client_id)
        self.connected.set()

    def _on_failure(self, data: Any) -> None:
        hint = connect_hint(self._config, data.exception)
        self.failure = f"{crt_error_text(data.exception)}{f'. {hint}' if hint else ''}"
        log.warning(
            "edge-sim %s could not connect to %s: %s; retrying",
            self.client_id,
            self._config.where(),
            self.failure,
        )

    def _on_disconnection(self, data: Any) -> None:
        self.connected.clear()
        log.info("edge-sim %s disconnected: %s", self.client_id, data.exception)

    def publish(self, topic: str, payload: bytes) -> None:
        with self._lock:
            self._report.published += 1
            self.outstanding += 1
        future = self.client.publish(
            mqtt5.PublishPacket(topic=topic, payload=payload, qos=mqtt5.QoS.AT_MOST_ONCE)
        )
        future.add_done_callback(self._on_publish_done)

    def _on_publish_done(self, future: Any) -> None:
        # QoS 0: completes once written to the socket, or fails while disconnected (offline queue policy).
        failed = future.exception() is not None
        with self._lock:
            self.outstanding -= 1
            if failed:
                self._report.publish_failures += 1


class EdgeSimulator:
    """Publishes telemetry for `config.devices` at `config.rate_hz` until `seconds` or the stop event."""

    def __init__(self, config: EdgeSimConfig) -> None:
        self.config = config
        self.rng = random.Random(config.seed)
        self.report = EdgeSimReport(
            malformed=dict.fromkeys(MALFORMED_KINDS, 0), per_device=dict.fromkeys(config.devices, 0)
        )
        self._lock = threading.Lock()
        self._skews = clock_skews_ms(config.devices, config.faults.clock_skew_ms)
        self._held: dict[str, tuple[bytes, int]] = {}
        self._topics = {device: telemetry_topic(config.topic_prefix, device) for device in config.devices}
        self._model_loads = ModelLoads() if config.model_loads else None
        self._arms = _physical_arms(config) if config.servos == "physical" else {}

    def _connections_needed(self) -> int:
        config = self.config
        if config.broker.kind != "iot":
            return 1
        if config.rate_hz > IOT_PUBLISHES_PER_CONNECTION:
            log.warning(
                "%.0f Hz per device exceeds IoT Core's %d publishes/s per connection; excess is discarded",
                config.rate_hz,
                IOT_PUBLISHES_PER_CONNECTION,
            )
        total = len(config.devices) * config.rate_hz * (1 + config.faults.duplicate)
        needed = min(len(config.devices), max(1, math.ceil(total / IOT_PUBLISHES_PER_CONNECTION)))
        if needed > 1:
            log.warning(
                "%d devices x %.1f Hz exceeds IoT Core's %d publishes/s per connection: spreading them over "
                "%d connections",
                len(config.devices),
                config.rate_hz,
                IOT_PUBLISHES_PER_CONNECTION,
                needed,
            )
        return needed

    def run(self, stop_event: threading.Event | None = None) -> EdgeSimReport:
        """Connect, publish on an absolute schedule, flush, disconnect; returns the counts."""
        stop_event = stop_event or threading.Event()
        config = self.config
        if config.servos == "mock" and not config.model_loads:
            # Said once, up front: a new user who sees a critical alarm on every arm takes it for a bug.
            log.info(
                "servos: the edge's mock mode, as a real edge in mock mode publishes: random velocity, load, "
                "temperature and current. Its currents (up to 1.95 A) raise each arm's critical gripper "
                "over_current alarm (1.3 A) within minutes, and it stays ACTIVE; --servos physical or "
                "--model-loads publish what servos holding the motion report"
            )
        connections = [
            _Connection(config.broker, self.report, self._lock) for _ in range(self._connections_needed())
        ]
        route = {device: connections[i % len(connections)] for i, device in enumerate(config.devices)}
        for connection in connections:
            connection.client.start()
        try:
            for connection in connections:
                if not connection.connected.wait(config.connect_timeout_s):
                    raise ConnectionError(_not_connected(config, connection.failure))
            self._loop(stop_event, route)
            self._flush(route)
            self._wait_outstanding(connections, timeout=10.0)
        finally:
            for connection in connections:
                connection.client.stop()
            for connection in connections:
                if not connection.stopped.wait(5.0):
                    log.warning("edge-sim %s did not report Stopped within 5 s", connection.client_id)
        self._log_report()
        return self.report

    def _loop(self, stop_event: threading.Event, route: dict[str, _Connection]) -> None:
        config = self.config
        period = 1.0 / config.rate_hz
        total_ticks = None if config.seconds is None else max(1, round(config.seconds * config.rate_hz))
        start = time.monotonic()
        # Wall clock and monotonic clock are read once: timestamps advance exactly with the schedule, like
        # an edge loop stamping each sample, instead of jittering with this process's scheduling.
        wall_start_ms = time.time() * 1000.0
        k = 0
        while not stop_event.is_set() and (total_ticks is None or k < total_ticks):
            target = start + k * period
            delay = target - time.monotonic()
            if delay > 0:
                if stop_event.wait(delay):
                    break
            elif delay < -1.0:
                # More than a second behind (suspended, overloaded): skip ahead rather than burst. Never
                # past the run's end, so published and skipped ticks add up to the run's ticks.
                behind = int(-delay / period)
                if total_ticks is not None:
                    behind = min(behind, total_ticks - k)
                self._skip(k, behind, period)
                k += behind
                continue
            t = k * period
            for device in config.devices:
                self._emit(device, t, int(wall_start_ms + t * 1000.0), route[device])
            k += 1
            self.report.ticks += 1
        self.report.elapsed_s = time.monotonic() - start

    def _skip(self, k: int, behind: int, period: float) -> None:
        """Ticks k .. k + behind - 1 go unpublished. The physical servos ran on meanwhile: their temperatures
        integrate over the skipped ticks as over published ones. Otherwise the next sample's current would
        stand for the whole gap (a gap of seconds at a thermal speed-up of 80 is minutes of heating at one
        instant's current: the demo's servo once read 70 C after 7 s skipped, where every tick taken keeps it
        at or below 69 C for the demo's longest run). At most MAX_SKIPPED_READINGS readings in all, spread
        evenly over the gap and ending on its last tick: every tick for the demo's arms, fewer for a large
        physical fleet, which must not fall further behind catching up."""
        self.report.skipped_ticks += behind
        arms = self._arms
        if not arms:
            return
        steps = max(1, min(behind, MAX_SKIPPED_READINGS // len(arms)))
        faults = self.config.servo_faults
        for n in range(1, steps + 1):
            t = (k - 1 + round(n * behind / steps)) * period
            for arm in arms.values():
                physical_readings(t, arm, faults)

    def _emit(self, device: str, t: float, now_ms: int, connection: _Connection) -> None:
        faults = self.config.faults
        rng = self.rng
        report = self.report
        report.generated += 1
        payload = make_payload(
            device,
            t,
            self.config.variant,
            rng,
            timestamp_ms=now_ms + self._skews[device],
            load_sign=self.config.load_sign,
            servo_faults=self.config.servo_faults,
            model_loads=self._model_loads,
            physical=self._arms.get(device),
        )
        if faults.drop and rng.random() < faults.drop:
            report.dropped += 1
            return
        if faults.malformed and rng.random() < faults.malformed:
            kind = rng.choice(MALFORMED_KINDS)
            report.malformed[kind] += 1
            data = make_malformed(kind, payload, rng)
        else:
            data = encode(payload)
        copies = 1
        if faults.duplicate and rng.random() < faults.duplicate:
            report.duplicated += 1
            copies = 2
        held = self._held.pop(device, None)
        if held is None and faults.reorder and rng.random() < faults.reorder:
            # Swap with the next message of this device: hold this one back until that one is out.
            report.reordered += 1
            self._held[device] = (data, copies)
            return
        self._publish(device, data, copies, connection)
        if held is not None:
            self._publish(device, held[0], held[1], connection)

    def _publish(self, device: str, data: bytes, copies: int, connection: _Connection) -> None:
        topic = self._topics[device]
        for _ in range(copies):
            connection.publish(topic, data)
        self.report.per_device[device] += copies

    def _flush(self, route: dict[str, _Connection]) -> None:
        for device, (data, copies) in list(self._held.items()):
            self._publish(device, data, copies, route[device])
        self._held.clear()

    def _wait_outstanding(self, connections: list[_Connection], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if all(c.outstanding == 0 for c in connections):
                    return
            time.sleep(0.01)

    def _log_report(self) -> None:
        r = self.report
        log.info(
            "edge-sim done: %d ticks, %d messages generated, %d published (%d failed), dropped %d, "
            "duplicated %d, reordered %d, malformed %d %s, skipped ticks %d, %.1f s",
            r.ticks,
            r.generated,
            r.published,
            r.publish_failures,
            r.dropped,
            r.duplicated,
            r.reordered,
            r.malformed_total,
            {k: v for k, v in r.malformed.items() if v},
            r.skipped_ticks,
            r.elapsed_s,
        )
