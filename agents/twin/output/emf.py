"""CloudWatch Embedded Metric Format (EMF): a handful of fleet metrics as JSON lines for the CloudWatch agent.

The agent appends one EMF document per line to a file; the CloudWatch agent on the instance ships the file
to a log group, and CloudWatch Logs extracts the metrics from each line (no PutMetricData call, no AWS
credentials in the twin agent). Format: the CloudWatch user guide's "Specification: Embedded metric format"
(a root object with `_aws.Timestamp` in epoch ms and `_aws.CloudWatchMetrics` directives naming the
root-level members that hold each metric and dimension value). tests/test_emf.py validates every line
against that specification.

Metrics stay low-cardinality on purpose: every distinct dimension value is a billed custom metric, so the
only dimensions are the agent's name and, for the alarm counts, the severity. Per-device and per-joint
figures live in /metrics (Prometheus) on the instance, not in CloudWatch.
"""

from __future__ import annotations

import json
import logging
import math
import os
import struct
import threading
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.core.throttle import Throttle
from twin.output.sinks import SinkStats

log = logging.getLogger(__name__)

NAMESPACE = "SO101Twin"
# Where the instance's agent writes, and what the CloudWatch agent follows (userdata/bootstrap.sh).
DEFAULT_EMF_FILE = "/var/log/so101-twin/emf.log"
AGENT_DIMENSION = "Agent"
SEVERITY_DIMENSION = "Severity"
# The specification's limits (one directive may define at most 100 metrics, a dimension set at most 30 keys,
# a dimension value at most 1024 characters; a log event is at most 1 MB).
MAX_METRICS_PER_DIRECTIVE = 100
MAX_DIMENSION_VALUE_CHARS = 1024
MAX_EVENT_BYTES = 1024 * 1024
# CloudWatch's unit names (MetricDatum); only the ones used here.
UNITS = frozenset({"Count", "Count/Second", "Percent", "Milliseconds", "Seconds", "None"})
# What was lost, per interval (counts) and how far history lags (a gauge): each has a stack alarm, but for
# HistoryCommitFailures, whose alarm reads HISTORY_COMMITS_FAILING (stacks/monitoring.py, whose names
# tests/infra/test_monitoring.py checks against these).
MESSAGES_DROPPED = "MessagesDropped"  # dropped before they were decoded (a queue full, a worker lost)
SINK_DROPS = "SinkDrops"  # samples a sink's queue dropped (it could not keep up)
WORKER_RESTARTS = "WorkerRestarts"  # worker processes that died and were started again
HISTORY_ROWS_DROPPED = "HistoryRowsDropped"  # history rows dropped: the write buffer was full (an outage)
HISTORY_COMMIT_FAILURES = "HistoryCommitFailures"  # history commits that failed (retried)
HISTORY_LAG = "HistoryLagSeconds"  # how long the oldest unwritten history row has waited
# 1 while history's last commit failed, 0 once one works (a gauge, a stack alarm): in an outage the writer
# backs off to a commit a minute or rarer, so HistoryCommitFailures leaves minutes at 0 and cannot page.
HISTORY_COMMITS_FAILING = "HistoryCommitsFailing"
SUBSCRIPTIONS_REFUSED = "SubscriptionsRefused"  # topic filters the broker refuses now (an IAM policy)
# Servo alarm e-mails the host could not publish to the alarm topic (attempts that failed; retried).
ALERT_PUBLISH_FAILURES = "AlertPublishFailures"
# The broker connections down now (a stack alarm): every arm then reads OFFLINE, which is not paged, and the
# loss figures count only arms that are not OFFLINE, so without it a host cut off from IoT Core pages no one.
BROKER_DISCONNECTED = "BrokerDisconnected"
LOSS_PERCENT = "LossPercent"  # the share of the arms' expected messages that did not arrive (a stack alarm)
# The share of its messages the arm losing most lost over its recent window (a stack alarm): LossPercent
# averages the arms, so one arm's loss shows there as a fraction of it.
WORST_ARM_LOSS_PERCENT = "WorstArmLossPercent"
# The highest internal latency p99 of the arms (receive to twin updated, over each arm's health window): how
# far behind its messages the agent is, which a stack alarm watches (arms' statuses are read where it stands).
INTERNAL_LATENCY_P99 = "InternalLatencyP99"
# Messages refused because the agent already tracked telemetry.max_devices arms (a stack alarm): arms that
# publish and are kept out, which no other figure tells from garbage.
DEVICE_LIMIT_REFUSALS = "DeviceLimitRefusals"
# The agent's own documents that could not be published, told in the next one written: the intervals
# CloudWatch got nothing for, which a heartbeat gap alone does not count. Mostly writes a full disk refused,
# but any error in publish_once counts (sampling the state, a value EMF cannot hold): the name says what a
# person finds, a document not written. Kept over a crash or a restart in a small file (UnsentCount).
EMF_WRITE_FAILURES = "EmfWriteFailures"
LOSS_METRICS: tuple[str, ...] = (
    MESSAGES_DROPPED,
    SINK_DROPS,
    WORKER_RESTARTS,
    HISTORY_ROWS_DROPPED,
    HISTORY_COMMIT_FAILURES,
    HISTORY_LAG,
)


@dataclass(frozen=True, slots=True)
class Metric:
    name: str
    value: float
    unit: str = "None"


def emf_document(
    metrics: Sequence[Metric],
    dimensions: Mapping[str, str],
    timestamp_ms: int,
    namespace: str = NAMESPACE,
) -> dict[str, Any]:
    """One EMF document: every metric under one dimension set. Raises ValueError on what the spec forbids."""
    if not metrics:
        raise ValueError("an EMF document needs at least one metric")
    if len(metrics) > MAX_METRICS_PER_DIRECTIVE:
        raise ValueError(f"{len(metrics)} metrics in one document; EMF allows {MAX_METRICS_PER_DIRECTIVE}")
    doc: dict[str, Any] = {}
    for key, value in dimensions.items():
        if not isinstance(value, str) or not value or len(value) > MAX_DIMENSION_VALUE_CHARS:
            raise ValueError(
                f"dimension {key}={value!r} must be a non-empty string of at most "
                f"{MAX_DIMENSION_VALUE_CHARS} characters"
            )
        doc[key] = value
    definitions = []
    for metric in metrics:
        if metric.unit not in UNITS:
            raise ValueError(f"metric {metric.name}: unit {metric.unit!r} is not one of {sorted(UNITS)}")
        if metric.name in doc or metric.name == "_aws":
            raise ValueError(f"metric name {metric.name!r} collides with another member of the document")
        if not math.isfinite(metric.value):
            raise ValueError(f"metric {metric.name} = {metric.value}: EMF values must be finite numbers")
        doc[metric.name] = metric.value
        definitions.append({"Name": metric.name, "Unit": metric.unit})
    doc["_aws"] = {
        "Timestamp": int(timestamp_ms),
        "CloudWatchMetrics": [
            {"Namespace": namespace, "Dimensions": [list(dimensions)], "Metrics": definitions}
        ],
    }
    return doc


@dataclass(frozen=True, slots=True)
class FleetMetrics:
    """The agent's CloudWatch figures for one publishing interval (docs/servo-health.md lists each)."""

    messages_per_s: float  # valid messages decoded per second over the interval, all devices
    rejects: int  # messages rejected by the decoder during the interval
    # Estimated share of expected messages that never arrived (see the service); None: no arm's loss measured
    # (every arm OFFLINE, or no rate known).
    loss_percent: float | None
    devices_online: int
    devices_stale: int
    devices_offline: int
    internal_latency_p99_ms: float | None  # receive -> twin updated; None when nothing was applied
    active_alarms: Mapping[str, int]  # severity -> alarms whose condition is present
    # Losses during the interval (LOSS_METRICS); the history figures are None while history is off.
    messages_dropped: int = 0
    sink_drops: int = 0
    worker_restarts: int = 0
    # Topic filters the broker refuses at the end of the interval: their telemetry does not arrive.
    subscriptions_refused: int = 0
    history_rows_dropped: int | None = None
    history_commit_failures: int | None = None
    history_lag_s: float | None = None
    history_commits_failing: int = 0  # HISTORY_COMMITS_FAILING: 1 while the last commit failed
    worst_arm_loss_percent: float | None = 0.0  # WORST_ARM_LOSS_PERCENT; None: every arm OFFLINE
    broker_disconnected: int = 0  # BROKER_DISCONNECTED: connections down at the end of the interval
    device_limit_refusals: int = 0  # DEVICE_LIMIT_REFUSALS during the interval
    alert_publish_failures: int = 0  # ALERT_PUBLISH_FAILURES during the interval
    emf_write_failures: int = 0  # EMF_WRITE_FAILURES since the last document written


def fleet_documents(
    fleet: FleetMetrics, agent: str, timestamp_ms: int, namespace: str = NAMESPACE
) -> list[dict[str, Any]]:
    """The interval's EMF documents: one for the fleet figures, one per alarm severity."""
    metrics = [
        # A heartbeat: the stack's "agent silent" alarm fires when these stop arriving.
        Metric("AgentUp", 1, "Count"),
        Metric("MessagesPerSecond", fleet.messages_per_s, "Count/Second"),
        Metric("Rejects", fleet.rejects, "Count"),
    ]
    # Not measured is left out, not 0 %: the dashboard's loss graph has a gap there, not an all-clear beside a
    # fleet all OFFLINE, and MessagesLost and ArmLosingMessages take a minute without it as not breaching.
    if fleet.loss_percent is not None:
        metrics.append(Metric(LOSS_PERCENT, fleet.loss_percent, "Percent"))
    if fleet.worst_arm_loss_percent is not None:
        metrics.append(Metric(WORST_ARM_LOSS_PERCENT, fleet.worst_arm_loss_percent, "Percent"))
    metrics += [
        Metric("DevicesOnline", fleet.devices_online, "Count"),
        Metric("DevicesStale", fleet.devices_stale, "Count"),
        Metric("DevicesOffline", fleet.devices_offline, "Count"),
    ]
    if fleet.internal_latency_p99_ms is not None:
        metrics.append(Metric(INTERNAL_LATENCY_P99, fleet.internal_latency_p99_ms, "Milliseconds"))
    metrics += [
        Metric(MESSAGES_DROPPED, fleet.messages_dropped, "Count"),
        Metric(SINK_DROPS, fleet.sink_drops, "Count"),
        Metric(WORKER_RESTARTS, fleet.worker_restarts, "Count"),
        Metric(SUBSCRIPTIONS_REFUSED, fleet.subscriptions_refused, "Count"),
        Metric(BROKER_DISCONNECTED, fleet.broker_disconnected, "Count"),
        Metric(DEVICE_LIMIT_REFUSALS, fleet.device_limit_refusals, "Count"),
        Metric(ALERT_PUBLISH_FAILURES, fleet.alert_publish_failures, "Count"),
        Metric(EMF_WRITE_FAILURES, fleet.emf_write_failures, "Count"),
    ]
    if fleet.history_lag_s is not None:
        metrics += [
            Metric(HISTORY_ROWS_DROPPED, fleet.history_rows_dropped or 0, "Count"),
            Metric(HISTORY_COMMIT_FAILURES, fleet.history_commit_failures or 0, "Count"),
            Metric(HISTORY_LAG, fleet.history_lag_s, "Seconds"),
            Metric(HISTORY_COMMITS_FAILING, fleet.history_commits_failing, "Count"),
        ]
    docs = [emf_document(metrics, {AGENT_DIMENSION: agent}, timestamp_ms, namespace)]
    for severity, count in sorted(fleet.active_alarms.items()):
        docs.append(
            emf_document(
                [Metric("ActiveAlarms", count, "Count")],
                {AGENT_DIMENSION: agent, SEVERITY_DIMENSION: severity},
                timestamp_ms,
                namespace,
            )
        )
    return docs


class EmfFileWriter:
    """Appends EMF documents as JSON lines to a file the CloudWatch agent follows.

    Bounded: when the file passes `max_bytes` it is renamed to `<name>.1` (replacing the previous one) and a
    new file begins, which the CloudWatch agent follows as a rotation. Thread-safe; every write is flushed so
    the CloudWatch agent sees whole lines.
    """

    def __init__(self, path: str | Path, *, max_bytes: int = 10 * 1024 * 1024) -> None:
        if max_bytes < MAX_EVENT_BYTES:
            raise ValueError(
                f"max_bytes {max_bytes} must be at least one EMF event ({MAX_EVENT_BYTES} bytes)"
            )
        self.path = Path(path)
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        self.lines_written = 0
        self.rotations = 0
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(
                exc.errno,
                f"cannot create the EMF directory {self.path.parent} ({exc.strerror}); set [cloudwatch] "
                "emf_file to a writable path, or leave it empty to publish no CloudWatch metrics",
            ) from exc

    def write(self, documents: Sequence[Mapping[str, Any]]) -> None:
        lines = []
        for doc in documents:
            line = json.dumps(doc, separators=(",", ":"), allow_nan=False)
            if len(line.encode()) > MAX_EVENT_BYTES:
                raise ValueError(
                    f"an EMF line of {len(line)} bytes is over the {MAX_EVENT_BYTES}-byte event limit"
                )
            lines.append(line + "\n")
        data = "".join(lines)
        with self._lock:
            try:
                size = self.path.stat().st_size
            except FileNotFoundError:
                size = 0
            if size and size + len(data) > self.max_bytes:
                os.replace(self.path, self.path.with_name(self.path.name + ".1"))
                self.rotations += 1
            elif size and _ends_cut_short(self.path):
                # A write the disk could not take (full) left part of a line: without a line end the next
                # interval's first document would join it and be lost with it.
                data = "\n" + data
            with self.path.open("a", encoding="utf-8") as fh:
                fh.write(data)
                fh.flush()
            self.lines_written += len(lines)


def _ends_cut_short(path: Path) -> bool:
    with path.open("rb") as fh:
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) != b"\n"


def unsent_path(emf_file: str | Path) -> Path:
    """Where the failed publishes no document told are kept: beside the EMF file, hidden, so the CloudWatch
    agent (which follows the EMF file by its name) never ships it as metrics."""
    path = Path(emf_file)
    return path.with_name(f".{path.name}.unsent")


class UnsentCount:
    """The count of the agent's failed publishes that no document told yet, in a small file that survives a
    crash, a kill or a reboot (docs/servo-health.md, "metrics unwritten").

    It matters most while the disk is full, when a file written anew (a temporary file renamed over the old
    one) cannot be: so the file has a fixed size, its blocks written once when it is made (at the start),
    and each save overwrites them in place, which a filesystem that writes in place (ext4 and XFS, the host's
    root volume) takes on a full disk. A copy-on-write one (btrfs) may refuse it; the save is then logged
    and the count stays in memory. Two slots, each a sequence number, the count and their CRC-32, written
    in turn and flushed to disk: a save a crash cut short leaves the other slot whole.
    """

    def __init__(self, path: str | Path, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        self._seq = 0
        self._lock = threading.Lock()
        self._error_lines = Throttle(UNSENT_TELL_EVERY_S, clock=clock)

    def load(self) -> int:
        """The count the file keeps (0 without a file, or with neither slot whole), making the file if it is
        missing or short, so the saves after it have their blocks."""
        with self._lock:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                self._failed("opened or created", exc)
                return 0
            data = b""
            try:
                data = os.pread(fd, UNSENT_FILE_BYTES, 0)
                if len(data) < UNSENT_FILE_BYTES:
                    os.pwrite(fd, data.ljust(UNSENT_FILE_BYTES, b"\0"), 0)
                    os.fsync(fd)
            except OSError as exc:
                self._failed("made", exc)
            finally:
                os.close(fd)
            slots = [_unsent_slot(data[i : i + _SLOT.size]) for i in (0, _UNSENT_SLOT_BYTES)]
            self._seq, count = max((slot for slot in slots if slot is not None), default=(0, 0))
            return count

    def save(self, count: int) -> bool:
        """Keep `count` in the slot the last save did not write; False (logged) when it could not be."""
        with self._lock:
            seq = self._seq + 1
            record = _SLOT.pack(seq, count, zlib.crc32(_SLOT_HEAD.pack(seq, count)))
            try:
                # No O_CREAT: a file that is gone is made again only by load, with its blocks.
                fd = os.open(self.path, os.O_WRONLY | os.O_CLOEXEC)
                try:
                    os.pwrite(fd, record, (seq % 2) * _UNSENT_SLOT_BYTES)
                    os.fsync(fd)
                finally:
                    os.close(fd)
            except OSError as exc:
                self._failed("written", exc)
                return False
            self._seq = seq
            return True

    def _failed(self, what: str, exc: OSError) -> None:
        since = self._error_lines.due()
        if since is not None:
            # The fix, as a person reads it in the log: a file not made is mostly a directory the agent's
            # user cannot write, or a disk already full at the start; a save refused, a disk that filled.
            log.error(
                "the count of unwritten CloudWatch metrics documents could not be %s in %s (%s), "
                "%d failure(s) since the last such line: it is kept in memory only, and a crash before a "
                "document is written loses it; check that the agent's user can write %s and that the disk "
                "has room (df -h %s)",
                what,
                self.path,
                exc,
                since,
                self.path.parent,
                self.path.parent,
            )


# A file that cannot be written fails at each failed publish: told at once, then at most once per this, each
# line with how many failed since the one before.
UNSENT_TELL_EVERY_S = 600.0
# The file: two slots of 32 bytes, each (sequence number, count, CRC-32 of the two) little-endian.
_SLOT_HEAD = struct.Struct("<QQ")
_SLOT = struct.Struct("<QQI")
_UNSENT_SLOT_BYTES = 32
UNSENT_FILE_BYTES = 2 * _UNSENT_SLOT_BYTES


def _unsent_slot(data: bytes) -> tuple[int, int] | None:
    """A slot's (sequence number, count), or None if it is not whole (never written, or cut short)."""
    if len(data) < _SLOT.size:
        return None
    seq, count, crc = _SLOT.unpack(data)
    if seq == 0 or crc != zlib.crc32(_SLOT_HEAD.pack(seq, count)):
        return None
    return seq, count


@dataclass(frozen=True, slots=True)
class FleetTotals:
    """What the service reports at one moment: running totals plus the gauges of that moment."""

    decoded: int  # valid messages since start, all devices
    rejected: int  # rejected messages since start, all devices
    devices_online: int
    devices_stale: int
    devices_offline: int
    # None: no arm's loss measured, every arm OFFLINE or no rate of theirs known (left out of the metrics).
    loss_percent: float | None
    internal_latency_p99_ms: float | None
    active_alarms: Mapping[str, int]
    # Running totals of what was lost (a restarted worker's count starts again: see EmfPublisher).
    messages_dropped: int = 0
    sink_drops: int = 0
    worker_restarts: int = 0
    subscriptions_refused: int = 0  # now, not a running total
    # History's totals and its lag now; None while history is off.
    history_rows_dropped: int | None = None
    history_commit_failures: int | None = None
    history_lag_s: float | None = None
    history_commits_failing: int = 0  # a gauge: HISTORY_COMMITS_FAILING
    worst_arm_loss_percent: float | None = 0.0  # a gauge: WORST_ARM_LOSS_PERCENT; None: every arm OFFLINE
    device_limit_refusals: int = 0  # a running total: DEVICE_LIMIT_REFUSALS
    broker_disconnected: int = 0  # now, not a running total: BROKER_DISCONNECTED
    alert_publish_failures: int = 0  # a running total: ALERT_PUBLISH_FAILURES


def increase(now: int | None, before: int | None) -> int:
    """How much a running total grew since `before`; a total that went down was started again (a worker
    restarted with its sinks), so all of it is new, as Prometheus treats a counter reset."""
    if now is None:
        return 0
    if before is None or now < before:
        return now
    return now - before


def _interval_metrics(
    totals: FleetTotals, before: FleetTotals | None, span: float, write_failures: int
) -> FleetMetrics:
    """One interval's figures: `totals` less `before` (the last written), over `span` seconds."""
    decoded = totals.decoded - (before.decoded if before else 0)
    rejected = totals.rejected - (before.rejected if before else 0)
    history = totals.history_lag_s is not None

    def grew(name: str) -> int:
        return increase(getattr(totals, name), getattr(before, name) if before else None)

    return FleetMetrics(
        messages_per_s=max(0, decoded) / span,
        rejects=max(0, rejected),
        loss_percent=totals.loss_percent,
        worst_arm_loss_percent=totals.worst_arm_loss_percent,
        devices_online=totals.devices_online,
        devices_stale=totals.devices_stale,
        devices_offline=totals.devices_offline,
        internal_latency_p99_ms=totals.internal_latency_p99_ms,
        active_alarms=totals.active_alarms,
        messages_dropped=grew("messages_dropped"),
        sink_drops=grew("sink_drops"),
        worker_restarts=grew("worker_restarts"),
        subscriptions_refused=totals.subscriptions_refused,
        broker_disconnected=totals.broker_disconnected,
        device_limit_refusals=grew("device_limit_refusals"),
        alert_publish_failures=grew("alert_publish_failures"),
        history_rows_dropped=grew("history_rows_dropped") if history else None,
        history_commit_failures=grew("history_commit_failures") if history else None,
        history_lag_s=totals.history_lag_s,
        history_commits_failing=totals.history_commits_failing,
        emf_write_failures=write_failures,
    )


# A wall clock that keeps moving (frozen, fast, flapping) is told once, then once per this with a count.
CLOCK_STEP_TELL_EVERY_S = 600.0


def next_slot(scheduled: float, now: float, interval_s: float) -> float:
    """The first time after `now` on the grid `scheduled` + k * `interval_s` (k >= 1). A publish that took
    longer than the interval (asking slow workers for their state) skips the slots it missed rather than
    writing them at once, and a slow one never pushes the later ones back: one document per interval, on
    the same second of each minute, so no minute the stack's alarms read goes without one."""
    slot = scheduled + interval_s
    if slot <= now:
        slot += (math.floor((now - slot) / interval_s) + 1) * interval_s
    return slot


def first_slot(mono: float, wall: float, interval_s: float) -> float:
    """The monotonic time of the first publish: an interval or more from now, where the wall clock reads the
    middle of a minute (30 s past it; for a shorter interval, half an interval past a grid line from the
    minute's start). A slot the start's chance put a few ms from a minute boundary could land, after some
    drift, in the next minute or the one before, leaving a minute empty and breaking its 5-of-5 alarms."""
    phase = min(interval_s / 2.0, 30.0)
    return mono + interval_s + (phase - (wall + interval_s)) % interval_s


def clock_step_tolerance(interval_s: float) -> float:
    """How far the wall clock may move against the monotonic one before the grid is lined up with it again
    (a step: chrony setting the clock at first boot, a person, a resumed suspend). NTP's slewing changes
    both clocks alike, so their difference moves only by such steps, and a move up to this is read noise. A
    leap second is no such step: exactly 1 s, it lies on this limit (intervals of 4 s and more), so read
    noise decides whether it moves the grid, and either way a slot stays within 1 s of its place. A slot lies
    half an interval from a minute's boundaries: one left in place by a move up to a quarter interval still
    lies a quarter interval or more from them."""
    return min(1.0, interval_s / 4.0)


def realigned_slot(slot: float, last: float, now: float, step: float, interval_s: float) -> float:
    """The next slot, due at monotonic time `slot` after the one at `last`, once the wall clock was stepped
    by `step` seconds: moved to where the wall clock now reads what it read there before, the next place in
    its minutes after the last document's, so no minute gets two. If a forward step passed it, the first
    such place after `now` (the minutes the clock jumped over get none); a backward step of more than an
    interval would put it more than two intervals after `last`, so then the place one to two intervals
    after `last` (its minute had a document before the step, and gets a second)."""
    slot -= step
    latest = last + 2.0 * interval_s
    if slot > latest:
        slot -= math.ceil((slot - latest) / interval_s) * interval_s
    return slot if slot > now else next_slot(slot, now, interval_s)


class EmfPublisher:
    """Every `interval_s`, turns the service's totals into one interval's FleetMetrics and writes them.

    Rates and counts are differences between successive totals, over the time between them (monotonic
    clock); the EMF timestamp is the wall clock. Runs on its own thread; a failed publish (a write, or the
    sample or encoding before it) is logged and counted (`failed`), never raised, so CloudWatch trouble cannot
    stop the twin. The count is in /state and /metrics (`sink_stats`) and in the next document written
    (EMF_WRITE_FAILURES). With `unsent`, the count no document told yet is kept there at each failure and
    read back at the start, so a crash, a kill or a stop that cannot write its last document loses none of
    it: the next run's first document written tells it.
    """

    def __init__(
        self,
        writer: EmfFileWriter,
        agent: str,
        sample: Callable[[], FleetTotals],
        *,
        interval_s: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        wait: Callable[[float], bool] | None = None,
        unsent: UnsentCount | None = None,
    ) -> None:
        """`wait(seconds)` sleeps until a slot and returns True once stop() was called (tests pass one that
        moves their `clock` instead). `unsent` keeps the failed publishes not told yet over a crash (read
        here: the run before's are told in this run's first document written)."""
        if not interval_s > 0:
            raise ValueError(f"the EMF interval must be positive seconds, got {interval_s}")
        self.writer = writer
        self.agent = agent
        self.interval_s = interval_s
        self._sample = sample
        self._clock = clock
        self._wall = wall
        self._last: tuple[float, FleetTotals] | None = None
        self._started = clock()
        self._stop = threading.Event()
        self._wait = wait or self._stop.wait
        self._thread: threading.Thread | None = None
        self.published = 0
        self.errors = 0
        self.last_error = ""
        self._errors_told = 0  # `errors` as the last document written told them
        self._unsent = unsent
        # The run before's failed publishes that no document told (they count as this run's first).
        self._carried = unsent.load() if unsent is not None else 0
        if self._carried:
            log.warning(
                "%d CloudWatch metrics document(s) of the agent's run before could not be written and were "
                "not told yet (%s): the first document written tells them as EmfWriteFailures",
                self._carried,
                unsent.path if unsent is not None else "",
            )
        self.clock_steps = 0  # wall clock steps seen (clock_step_tolerance), each counted
        # How far the offset the grid was first lined up with may be off: half the stall of a first clock
        # read that never got a clean one (_first_clock_offset); 0 once a clean read came.
        self._loose_s = 0.0
        self._step_lines = Throttle(CLOCK_STEP_TELL_EVERY_S, clock=clock)

    def publish_once(self, totals: FleetTotals | None = None) -> FleetMetrics:
        """Sample (or take `totals`: the agent's last document, at its stop), write this interval's documents,
        return the figures (the first call's totals are taken as rising from zero, since tracking began)."""
        now = self._clock()
        # The wall clock as the publish begins, not at the end of a sample that can wait seconds on slow
        # workers: a slot lies mid-minute (first_slot), so CloudWatch files the document under its minute.
        wall_ms = round(self._wall() * 1000)
        if totals is None:
            totals = self._sample()
        if self._last is None:
            # The first slot lies one to two intervals after the start (first_slot): its totals rose over
            # all of that time, which one interval would overstate up to twice.
            since, before = min(now - self.interval_s, self._started), None
        else:
            since, before = self._last
        span = max(now - since, 1e-9)
        errors = self.errors
        untold = self._carried + errors - self._errors_told
        fleet = _interval_metrics(totals, before, span, untold)
        counts, *by_severity = fleet_documents(fleet, self.agent, wall_ms)
        self.writer.write([counts])
        # Only once the counts are written, and before the rest: an interval whose counts a full disk refused
        # is counted in the next one (its losses still reach the alarms), and one whose counts are in the
        # file is not counted again if the severity lines after them fail (a review saw 7 drops sent as 14).
        self._last = (now, totals)
        self._errors_told = errors
        if untold:
            # A crash before this save tells them again in the next run: twice is better than never.
            self._carried = 0
            self._keep_untold()
        if by_severity:
            self.writer.write(by_severity)
        self.published += 1
        return fleet

    def failed(self, exc: BaseException) -> None:
        """Count a publish that raised `exc` (the caller logs it)."""
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        self._keep_untold()

    def _keep_untold(self) -> None:
        """Save the count no document told yet, so a crash or a kill while the disk stays full loses none."""
        if self._unsent is not None:
            self._unsent.save(self._carried + self.errors - self._errors_told)

    def sink_stats(self) -> SinkStats:
        """The EMF file as an output in /state `agent.sinks` and /metrics (`emf`): its failed writes were only
        logged, so metrics lost to a full disk showed nowhere a person looks."""
        return SinkStats(name="emf", delivered=self.published, errors=self.errors, last_error=self.last_error)

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self.run, name="twin-emf", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def run(self) -> None:
        """Publish at every slot of a fixed grid, `interval_s` apart on the monotonic clock from a first slot
        lined up with the wall clock's minutes (first_slot, next_slot), and lined up again after a step of the
        wall clock (realigned_slot), until stop(); start() runs this on its own thread. A slot is moved once
        at most, steps seen after that move the next one: a wall clock that keeps moving (frozen, fast,
        flapping) moved every slot on before it came, and the AgentUp heartbeat stopped. So a document goes
        out at most two intervals (monotonic) after the last slot, whatever the wall clock does."""
        mono, offset = self._first_clock_offset()
        slot = first_slot(mono, mono + offset, self.interval_s)
        last = slot - self.interval_s  # where the grid had its last slot, as if before the first
        # The wait is cut into short ones so a step is seen before the slot it moves, not only after it.
        poll_s = clock_step_tolerance(self.interval_s)
        moved, pending = False, 0.0  # the slot was moved already; the steps seen since, for the next one
        while True:
            if self._wait(max(0.0, min(slot - self._clock(), poll_s))):
                return
            now, step, offset = self._wall_step(offset)
            if step and not moved:
                slot, moved = realigned_slot(slot, last, now, step, self.interval_s), True
                continue
            pending += step
            if self._clock() < slot:  # a wake before the slot waits again; a late one publishes at once
                continue
            try:
                self.publish_once()
            except Exception as exc:
                self.failed(exc)
                log.exception("publishing CloudWatch metrics to %s failed", self.writer.path)
            last, slot = slot, next_slot(slot, self._clock(), self.interval_s)
            if moved := bool(pending):
                slot = realigned_slot(slot, last, self._clock(), pending, self.interval_s)
            pending = 0.0

    def _first_clock_offset(self) -> tuple[float, float]:
        """The monotonic time and the wall clock minus it, to line the first slot up with. Each try reads the
        wall clock between two monotonic reads and sets it against their middle (_clock_read); a try whose
        two reads lie over a quarter of the step tolerance apart (the thread stalled) is tried again, and
        after three the one with the shortest stall is taken. Its offset is off by half that stall at most
        (`_loose_s`, until a clean read): a stall over twice clock_step_tolerance on every try then moves the
        grid once, later, but is no step of the clock, so it is not counted or told (_wall_step)."""
        reads: list[tuple[float, float, float]] = []
        for _ in range(3):
            reads.append(self._clock_read())
            if reads[-1][0] <= clock_step_tolerance(self.interval_s) / 4.0:
                break
        gap, mono, offset = min(reads)
        self._loose_s = gap / 2.0 if gap > clock_step_tolerance(self.interval_s) / 4.0 else 0.0
        return mono, offset

    def _clock_offset(self) -> tuple[float, float | None]:
        """The monotonic time and the wall clock minus it (_clock_read). The difference is None if the two
        monotonic reads lie over a quarter of the step tolerance apart (the thread stalled between the
        reads): so loose a reading, taken for a step, would move the grid and warn twice."""
        gap, after, offset = self._clock_read()
        return after, (None if gap > clock_step_tolerance(self.interval_s) / 4.0 else offset)

    def _clock_read(self) -> tuple[float, float, float]:
        """How far apart two monotonic reads lie, the second, and the wall clock read between them minus
        their middle: a stall anywhere in the reads moves that offset by half the gap at most."""
        before = self._clock()
        wall = self._wall()
        after = self._clock()
        return after - before, after, wall - (before + after) / 2.0

    def _wall_step(self, offset: float) -> tuple[float, float, float]:
        """The monotonic time, how far the wall clock was stepped since `offset` (wall minus monotonic) was
        read (0.0 if by no more than clock_step_tolerance), and the offset the grid is lined up with then.
        Every step is counted; the warning is throttled, since a flapping clock steps every few seconds. The
        first clean read after a first read that never got one moves the grid like a step, but counts and
        tells only a move larger than that read's own error could make (a review: three stalls over 2 s at
        the start counted a step of a clock nobody touched)."""
        now, read = self._clock_offset()
        if read is None:
            return now, 0.0, offset
        loose, self._loose_s = self._loose_s, 0.0
        tolerance = clock_step_tolerance(self.interval_s)
        if abs(read - offset) <= tolerance:
            return now, 0.0, offset
        if abs(read - offset) <= tolerance + loose:
            return now, read - offset, read
        self.clock_steps += 1
        steps = self._step_lines.due(now=now)
        if steps is not None:
            log.warning(
                "the wall clock moved %+.1f s against the monotonic one (stepped by NTP or by hand; %d "
                "step(s) since the last such line); the next CloudWatch metrics document is moved to the "
                "middle of a minute after the last one. If this repeats, the host's time sync is wrong: "
                "check `chronyc tracking`",
                read - offset,
                steps,
            )
        return now, read - offset, read
