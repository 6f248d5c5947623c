"""Prometheus exposition of the agent's typed state, through prometheus_client.

The agent keeps its own counters (health, mailbox, subscriber, sinks) and publishes them as one `AgentState`,
so the metrics are rendered from that snapshot by a custom collector instead of being mirrored into
prometheus_client's own Counter objects: /metrics then shows exactly the numbers /state shows, from the same
instant. prometheus_client does the text format (escaping, HELP/TYPE lines, value formatting).

Metric names are documented in docs/http-api.md; every counter family ends in `_total`, and an unknown value
(no sample yet) is left out rather than published as a made-up zero.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4

from twin.core.health import DeviceStatus
from twin.service.state import AgentInfo, AgentState, AlarmInfo, DeviceState, HistoryState, ServoState

# Every metric name is valid in the classic format, so the widely parsed 0.0.4 text format is served.
CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4
UNTRACKED_DEVICE = "_untracked"  # the device label of rejections that belong to no tracked device
_STATUSES = tuple(DeviceStatus)

_BROKER_COUNTERS = (
    ("connection_successes", "MQTT connections established (the first and every reconnect)."),
    ("connection_failures", "MQTT connection attempts that failed."),
    ("disconnections", "MQTT connections lost."),
    ("subscribes", "SUBSCRIBE requests acknowledged by the broker."),
    ("messages", "PUBLISH packets received from the broker (all devices, before decoding)."),
)
_MESSAGE_COUNTERS = (
    ("received", "Messages taken from the mailbox for decoding."),
    ("decoded", "Messages that decoded into valid telemetry."),
    ("applied", "Messages applied to the twin (newer than the last applied one)."),
    (
        "ignored_stale",
        "Valid messages ignored because their timestamp was not newer (duplicate or reordered).",
    ),
    (
        "coalesced",
        "Valid messages not applied because a newer one of the same arm was waiting (worker catching up).",
    ),
    ("overwritten", "Messages dropped undecoded because the worker fell a whole queue behind."),
)
_SINK_COUNTERS = (
    ("delivered", "Samples a sink handled."),
    ("dropped", "Samples a sink dropped because its queue was full or it was closing."),
    ("errors", "Errors a sink raised while handling a sample."),
    ("skipped", "Samples a sink chose not to write (its rate cap, e.g. the Rerun stream's max_rate_hz)."),
)


def _gauge(name: str, help_text: str, value: float | None) -> GaugeMetricFamily:
    family = GaugeMetricFamily(name, help_text)
    if value is not None:
        family.add_metric([], value)
    return family


def _counter(name: str, help_text: str, value: float | None) -> CounterMetricFamily:
    family = CounterMetricFamily(name, help_text)
    if value is not None:
        family.add_metric([], value)
    return family


def _agent_families(agent: AgentInfo) -> Iterator[Metric]:
    """The agent's own families, in the order docs/http-api.md lists them."""
    broker = agent.broker
    yield _gauge("twin_up", "1 while the agent service is running.", 1 if agent.running else 0)
    yield _gauge("twin_uptime_seconds", "Seconds since the agent service started.", agent.uptime_s)
    yield _gauge("twin_broker_connected", "1 while the MQTT connection is up.", 1 if broker.connected else 0)
    for key, help_text in _BROKER_COUNTERS:
        yield _counter(f"twin_broker_{key}_total", help_text, getattr(broker, key))
    yield _counter(
        "twin_mailbox_overwritten_total",
        "Messages dropped undecoded because the worker fell a whole queue behind.",
        agent.mailbox.overwritten_total,
    )
    yield _counter(
        "twin_mailbox_refused_keys_total",
        "Messages refused: too many distinct topics pending.",
        agent.mailbox.refused_keys,
    )
    yield _counter(
        "twin_worker_batches_total", "Batches the twin worker took from the mailbox.", agent.worker.batches
    )
    yield _gauge(
        "twin_worker_behind_seconds",
        "How far behind its messages a worker stands, the most of any worker: its last sweep's lag, or the "
        "age of the oldest message of the batch it is handling if more.",
        agent.worker.behind_s,
    )
    yield from _sink_families(agent)
    yield _counter(
        "twin_emf_clock_steps_total",
        "Steps of the host's wall clock the CloudWatch metrics publisher saw (time sync stepping it).",
        agent.emf_clock_steps,
    )
    if agent.history is not None:
        yield from _history_families(agent.history)
    yield from _alarm_families(agent)
    yield from _pool_families(agent)
    yield from _worker_families(agent)
    loss = agent.loss
    yield _counter(
        "twin_fleet_messages_lost_total",
        "Messages estimated lost in transit over every device (gaps in the edge timestamps).",
        loss.lost,
    )
    yield _gauge(
        "twin_fleet_loss_ratio", "Estimated lost / (received + lost) over every device.", loss.loss_ratio
    )
    yield _gauge("twin_fleet_devices_losing", "Devices that lost messages recently.", loss.devices_losing)


def _sink_families(agent: AgentInfo) -> Iterator[Metric]:
    for key, help_text in _SINK_COUNTERS:
        family = CounterMetricFamily(f"twin_sink_{key}_total", help_text, labels=["sink"])
        for sink in agent.sinks:
            family.add_metric([sink.name], getattr(sink, key))
        yield family
    pending = GaugeMetricFamily(
        "twin_sink_pending", "Samples queued in a sink, not yet handled.", labels=["sink"]
    )
    for sink in agent.sinks:
        pending.add_metric([sink.name], sink.pending)
    yield pending


def _history_families(h: HistoryState) -> Iterator[Metric]:
    yield _counter(
        "twin_history_rows_committed_total", "Telemetry rows committed to history.", h.rows_committed
    )
    yield _counter("twin_history_commits_total", "History commits (telemetry table).", h.commits)
    yield _counter(
        "twin_history_commit_failures_total",
        "Failed history commits (retried with backoff).",
        h.commit_failures,
    )
    yield _counter(
        "twin_history_rows_dropped_total",
        "History rows dropped: the write buffer was full.",
        h.rows_dropped,
    )
    yield _counter(
        "twin_history_rows_lost_total",
        "History rows lost with a history writer process that died holding them.",
        h.rows_lost,
    )
    yield _counter(
        "twin_history_rows_expired_total",
        "History rows deleted by maintenance for being older than [history] keep_days.",
        h.rows_expired,
    )
    yield _counter(
        "twin_history_log_entries_set_aside_total",
        "Newest history log entries found empty (a commit cut short by a crash) and moved aside.",
        h.log_entries_set_aside,
    )
    yield _counter(
        "twin_history_writer_restarts_total",
        "Times the history writer process was started again after it died.",
        h.writer_restarts,
    )
    yield _gauge("twin_history_rows_buffered", "History rows waiting for a commit.", h.rows_buffered)
    if h.storage_ok is not None:  # unknown until the writer's first commit attempt: no sample, not a 1
        yield _gauge(
            "twin_history_storage_ok",
            "1 while each history table's last commit succeeded (absent before the first attempt).",
            1.0 if h.storage_ok else 0.0,
        )
    yield _gauge(
        "twin_history_lag_seconds",
        "How long ago the oldest history row not yet written arrived (0: every row is written).",
        h.lag_s,
    )


def _alarm_families(agent: AgentInfo) -> Iterator[Metric]:
    alarms = agent.alarms
    gauge = GaugeMetricFamily(
        "twin_servo_alarms",
        "Servo alarms by severity and state (NORMAL included).",
        labels=["severity", "state"],
    )
    for severity, states in sorted(alarms.by_state.items()):
        for state, count in sorted(states.items()):
            gauge.add_metric([severity, state], count)
    yield gauge
    present = GaugeMetricFamily(
        "twin_servo_alarms_present",
        "Servo alarms whose condition is present (ACTIVE or ACKNOWLEDGED), by severity.",
        labels=["severity"],
    )
    for severity, count in sorted(alarms.present.items()):
        present.add_metric([severity], count)
    yield present
    for key, help_text in (
        ("raised", "Servo alarms raised (NORMAL or LATCHED -> ACTIVE), by kind."),
        ("cleared", "Servo alarm conditions cleared, by kind."),
        ("acknowledged", "Servo alarms acknowledged by a person, by kind."),
    ):
        family = CounterMetricFamily(f"twin_servo_alarms_{key}_total", help_text, labels=["kind"])
        for kind, count in sorted(getattr(alarms, f"{key}_total").items()):
            family.add_metric([kind], count)
        yield family


# ServoState field -> (metric name, help): the servo readings in physical units, per device and joint.
_SERVO_GAUGES = (
    ("velocity_rad_s", "twin_servo_velocity_radians_per_second", "Servo velocity (rad/s, signed)."),
    ("load_percent", "twin_servo_load_percent", "Servo load, percent of stall torque (signed)."),
    ("temperature_c", "twin_servo_temperature_celsius", "Servo temperature (C)."),
    ("current_a", "twin_servo_current_amperes", "Servo current (A)."),
    ("voltage_v", "twin_servo_voltage_volts", "Servo supply voltage (V)."),
    (
        "model_load_percent",
        "twin_servo_model_load_percent",
        "Load the model's inverse-dynamics holding torque implies, percent of stall torque.",
    ),
    (
        "mismatch_percent",
        "twin_servo_model_mismatch_percent",
        "| |load| - |model load| | in percentage points, while the joint is still.",
    ),
)


def _worker_families(agent: AgentInfo) -> Iterator[Metric]:
    """A sharded agent's worker processes (none when one process does everything)."""
    if not agent.workers:
        return
    label = ["worker"]
    up = GaugeMetricFamily("twin_worker_up", "1 while a worker process runs.", labels=label)
    devices = GaugeMetricFamily("twin_worker_devices", "Devices a worker process mirrors.", labels=label)
    queued = GaugeMetricFamily(
        "twin_worker_queued", "Messages the receiving process holds for a worker.", labels=label
    )
    restarts = CounterMetricFamily(
        "twin_worker_restarts_total", "Times a worker process was started again.", labels=label
    )
    dropped = CounterMetricFamily(
        "twin_worker_dropped_total",
        "Messages the receiving process dropped for a worker (its queue full, or the worker down).",
        labels=label,
    )
    for w in agent.workers:
        index = [str(w.index)]
        up.add_metric(index, 1 if w.alive else 0)
        devices.add_metric(index, w.devices)
        queued.add_metric(index, w.queued)
        restarts.add_metric(index, w.restarts)
        dropped.add_metric(index, w.dropped)
    yield from (up, devices, queued, restarts, dropped)


def _pool_families(agent: AgentInfo) -> Iterator[Metric]:
    broker = agent.broker
    yield _gauge(
        "twin_broker_per_connection_limit",
        "Publishes per second one connection may carry (absent: unlimited).",
        broker.per_connection_limit,
    )
    yield _gauge("twin_broker_connections", "Connections in the subscriber pool.", len(broker.connections))
    yield _gauge(
        "twin_broker_quota_discarding",
        "1 while the broker's per-connection quota discards what the pool cannot take on (/healthz: why).",
        1.0 if broker.quota_notice else 0.0,
    )
    labels = ["connection", "client_id"]
    up = GaugeMetricFamily("twin_connection_up", "1 while this pool connection is connected.", labels=labels)
    rate = GaugeMetricFamily(
        "twin_connection_message_rate_hz", "Messages per second received on this connection.", labels=labels
    )
    messages = CounterMetricFamily(
        "twin_connection_messages_total", "Messages received on this connection.", labels=labels
    )
    reconnects = CounterMetricFamily(
        "twin_connection_disconnections_total", "Times this connection was lost.", labels=labels
    )
    refused = GaugeMetricFamily(
        "twin_connection_refused_filters",
        "Topic filters the broker refused on this connection (an IoT policy that does not allow them).",
        labels=labels,
    )
    for c in broker.connections:
        key = [str(c.index), c.client_id]
        up.add_metric(key, 1 if c.state in ("connected", "refused") else 0)
        rate.add_metric(key, c.rate_hz)
        messages.add_metric(key, c.messages)
        reconnects.add_metric(key, c.disconnections)
        refused.add_metric(key, len(c.refused))
    yield from (up, rate, messages, reconnects, refused)


class _DeviceFamilies:
    """The per-device families, filled device by device (one family per metric, many label sets)."""

    def __init__(self) -> None:
        # One declaration per family (name, help, labels), as docs/http-api.md lists them: health, latency,
        # twin.
        self._declare_health(["device"])
        self._declare_latency(["device"])
        self._declare_twin(["device"])

    def _declare_health(self, dev: list[str]) -> None:
        self.status = GaugeMetricFamily(
            "twin_device_status", "Device health status (1 for the current status).", labels=[*dev, "status"]
        )
        self.age = GaugeMetricFamily(
            "twin_device_last_message_age_seconds",
            "Seconds since the last valid message (agent clock).",
            labels=dev,
        )
        self.rate = GaugeMetricFamily(
            "twin_device_message_rate_hz", "Valid messages per second over the health window.", labels=dev
        )
        self.messages = {
            key: CounterMetricFamily(f"twin_messages_{key}_total", help_text, labels=dev)
            for key, help_text in _MESSAGE_COUNTERS
        }
        self.rejected = CounterMetricFamily(
            "twin_messages_rejected_total",
            "Messages rejected by the decoder, by reason.",
            labels=[*dev, "reason"],
        )
        self.errors = CounterMetricFamily(
            "twin_worker_errors_total", "Unexpected errors while processing a message.", labels=dev
        )
        self.resets = CounterMetricFamily(
            "twin_edge_clock_resets_total", "Edge clock jumps backwards that re-based the twin.", labels=dev
        )
        self.lost = CounterMetricFamily(
            "twin_messages_lost_total",
            "Messages estimated lost in transit (gaps in the edge timestamps).",
            labels=dev,
        )
        self.loss_ratio = GaugeMetricFamily(
            "twin_device_loss_ratio", "Estimated lost / (received + lost) since start.", labels=dev
        )
        self.losing = GaugeMetricFamily(
            "twin_device_losing", "1 while the device lost messages recently.", labels=dev
        )

    def _declare_latency(self, dev: list[str]) -> None:
        self.edge_p50 = GaugeMetricFamily(
            "twin_edge_clock_latency_p50_seconds",
            "Median of receive wall time minus edge timestamp; "
            "includes edge clock offset (not NTP-disciplined).",
            labels=dev,
        )
        self.edge_p99 = GaugeMetricFamily(
            "twin_edge_clock_latency_p99_seconds",
            "p99 of receive wall time minus edge timestamp.",
            labels=dev,
        )
        self.offset = GaugeMetricFamily(
            "twin_edge_clock_offset_seconds",
            "Window minimum of receive wall time minus edge timestamp: "
            "clock offset plus the fastest transit.",
            labels=dev,
        )
        self.int_p50 = GaugeMetricFamily(
            "twin_internal_latency_p50_seconds", "Median time from receive to twin updated.", labels=dev
        )
        self.int_p99 = GaugeMetricFamily(
            "twin_internal_latency_p99_seconds", "p99 time from receive to twin updated.", labels=dev
        )

    def _declare_twin(self, dev: list[str]) -> None:
        self.joints = GaugeMetricFamily(
            "twin_joint_position_radians", "Joint angle of the twin, radians.", labels=[*dev, "joint"]
        )
        self.torques = GaugeMetricFamily(
            "twin_joint_torque_newton_metres",
            "Inverse-dynamics joint torque of the measured pose.",
            labels=[*dev, "joint"],
        )
        self.servos = {
            attr: GaugeMetricFamily(name, help_text, labels=[*dev, "joint"])
            for attr, name, help_text in _SERVO_GAUGES
        }

    def add(self, device: str, d: DeviceState) -> None:
        for status in _STATUSES:
            self.status.add_metric([device, status.value], 1 if d.health.status == status else 0)
        _maybe(self.age, [device], d.health.age_s)
        _maybe(self.rate, [device], d.health.rate_hz)
        c = d.health.counters
        for key, family in self.messages.items():
            family.add_metric([device], getattr(c, key))
        for reason, count in sorted(c.rejected.items()):
            self.rejected.add_metric([device, reason], count)
        self.errors.add_metric([device], c.errors)
        self.resets.add_metric([device], c.clock_resets)
        _maybe(self.edge_p50, [device], d.health.edge_clock_latency_s.p50)
        _maybe(self.edge_p99, [device], d.health.edge_clock_latency_s.p99)
        _maybe(self.offset, [device], d.health.edge_clock_offset_s)
        _maybe(self.int_p50, [device], d.health.internal_latency_s.p50)
        _maybe(self.int_p99, [device], d.health.internal_latency_s.p99)
        for joint, value in (d.joints_rad or {}).items():
            self.joints.add_metric([device, joint], value)
        for joint, value in (d.torques_nm or {}).items():
            self.torques.add_metric([device, joint], value)
        for joint, servo in (d.servos or {}).items():
            self._add_servo(device, joint, servo)
        self.lost.add_metric([device], d.loss.lost)
        self.loss_ratio.add_metric([device], d.loss.loss_ratio)
        self.losing.add_metric([device], 1 if d.loss.losing else 0)

    def _add_servo(self, device: str, joint: str, servo: ServoState) -> None:
        for attr, family in self.servos.items():
            _maybe(family, [device, joint], getattr(servo, attr))

    def all(self) -> Iterator[Metric]:
        yield self.status
        yield self.age
        yield self.rate
        yield from self.messages.values()
        yield from (self.rejected, self.errors, self.resets, self.edge_p50, self.edge_p99, self.offset)
        yield from (self.int_p50, self.int_p99, self.joints, self.torques)
        yield from self.servos.values()
        yield from (self.lost, self.loss_ratio, self.losing)


def _maybe(family: GaugeMetricFamily, labels: list[str], value: float | None) -> None:
    if value is not None:  # an unknown value (no samples yet) is absent, not a fake zero
        family.add_metric(labels, value)


class _StateCollector:
    """A prometheus_client collector over one state snapshot."""

    def __init__(self, state: AgentState, alarms: Sequence[AlarmInfo]) -> None:
        self._state = state
        self._alarms = alarms

    def collect(self) -> Iterator[Metric]:
        state = self._state
        yield from _agent_families(state.agent)
        yield _alarm_series(self._alarms)
        devices = _DeviceFamilies()
        for device, d in sorted(state.devices.items()):
            devices.add(device, d)
        for reason, count in sorted(state.untracked_rejected.items()):
            devices.rejected.add_metric([UNTRACKED_DEVICE, reason], count)
        yield from devices.all()


def _alarm_series(alarms: Sequence[AlarmInfo]) -> GaugeMetricFamily:
    """One series per servo alarm that is not NORMAL, naming its arm, servo, kind and state: an alerting rule
    can then say which servo, where the counts above say only how many. Bounded by the alarms present."""
    family = GaugeMetricFamily(
        "twin_servo_alarm",
        "1 for each servo alarm that is not NORMAL, by device, joint, kind, severity and state.",
        labels=["device", "joint", "kind", "severity", "state"],
    )
    for a in alarms:
        if a.state != "NORMAL":
            family.add_metric([a.device, a.joint, a.kind, a.severity, a.state], 1)
    return family


def render_metrics(state: AgentState, alarms: Sequence[AlarmInfo] = ()) -> str:
    """The state, and the servo alarms that are not NORMAL (GET /alarms), as Prometheus text exposition
    format (every family with HELP and TYPE)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_StateCollector(state, alarms))
    return generate_latest(registry).decode()
