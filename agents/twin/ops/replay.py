"""`twin replay`: publish a device's recorded telemetry to a broker again, so the agent and viewer mirror it.

Each message is rebuilt from the stored raw readings exactly as the edge sent them (JSON integers for a
ticks device, floats for LeRobot-normalised ones), so the agent decodes the same angles it decoded the first
time. Messages go out at their recorded pace (receive-time spacing, divided by `speed`) through the project's
awscrt client (twin.transport.subscriber.build_mqtt5_client), QoS 0 like the edge. Timestamps are shifted so
the first replayed message carries "now" and the rest keep their edge spacing (divided by `speed`): an agent
that has mirrored the live arm would otherwise ignore a replay as older than what it has. `--original-
timestamps` keeps them as recorded.

A replay under the id of an arm that is publishing would interleave two arms' poses in one twin, and its
history and alarms with them: before it publishes, the replay listens on its topic for LIVE_CHECK_S and
refuses (ReplayRefusedError, naming the fix) if anything other than a retained message arrives.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from twin.core.topics import telemetry_topic
from twin.ops.history import HistoryReader, HistoryReadError, empty_hint, iso_utc
from twin.output.history import JOINTS, RAW_FIELDS, raw_column
from twin.transport.broker import BrokerConfig, crt_error_text, failure_hint, new_client_id
from twin.transport.client import build_mqtt5_client

log = logging.getLogger(__name__)

# IoT Core accepts at most 100 publishes per second on one connection (docs/aws-facts.md, "IoT Core quotas").
IOT_PUBLISHES_PER_S = 100
# Rows are read in windows of this length, so a day's replay never holds a day in memory.
READ_WINDOW = dt.timedelta(minutes=10)
# How long a replay waits, once every row is handed to the client, for its publishes to reach the socket.
FLUSH_TIMEOUT_S = 30.0
# How long a replay listens on its topic for a live arm first: the edge publishes at 10 Hz, so about 20 times.
LIVE_CHECK_S = 2.0
# A wait for the next recorded message at least this long is a pause in the window (the arm off), told.
PAUSE_S = 10.0


# What a replay tells as it goes: its report so far, and the wait before the next message when the window
# pauses there (else 0).
Progress = Callable[["ReplayReport", float], None]


class ReplayRefusedError(Exception):
    """The replay would publish under the id of an arm that is live, or could not check that it is not."""


@dataclass(frozen=True)
class ReplayConfig:
    uri: str
    device: str
    start: dt.datetime
    end: dt.datetime
    broker: BrokerConfig
    topic_prefix: str = "dt/lerobot"
    speed: float = 1.0
    as_device: str | None = None
    original_timestamps: bool = False
    storage_options: Mapping[str, str] = field(default_factory=dict)
    connect_timeout_s: float = 15.0
    live_check_s: float = LIVE_CHECK_S

    def __post_init__(self) -> None:
        if self.live_check_s <= 0:
            raise ValueError(f"live_check_s {self.live_check_s} must be positive")
        if not 0 < self.speed <= 1000:
            raise ValueError(f"--speed {self.speed} must be in (0, 1000]")
        if self.end <= self.start:
            raise ValueError(f"--to ({iso_utc(self.end)}) must be after --from ({iso_utc(self.start)})")
        telemetry_topic(self.topic_prefix, self.target_device)  # refuses ids that are not one topic level

    @property
    def target_device(self) -> str:
        return self.as_device or self.device


@dataclass
class ReplayReport:
    published: int = 0
    publish_failures: int = 0
    late: int = 0  # messages sent more than 50 ms after their due time (the machine could not keep up)
    first_recorded: str | None = None
    last_recorded: str | None = None
    elapsed_s: float = 0.0
    stopped: bool = False

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _number(value: float, integral: bool) -> int | float:
    return int(value) if integral and value.is_integer() else value


def payload_for(row: Mapping[str, Any], device_id: str, timestamp_ms: int) -> bytes:
    """The edge message for one stored row; absent readings stay absent."""
    ticks = row["units"] == "ticks"
    joints: dict[str, dict[str, int | float]] = {}
    for joint in JOINTS:
        entry: dict[str, int | float] = {}
        for name in RAW_FIELDS:
            value = row.get(raw_column(joint, name))
            if value is not None:
                # The ticks variant sends JSON integers (the decoder insists on them for positions).
                entry[name] = _number(float(value), ticks)
        joints[joint] = entry
    message = {"device_id": device_id, "timestamp": int(timestamp_ms), "joints": joints}
    return json.dumps(message, separators=(",", ":")).encode()


def recorded_rows(reader: HistoryReader, device: str, start: dt.datetime, end: dt.datetime) -> Iterator[dict]:
    """The device's rows in [start, end), oldest first, read one window at a time."""
    columns = ["received_at", "edge_time", "units"] + [raw_column(j, n) for j in JOINTS for n in RAW_FIELDS]
    cursor = start
    while cursor < end:
        upper = min(end, cursor + READ_WINDOW)
        frame = reader.collect(reader.window(device, cursor, upper, decoded=False).select(columns))
        yield from frame.iter_rows(named=True)
        cursor = upper


def replay(
    config: ReplayConfig,
    *,
    stop: threading.Event | None = None,
    reader: HistoryReader | None = None,
    on_progress: Progress | None = None,
) -> ReplayReport:
    """Publish the recorded window; returns the counts. Raises HistoryReadError when there is nothing (or
    no broker), and ReplayRefusedError when the target device is live (or that could not be checked).
    `on_progress(report, pause_s)`: called as the publishing begins (nothing published yet), after each
    message, and before a pause in the window (`pause_s`: the wait for the next message, else 0)."""
    stop = stop or threading.Event()
    reader = reader or HistoryReader(config.uri, config.storage_options)
    rows = recorded_rows(reader, config.device, config.start, config.end)
    first = next(rows, None)
    if first is None:
        # As ls, plot and export say it: not summary(), which worked out every session of the whole table,
        # nor every id of a fleet.
        hint = empty_hint(reader, config.device)
        raise HistoryReadError(
            f"no history rows for device {config.device!r} between {iso_utc(config.start)} and "
            f"{iso_utc(config.end)}{hint} (see `twin history ls`)"
        )
    if config.broker.kind == "iot" and 10.0 * config.speed > IOT_PUBLISHES_PER_S:
        log.warning(
            "replaying at %.1fx may exceed IoT Core's %d publishes/s per connection; excess is discarded",
            config.speed,
            IOT_PUBLISHES_PER_S,
        )
    report = ReplayReport()
    heard = _Heard()
    client, connection, on_done, outstanding = _client(config, report, heard)
    try:
        connection.wait()
        if not _check_not_live(config, client, heard, stop):
            report.stopped = True
            return report
        _publish_rows(
            config,
            client,
            _chain(first, rows),
            report,
            on_done=on_done,
            outstanding=outstanding,
            stop=stop,
            on_progress=on_progress,
        )
        # A QoS 0 publish completes once it is on the socket: stopping before then would lose the last ones.
        if not outstanding.wait_empty(FLUSH_TIMEOUT_S):
            log.warning(
                "replay: %d publishes still unwritten after %.0f s", outstanding.count, FLUSH_TIMEOUT_S
            )
    finally:
        client.stop()
    return report


class _Heard:
    """Messages the replay's client received on the target topic while it listened for a live arm."""

    def __init__(self) -> None:
        self.count = 0

    def on_publish(self, data: Any) -> None:
        # A retained message is the broker's memory, not an arm publishing now.
        if not data.publish_packet.retain:
            self.count += 1


def _check_not_live(config: ReplayConfig, client: Any, heard: _Heard, stop: threading.Event) -> bool:
    """Listen on the target topic for `live_check_s`; ReplayRefusedError if an arm publishes there, or if the
    broker does not let the replay listen. False when stopped meanwhile."""
    from awscrt import mqtt5  # noqa: PLC0415

    device = config.target_device
    topic = telemetry_topic(config.topic_prefix, device)
    refused = (
        f"could not check that {device} is not live on {config.broker.url}: the subscription to {topic} "
        "was refused ({}); the replay needs to subscribe to and receive its topic (iot:Subscribe and "
        "iot:Receive on IoT Core, as the agent has)"
    )
    packet = mqtt5.SubscribePacket(
        subscriptions=[mqtt5.Subscription(topic_filter=topic, qos=mqtt5.QoS.AT_MOST_ONCE)]
    )
    try:
        suback = client.subscribe(packet).result(config.connect_timeout_s)
    except Exception as exc:
        raise ReplayRefusedError(refused.format(f"{type(exc).__name__}: {exc}")) from exc
    failed = [code for code in suback.reason_codes if code.value >= 0x80]
    if failed:
        raise ReplayRefusedError(refused.format(failed[0].name))
    if stop.wait(config.live_check_s):
        return False
    # Stop listening before publishing: its own messages would come back to it. A failure here is the
    # connection's, which the publishes then meet and count.
    try:
        client.unsubscribe(mqtt5.UnsubscribePacket(topic_filters=[topic])).result(config.connect_timeout_s)
    except Exception as exc:
        log.warning("replay: unsubscribing from %s failed (%s: %s)", topic, type(exc).__name__, exc)
    if heard.count:
        raise ReplayRefusedError(
            f"{device} is live: {heard.count} messages on {topic} within {config.live_check_s:.0f} s. A "
            "replay under its id would mix two arms' poses in its twin, history and alarms; replay under "
            f"another id (--as-device {device}-replay), or once the arm is off"
        )
    return True


class _Outstanding:
    """Publishes handed to the client and not yet completed."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.count = 0

    def add(self) -> None:
        with self._cond:
            self.count += 1

    def done(self) -> None:
        with self._cond:
            self.count -= 1
            if self.count == 0:
                self._cond.notify_all()

    def wait_empty(self, timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: self.count == 0, timeout)


class _Connection:
    """The replay's connection: whether it is up, and the last failed connect's error with what to check."""

    def __init__(self, config: BrokerConfig, timeout_s: float) -> None:
        self.connected = threading.Event()
        self.failure = ""
        self._config = config
        self._timeout_s = timeout_s

    def on_failure(self, data: Any) -> None:
        hint = failure_hint(self._config, data)
        first = not self.failure
        self.failure = f"{crt_error_text(data.exception)}{f'. {hint}' if hint else ''}"
        if first:  # said at once: the command otherwise sat silent until its timeout
            log.warning(
                "could not connect to %s: %s; retrying for up to %.0f s",
                self._config.where(),
                self.failure,
                self._timeout_s,
            )

    def wait(self) -> None:
        """Until connected; HistoryReadError after the timeout, with the last failed connect's error and
        what to check ("check that the broker runs" alone left a user with a mistyped port to guess)."""
        if self.connected.wait(self._timeout_s):
            return
        why = f": {self.failure}" if self.failure else "; check --broker and that the broker runs"
        raise HistoryReadError(
            f"could not connect to the broker {self._config.where()} within {self._timeout_s:.0f} s{why}"
        )


def _client(
    config: ReplayConfig, report: ReplayReport, heard: _Heard
) -> tuple[Any, _Connection, Callable[[Any], None], _Outstanding]:
    """A started MQTT5 client, its connection, the publish callback that counts failures in `report`, and
    the count of publishes not yet completed. What it receives is counted in `heard`."""
    connection = _Connection(config.broker, config.connect_timeout_s)
    lock = threading.Lock()
    outstanding = _Outstanding()

    def on_done(future: Any) -> None:
        if future.exception() is not None:
            with lock:
                report.publish_failures += 1
        outstanding.done()

    client = build_mqtt5_client(
        config.broker,
        new_client_id(config.broker.client_id_prefix),
        on_publish_received=heard.on_publish,
        on_connection_success=lambda _data: connection.connected.set(),
        on_connection_failure=connection.on_failure,
    )
    client.start()
    return client, connection, on_done, outstanding


def _publish_rows(
    config: ReplayConfig,
    client: Any,
    rows: Iterator[dict],
    report: ReplayReport,
    *,
    on_done: Callable[[Any], None],
    outstanding: _Outstanding,
    stop: threading.Event,
    on_progress: Progress | None,
) -> None:
    """Publish each row at its recorded time (divided by the speed), restamped unless asked not to."""
    from awscrt import mqtt5  # noqa: PLC0415

    topic = telemetry_topic(config.topic_prefix, config.target_device)
    started = time.monotonic()
    # Whole milliseconds: each stamp is this plus its rounded offset, so the replayed spacing is the
    # recording's (scaled) exactly; a fractional base made a half-millisecond tie round a gap one way or the
    # other about once in 4,096 replays.
    now_ms = round(time.time() * 1000.0)
    first_received = first_edge_ms = None
    for row in rows:
        if first_received is None:
            first_received = row["received_at"]
            first_edge_ms = row["edge_time"].timestamp() * 1000.0
            report.first_recorded = iso_utc(first_received)
            if on_progress is not None:
                on_progress(report, 0.0)
        if stop.is_set():
            report.stopped = True
            break
        wait = (
            started + (row["received_at"] - first_received).total_seconds() / config.speed - time.monotonic()
        )
        if on_progress is not None and wait >= PAUSE_S:
            on_progress(report, wait)  # the window pauses (the arm was off): said, not a silent wait
        if wait > 0 and stop.wait(wait):
            report.stopped = True
            break
        if -wait > 0.05:
            report.late += 1
        edge_ms = row["edge_time"].timestamp() * 1000.0
        if config.original_timestamps:
            stamp = round(edge_ms)
        else:
            stamp = now_ms + round((edge_ms - first_edge_ms) / config.speed)
        outstanding.add()
        future = client.publish(
            mqtt5.PublishPacket(
                topic=topic, payload=payload_for(row, config.target_device, stamp), qos=mqtt5.QoS.AT_MOST_ONCE
            )
        )
        future.add_done_callback(on_done)
        report.published += 1
        report.last_recorded = iso_utc(row["received_at"])
        if on_progress is not None:
            on_progress(report, 0.0)
    report.elapsed_s = time.monotonic() - started


def _chain(first: dict, rest: Iterator[dict]) -> Iterator[dict]:
    yield first
    yield from rest
