"""The agent's typed state: what `AgentService.state()` returns and `/state`, `/metrics`, `/stream` publish.

Frozen dataclasses, one document: `AgentState.to_json()` is the body of `GET /state` and of every `/stream`
event, `AgentState.from_json()` reads it back (the viewer, `twin bench`), and `twin.service.metrics` renders
the Prometheus exposition from the same object, so the three endpoints cannot disagree. docs/http-api.md
describes every field. The JSON encoding is msgspec's: field order as declared, NaN and infinities as `null`
(JSON has no NaN), enums by value.

A document must have `agent` and `devices` (anything else is not an agent state); every other field has a
default, so a document from an agent that lacks a newer field still parses (the field reads as its
default), and fields this version does not know are ignored.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import msgspec

from twin.core.health import DeviceCounters, DeviceStatus, HealthSnapshot, WindowLatency
from twin.core.latency import LatencySummary
from twin.core.loss import FleetLoss, LossSnapshot
from twin.core.modes import TwinMode
from twin.core.units import Units
from twin.output.sinks import SinkStats

__all__ = [
    "AgentInfo",
    "AgentState",
    "AlarmInfo",
    "AlarmList",
    "AlarmsSummary",
    "BrokerState",
    "ConnectionState",
    "DeviceCounters",
    "DeviceState",
    "DeviceView",
    "FleetLatency",
    "FleetLoss",
    "HealthReport",
    "HealthSnapshot",
    "LatencySummary",
    "LossSnapshot",
    "MailboxState",
    "MirrorStatus",
    "RecordingState",
    "ServoState",
    "SinkStats",
    "WindowLatency",
    "WorkerInfo",
    "WorkerState",
]

_ENCODER = msgspec.json.Encoder()


class MirrorStatus(StrEnum):
    """Whether a device's mirror runs: `restarting` while its worker process is being started again, and
    `stopping` once the agent's stop has ended it (the device's figures are then its worker's last checkpoint,
    service.shards)."""

    RUNNING = "running"
    RESTARTING = "restarting"
    STOPPING = "stopping"


@dataclass(frozen=True, slots=True)
class ServoState:
    """One joint's servo in physical units (None: not sent), what the model expects of it, and its worst
    alarm that is not NORMAL (docs/servo-health.md)."""

    velocity_rad_s: float | None = None
    load_percent: float | None = None  # of the servo's stall torque
    temperature_c: float | None = None
    current_a: float | None = None
    voltage_v: float | None = None
    # The inverse-dynamics holding torque as the load the servo should report, and how far the measured load
    # is from it (only while the joint is still).
    model_load_percent: float | None = None
    mismatch_percent: float | None = None
    still: bool | None = None
    alarm_severity: str | None = None  # warning | critical
    alarm_state: str | None = None  # ACTIVE | ACKNOWLEDGED | LATCHED
    # The error bits the servo itself sets in its status register, by name (robot.sts3215.STATUS_BITS);
    # None when the edge sends no status.
    errors: tuple[str, ...] | None = None


@dataclass(frozen=True, slots=True)
class AlarmInfo:
    """One servo alarm (GET /alarms); `changed_at` is the wall time of its last state change."""

    alarm_id: str = ""
    device: str = ""
    joint: str = ""
    kind: str = ""
    severity: str = ""
    state: str = ""
    value: float | None = None
    threshold: float = 0.0
    unit: str = ""
    changed_at: float = 0.0
    raised: int = 0
    message: str = ""
    advice: str = ""  # what to do at the arm (core.alarms.what_to_do)


@dataclass(frozen=True)
class AlarmList:
    """The body of GET /alarms: alarms that are not NORMAL (all of them with ?all=1), worst first."""

    alarms: tuple[AlarmInfo, ...] = ()

    def to_json(self) -> bytes:
        return _ENCODER.encode(self)

    @classmethod
    def from_json(cls, data: bytes | str) -> AlarmList:
        return msgspec.json.decode(data, type=cls)


@dataclass(frozen=True)
class AlarmsSummary:
    """Servo alarms across the fleet: counts by state and severity, and running totals of state changes."""

    present: dict[str, int] = field(default_factory=dict)  # severity -> ACTIVE or ACKNOWLEDGED alarms
    by_state: dict[str, dict[str, int]] = field(default_factory=dict)  # severity -> state -> alarms
    raised_total: dict[str, int] = field(default_factory=dict)  # kind -> times raised
    cleared_total: dict[str, int] = field(default_factory=dict)
    acknowledged_total: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class ConnectionState:
    """One connection of the subscriber pool (twin.transport.pool)."""

    index: int = 0
    client_id: str = ""
    state: str = "connecting"
    filters: int = 0
    rate_hz: float = 0.0
    messages: int = 0
    connection_successes: int = 0
    disconnections: int = 0
    # The latest error, kept after the connection recovered, and its wall time (None: none yet): one older
    # than `connected_at`, its latest connect, is past.
    last_error: str = ""
    last_error_at: float | None = None
    connected_at: float | None = None
    # Topic filters the broker refused on this connection (state "refused"): their telemetry does not arrive.
    refused: tuple[str, ...] = ()


@dataclass(frozen=True)
class DeviceState:
    """One device: its health (status, age, rate, counters, latencies; twin.core.health) and its twin's
    latest pose."""

    device_id: str = ""
    health: HealthSnapshot = field(default_factory=HealthSnapshot)
    # The twin: None until the first message of this device is applied.
    units: Units = Units.AUTO
    mode: TwinMode = TwinMode.KINEMATIC
    timestamp_ms: int | None = None
    joints_rad: dict[str, float] | None = None
    targets_rad: dict[str, float] | None = None
    torques_nm: dict[str, float] | None = None
    tcp_position_m: tuple[float, float, float] | None = None
    gripper_percent: float | None = None
    # Per joint, from the last applied message: None until one arrives.
    servos: dict[str, ServoState] | None = None
    # Messages estimated lost in transit, from the gaps in its edge timestamps (twin.core.loss).
    loss: LossSnapshot = field(default_factory=LossSnapshot)
    # Where the LeRobot calibration it decodes with came from: its own file in the calibration store, the
    # config's one for every arm, or "" for none (the nominal SO-101). `uncalibrated`: none, while its units
    # (ticks, range100) need one, so its angles are the nominal arm's, not this arm's (docs/agent.md,
    # "Calibration").
    calibration: str = ""
    uncalibrated: bool = False
    # Why its file in the calibration store was refused (it keeps the calibration it had); "" when it was not.
    calibration_problem: str = ""
    # running, or restarting while its worker process is started again (the figures are then its last
    # checkpoint's; the arm never leaves /state).
    mirror: MirrorStatus = MirrorStatus.RUNNING


@dataclass(frozen=True, slots=True)
class BrokerState:
    """The broker side, summed over the pool's connections (`connections` has each one)."""

    url: str = ""
    client_id: str | None = None
    connected: bool = False
    connection_successes: int = 0
    connection_failures: int = 0
    disconnections: int = 0
    subscribes: int = 0
    messages: int = 0
    # The latest error of any connection, kept after it recovered, and its wall time (None: none yet);
    # `connected` says whether the broker is reached now.
    last_error: str = ""
    last_error_at: float | None = None
    # Publishes per second one connection may carry (None: unlimited), and the pool's measured total rate.
    per_connection_limit: float | None = None
    rate_hz: float = 0.0
    # Topic filters refused now, over every connection (an IoT policy that does not allow them).
    subscriptions_refused: int = 0
    # While the broker's per-connection quota discards what the pool cannot take on, what /healthz says of it
    # (the cause and the fix); "" otherwise. A scraper or script reading /state saw only the loss it causes.
    quota_notice: str = ""
    connections: tuple[ConnectionState, ...] = ()


@dataclass(frozen=True, slots=True)
class MailboxState:
    """The queue between the MQTT threads and the worker. Every message is decoded; `overwritten_total`
    counts those dropped undecoded because the worker fell a whole queue behind."""

    overwritten_total: int = 0
    refused_keys: int = 0
    pending: int = 0


@dataclass(frozen=True, slots=True)
class FleetLatency:
    """Fleet-wide distributions over every applied message since start (log-bucket histograms)."""

    internal_s: LatencySummary = field(default_factory=LatencySummary)
    end_to_end_s: LatencySummary = field(default_factory=LatencySummary)


@dataclass(frozen=True, slots=True)
class WorkerState:
    alive: bool = False
    batches: int = 0
    processed: int = 0
    errors: int = 0
    # CPU seconds the mirrors' worker threads spent in each stage since start (hand_over, decode, twin,
    # health_alarms, sinks), summed over the workers: where the agent's CPU goes (`twin bench cost`). An
    # estimate: the stages are timed on a sample of the batches and scaled (service.stagetiming).
    stage_cpu_s: dict[str, float] = field(default_factory=dict)
    # The batches whose stages were timed, summed over the workers (what the estimate rests on).
    stage_timed_batches: int = 0
    # Messages the servo alarm engine evaluated, summed over the workers since each started: 0 with
    # [alarms] enabled = false (`twin bench cost --no-alarms` shows it was).
    alarm_rows: int = 0
    # How far behind its messages a worker stands, the most of any worker, read when asked: where its last
    # status sweep found it (the newest receive time of the batch it handled then, to the clock; 0 once it
    # found nothing waiting), or the age of the oldest message of the batch it is handling if more, so a
    # worker held in one batch shows its lag growing. The arms' statuses and rates are read at the sweep's
    # point (docs/agent.md, "Health").
    behind_s: float = 0.0


@dataclass(frozen=True, slots=True)
class RecordingState:
    """The USD session recording (a sink; its queue figures are in `agent.sinks`)."""

    # The newest session file on disk; "" once none is (a session with no sample is removed at close).
    path: str = ""
    samples_written: int = 0
    # Samples less than one time code (1/30 s) after the device's previous one: the stage keeps 30 per second.
    samples_dropped: int = 0
    flushes: int = 0
    flush_errors: int = 0
    # New session files begun ([twin] record_max_mb, record_max_age_s) and old ones deleted to keep the
    # directory within record_budget_mb.
    rotations: int = 0
    files_deleted: int = 0


@dataclass(frozen=True, slots=True)
class HistoryState:
    """The telemetry history writer (docs/history.md; its queue figures are in `agent.sinks`)."""

    uri: str = ""
    # Each table's last commit worked; None (null) until the writer process's first commit attempt.
    storage_ok: bool | None = None
    rows_committed: int = 0
    commits: int = 0
    commit_failures: int = 0
    # Rows dropped because the write buffer was full (an outage longer than max_buffer_rows lasts).
    rows_dropped: int = 0
    rows_buffered: int = 0
    rejected_rows_committed: int = 0
    maintenance_runs: int = 0
    maintenance_failures: int = 0
    # Rows maintenance deleted for being older than [history] keep_days: gone on purpose, not lost.
    rows_expired: int = 0
    # Newest log entries found empty (a commit cut short by a crash or a full disk) and moved aside.
    log_entries_set_aside: int = 0
    last_error: str = ""
    # How long the oldest row not yet written has waited, seconds (0: nothing waits); grows in an outage.
    lag_s: float = 0.0
    # The process that writes the history (its own, apart from the mirrors); None while it is not running.
    writer_pid: int | None = None
    # Times the writer process was started again after it died, the rows it received from the mirrors, and
    # the rows lost with a writer that died holding them (not yet committed).
    writer_restarts: int = 0
    rows_received: int = 0
    rows_lost: int = 0

    @property
    def rows_not_written(self) -> int:
        """Rows that will never be written: dropped by the writer's buffer, or lost with a writer process
        that died holding them (what CloudWatch's HistoryRowsDropped counts)."""
        return self.rows_dropped + self.rows_lost


@dataclass(frozen=True, slots=True)
class WorkerInfo:
    """One worker process of a sharded agent (`twin run --workers N`, docs/scaling.md "Workers"): the devices
    it mirrors, what it handled, and what the receiving process queued for it or could not hand over."""

    index: int = 0
    pid: int = 0
    alive: bool = False
    restarts: int = 0
    devices: int = 0
    queued: int = 0
    dropped: int = 0
    processed: int = 0
    errors: int = 0
    recording: str = ""
    # Died and being started again: its arms show as restarting until it runs.
    restarting: bool = False


@dataclass(frozen=True)
class AgentInfo:
    running: bool = False
    pid: int = 0
    started_at: float | None = None
    uptime_s: float = 0.0
    time: float = 0.0
    mode: TwinMode = TwinMode.KINEMATIC
    units: Units = Units.AUTO
    devices: tuple[str, ...] = ()
    topic_filters: tuple[str, ...] = ()
    broker: BrokerState = field(default_factory=BrokerState)
    mailbox: MailboxState = field(default_factory=MailboxState)
    latency: FleetLatency = field(default_factory=FleetLatency)
    worker: WorkerState = field(default_factory=WorkerState)
    recording: RecordingState | None = None
    history: HistoryState | None = None
    sinks: tuple[SinkStats, ...] = ()
    alarms: AlarmsSummary = field(default_factory=AlarmsSummary)
    loss: FleetLoss = field(default_factory=FleetLoss)
    # A sharded agent's worker processes (empty when one process does everything).
    workers: tuple[WorkerInfo, ...] = ()
    # Where it reads each arm's own calibration ([telemetry] calibrations): s3://bucket/prefix or an absolute
    # directory, "" for none. The console's Arm page says how to push to it (docs/agent.md, "Calibration").
    calibration_store: str = ""
    # Steps of the host's wall clock the CloudWatch metrics publisher saw (`null` without [cloudwatch]
    # emf_file): only logged before, so a host whose time sync keeps stepping showed it nowhere one looks.
    emf_clock_steps: int | None = None


@dataclass(frozen=True)
class AgentState:
    """The whole state document (GET /state)."""

    agent: AgentInfo
    devices: dict[str, DeviceState]
    untracked_rejected: dict[str, int] = field(default_factory=dict)

    def messages_handled(self) -> int:
        """How many messages the agent is done counting: each ends as `received` of a device it tracks
        (applied, ignored, coalesced or rejected) or as a rejection of an untracked one. Unlike
        `agent.worker.processed`, which counts a message when a mirror takes it, these are counted after it
        was decoded and its health recorded, so a reader waiting for N messages can wait on this."""
        tracked = sum(d.health.counters.received for d in self.devices.values())
        return tracked + sum(self.untracked_rejected.values())

    def to_json(self) -> bytes:
        """The JSON document (UTF-8); NaN and infinities become null."""
        return _ENCODER.encode(self)

    @classmethod
    def from_json(cls, data: bytes | str) -> AgentState:
        """Parse a /state document; raises ValueError (msgspec.ValidationError) naming the bad field."""
        return msgspec.json.decode(data, type=cls)


@dataclass(frozen=True)
class DeviceView:
    """One arm as `GET /stream?device=<id>` sends it (what `twin view` follows): the agent's wall time, the
    arm (None while no mirror tracks it) and every device id the agent tracks, so a viewer can page through
    the fleet without the whole fleet's state at every frame."""

    time: float
    device: DeviceState | None
    devices: list[str]
    # The arms among `devices` that want a look, with why (attention_mark): the desktop shows one arm at a
    # time, and a critical alarm on another must not wait for someone to page to it. Read with `devices`.
    attention: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> bytes:
        """The JSON document (UTF-8); NaN and infinities become null."""
        return _ENCODER.encode(self)

    @classmethod
    def from_json(cls, data: bytes | str) -> DeviceView:
        """Parse one such document; raises ValueError (msgspec.ValidationError) naming the bad field."""
        return msgspec.json.decode(data, type=cls)


@dataclass(frozen=True)
class HealthReport:
    """GET /healthz: healthy when the service runs, the broker is connected and no configured device is
    OFFLINE; `reasons` says what is wrong otherwise."""

    status: str = "unavailable"
    running: bool = False
    broker_connected: bool = False
    devices: dict[str, DeviceStatus] = field(default_factory=dict)
    reasons: tuple[str, ...] = ()

    @property
    def healthy(self) -> bool:
        return self.status == "ok"

    def to_json(self) -> bytes:
        return _ENCODER.encode(self)


_SEVERITY_RANK = {"critical": 2, "warning": 1}


def attention_mark(status: str, alarm_severity: str | None, alarm_state: str | None) -> str | None:
    """Why an arm wants a look, in a few words, or None: its status when not ONLINE, and its worst alarm's
    severity, upper case while no one has acknowledged it (`OFFLINE`, `CRITICAL`, `STALE, warning ack`)."""
    parts = [] if status == DeviceStatus.ONLINE else [str(status)]
    if alarm_severity:
        acknowledged = alarm_state == "ACKNOWLEDGED"
        parts.append(f"{alarm_severity} ack" if acknowledged else alarm_severity.upper())
    return ", ".join(parts) or None


def device_attention(device: DeviceState) -> str | None:
    """`attention_mark` of one arm of a state: its worst servo alarm, an unacknowledged one before an
    acknowledged one of the same severity (the Fleet page's order)."""
    worst: tuple[int, int, str, str | None] | None = None
    for servo in (device.servos or {}).values():
        if servo.alarm_severity:
            key = (
                _SEVERITY_RANK.get(servo.alarm_severity, 0),
                int(servo.alarm_state != "ACKNOWLEDGED"),
                servo.alarm_severity,
                servo.alarm_state,
            )
            worst = key if worst is None or key[:2] > worst[:2] else worst
    severity, state = (worst[2], worst[3]) if worst else (None, None)
    return attention_mark(str(device.health.status), severity, state)
