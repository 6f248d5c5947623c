"""The fleet's shares: which mirror mirrors which device, the mirrors in worker processes, and the merge.

The agent (service.agent) hands every message to one of its shards, and each shard runs one mirror
(service.mirror: decode, loss, twin, health, alarms, sinks) over its share of the devices. With one shard
the mirror runs in the agent's own process (`LocalShard`, in service.mirror); `twin run --workers N` runs N
shards, each a worker process (`WorkerShard`, here):

    agent: connection pool --CRT threads: feed()--> device from the topic, its shard (`WorkerPlan.worker_of`)
      --> the shard's bounded queue --sender thread: batches over a pipe (transport.pipe)-->
    worker process k: a Mirror reading that pipe on its own worker thread, answering the control pipe

Each device belongs to exactly one shard for as long as the agent runs: a listed fleet is dealt out in list
order (balanced, deterministic), the whole fleet (`*`) by a stable hash of the device id (CRC-32, the same in
every process and on every run). A device's messages travel one queue and one pipe in order, so the order they
arrived in is kept. The agent's side does no per-message work beyond the routing: the connection pool's no-op
ceiling (docs/performance.md) is what it costs. Admission (`telemetry.max_devices`) is the mirrors' own, after
decoding, from one budget every process shares (service.admission).

The agent asks the shards for their figures with typed requests (`ReportRequest`, `AlarmsRequest`,
`AckRequest`); a worker answers over its control pipe, a local shard at once, and `merge_reports` makes one
state of the answers, whatever the number of shards.

A worker that dies (a crash in a native library, say) is started again from its last checkpoint (the agent
takes one every CHECKPOINT_EVERY_S: counters, loss estimates, alarms, poses), is sent again every message the
checkpoint does not count, then what arrived while it was down (`WorkerShard`); its arms show as `restarting`
meanwhile and never leave `/state`. Messages are counted as dropped (`overwritten`) against their devices only
when the queue or the messages kept for a restart overflowed. Workers ignore
SIGINT and SIGTERM: the agent stops them in order (the rest of the queue, then an end marker), so each one
flushes its sinks (USD recording, history) before it exits. A worker whose parent vanished sees its pipe close
and exits too.

Light on purpose: the agent imports it with worker processes too, and must not load MuJoCo (only the worker
processes do, in `worker_main`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import os
import pickle
import signal
import threading
import time
import zlib
from collections import Counter, deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from multiprocessing.connection import Connection
from multiprocessing.context import ForkServerContext, ForkServerProcess
from typing import TYPE_CHECKING, Protocol

from twin.core.alarms import (
    AlarmCounters,
    AlarmNotFound,
    AlarmRecord,
    AlarmState,
    AlarmView,
    IdleRow,
    NothingToAcknowledge,
    record_view,
    what_to_do,
)
from twin.core.bounded import BoundedCounter, merged_counts
from twin.core.health import HealthCheckpoint, HealthRow, HealthThresholds
from twin.core.latency import LatencyHistogram
from twin.core.loss import DeviceLoss, LossSnapshot, LossState, fleet_loss
from twin.core.units import Units
from twin.output.sinks import SinkStats
from twin.service.admission import DeviceBudget
from twin.service.config import AgentConfig, ConfigError
from twin.service.console import FleetRow, ForgetOffer
from twin.service.events import Event, FlapRow
from twin.service.logs import name_native_thread
from twin.service.state import (
    AgentInfo,
    AgentState,
    AlarmInfo,
    AlarmsSummary,
    DeviceState,
    FleetLatency,
    HistoryState,
    MailboxState,
    MirrorStatus,
    RecordingState,
    WorkerInfo,
    WorkerState,
)
from twin.transport.mailbox import MAX_OVERFLOW_KEYS, UNTRACKED_KEY, InboundQueue
from twin.transport.pipe import Message, encode_batch, messages_of, send_encoded, send_end

if TYPE_CHECKING:
    from twin.output.history_feed import HistoryLink, Resume
    from twin.service.mirror import Mirror

log = logging.getLogger(__name__)

# Per worker, the agent queues at most this many messages for its pipe (about 40 MB of payloads across the
# fleet's queues at most); beyond it the oldest are dropped and counted, as in an in-process mirror's queue.
MAX_QUEUED_PER_WORKER = 25_000
# ... and at most this many bytes of their payloads (a few large messages weigh as much as many small ones).
MAX_QUEUED_BYTES_PER_WORKER = 32 * 2**20
# The agent keeps each message it handed a worker until the worker's checkpoint counts it, at most this many
# (a few seconds of a large fleet): a worker that dies is sent them again once it runs again.
MAX_UNCONFIRMED = 50_000
# A stop report's count of the messages queued for a worker that a failed start never handed to it.
UNMIRRORED = "messages_not_mirrored"
# How often the agent takes each worker's checkpoint (its supervisor thread; service.agent).
CHECKPOINT_EVERY_S = 1.0
# One pipe write carries at most this many messages: a backlog goes over in pieces the worker can start on.
MAX_BATCH = 1000
# Above this many messages a second for one worker, its sender pauses after each hand-over (unless it had a
# full batch), so messages arriving meanwhile go over together: long enough for about BATCH_TARGET messages,
# at most MAX_SEND_PAUSE_S. Without the pause every message woke the sender and crossed the pipe alone (at
# 10,000 msg/s a worker the agent spent 26 us a message instead of 18), and the mirror's stages cost about
# 50-80 us a batch whatever its size (their timers, the lock, the numpy arrays of the servo alarms and the
# latency histograms), over 5 us a message in batches of 10. Below the rate the wake-ups cost little and
# the pause would only add latency (the 100-arm target: internal p99 <= 2 ms).
PAUSE_ABOVE_RATE = 2000.0
BATCH_TARGET = 64
MAX_SEND_PAUSE_S = 0.008
# Of the shutdown budget, a worker leaves this much to the agent (its own stop steps and the pipes).
WORKER_BUDGET_MARGIN_S = 8.0
# How long a worker may take to answer one request (a state of thousands of arms takes tens of ms).
ASK_TIMEOUT_S = 10.0
# A running worker that lets this many asks in a row go unanswered (ASK_TIMEOUT_S each: half a minute and
# more) is hung, not busy: it is killed, and started again from its checkpoint as one that died.
HUNG_AFTER_ASKS = 3
# A worker must be up within this (Python, MuJoCo and the sinks it opens, e.g. a Delta table on S3).
START_TIMEOUT_S = 120.0
# A worker that dies within this long of starting is restarted after a growing pause (1, 2, 4 ... s, at most
# MAX_RESTART_PAUSE_S) rather than at once, so a worker that cannot run does not spin.
QUICK_DEATH_S = 30.0
MAX_RESTART_PAUSE_S = 60.0


class WorkerError(RuntimeError):
    """A worker process could not start, or did not answer."""


class AskTimedOutError(WorkerError):
    """A worker's answer did not come in time (its mirror thread busy or stuck, or the process hung). What it
    was asked may still be done: the request waits in the worker until its mirror thread gets to it."""


class ForgetTimedOutError(WorkerError):
    """A forget that got no answer in time, whichever wait ran out: not known whether the arm is forgotten
    (HTTP 504 `forget_timed_out`). Its message is the one the console shows."""


class WorkerPlan:
    """Which shard mirrors which device: listed devices dealt out in list order, any other by CRC-32."""

    def __init__(self, count: int, listed: Sequence[str] = ()) -> None:
        if count < 1:
            raise ValueError(f"an agent needs at least one shard, got {count}")
        self.count = count
        self._listed = {device: i % count for i, device in enumerate(listed)}

    def worker_of(self, device: str) -> int:
        if self.count == 1:
            return 0
        listed = self._listed.get(device)
        if listed is not None:
            return listed
        return zlib.crc32(device.encode("utf-8", "surrogatepass")) % self.count

    def devices_of(self, index: int) -> tuple[str, ...]:
        """The listed devices shard `index` mirrors."""
        return tuple(device for device, worker in self._listed.items() if worker == index)


def worker_config(config: AgentConfig, plan: WorkerPlan, index: int) -> AgentConfig:
    """What the mirror of shard `index` runs with: its share of a listed fleet (so each configured device is
    reported by one mirror), and no CloudWatch file (the agent publishes the fleet's metrics)."""
    telemetry = config.telemetry
    if not telemetry.all_devices:
        telemetry = dataclasses.replace(telemetry, devices=plan.devices_of(index))
    return dataclasses.replace(
        config,
        telemetry=telemetry,
        twin=dataclasses.replace(config.twin, workers=1),
        cloudwatch=dataclasses.replace(config.cloudwatch, emf_file=""),
    )


# ------------------------------------------------------------------------------------ what a mirror reports


@dataclass(frozen=True)
class MirrorReport:
    """One mirror's part of the agent's state: its devices and rejections, its queue, worker and sinks, and
    its latency histograms (percentiles do not add up; histograms do). `merge_reports` makes the state."""

    devices: dict[str, DeviceState]
    untracked_rejected: dict[str, int]
    mailbox: MailboxState
    worker: WorkerState
    recording: RecordingState | None
    history: HistoryState | None
    sinks: tuple[SinkStats, ...]
    alarms: AlarmsSummary
    internal: LatencyHistogram
    end_to_end: LatencyHistogram


# -------------------------------------------------------------------------------------------- requests


@dataclass(frozen=True, slots=True)
class ReportRequest:
    """The mirror's `MirrorReport`."""


@dataclass(frozen=True, slots=True)
class AlarmsRequest:
    """The mirror's servo alarms, worst first; NORMAL ones only with `include_normal`."""

    include_normal: bool = False


@dataclass(frozen=True, slots=True)
class AckRequest:
    """Acknowledge one alarm of the mirror's devices; refused as AlarmNotFound or NothingToAcknowledge.
    Answered with the alarm (AlarmInfo); with `checkpoint`, with Acknowledged: the alarm and the mirror's
    checkpoint begun right after the acknowledgement, between the same two batches, a worker's restart point
    that holds it (service.agent keeps it at once)."""

    alarm_id: str
    checkpoint: bool = False


@dataclass(frozen=True, slots=True)
class Acknowledged:
    """The answer to an AckRequest that asked for a checkpoint."""

    alarm: AlarmInfo
    checkpoint: MirrorCheckpoint | None  # None: not taken in time (the next one holds the acknowledgement)


# The most alarm ids one bulk acknowledgement takes (POST /alarms/ack): one request's work under the mirror's
# lock and one answer stay small (a thousand ids: a few ms, about 100 kB of answer), however many wait.
ACK_MANY_MAX = 1000


class AckOutcome(StrEnum):
    """What became of one id of a bulk acknowledgement (AckManyRequest)."""

    ACKNOWLEDGED = "acknowledged"  # ACTIVE -> ACKNOWLEDGED, or LATCHED -> NORMAL (reset)
    NOTHING_TO_ACKNOWLEDGE = "nothing_to_acknowledge"  # already ACKNOWLEDGED, or NORMAL (cleared)
    ALARM_NOT_FOUND = "alarm_not_found"  # no alarm has this id (its arm forgotten, or a mistyped id)
    WORKER_UNAVAILABLE = "worker_unavailable"  # its worker is being started again: not asked


# What an unknown id's answer says, to one acknowledgement (404) and in a bulk one's results alike.
ALARM_NOT_FOUND_DETAIL = "no alarm has this id (its arm forgotten?); GET /alarms?all=1 lists every id"


@dataclass(frozen=True, slots=True)
class AckResult:
    """One id's outcome; `state` the alarm's state after (None when there is no such alarm), `detail` why it
    was not made. The state alone: the answer of 1,000 ids is pickled back over a worker's pipe."""

    alarm_id: str
    outcome: AckOutcome
    state: str | None = None
    detail: str = ""


@dataclass(frozen=True, slots=True)
class AckManyRequest:
    """Acknowledge several alarms of the mirror's devices in one go, each id's outcome answered rather than
    the first refusal raised: AckedMany, in the order asked. With `checkpoint`, as AckRequest's: the mirror's
    checkpoint begun right after the last of them, which holds them all."""

    alarm_ids: tuple[str, ...]
    checkpoint: bool = False


@dataclass(frozen=True, slots=True)
class AckedMany:
    """The answer to an AckManyRequest."""

    results: tuple[AckResult, ...]
    checkpoint: MirrorCheckpoint | None = None


@dataclass(frozen=True, slots=True)
class ForgetRequest:
    """Forget one OFFLINE arm of the mirror's devices (its twin, health, alarms, budget place); answered
    with ArmForgotten, refused as ArmNotFoundError or ArmNotForgettableError. With `checkpoint`, the answer
    carries the mirror's checkpoint begun right after the forget, between the same two batches: a worker's
    restart point that no longer holds the arm (service.agent keeps it at once). `reason`: why the agent
    forgot it itself (telemetry.forget_offline_after_s); empty for an operator's forget."""

    device: str
    checkpoint: bool = False
    reason: str = ""


@dataclass(frozen=True, slots=True)
class ArmForgotten:
    """What forgetting an arm removed: its status then, and its alarms by state (NORMAL ones not counted);
    the mirror's checkpoint after it when the request asked for one."""

    device: str
    status: str
    alarms_removed: dict[str, int] = field(default_factory=dict)
    checkpoint: MirrorCheckpoint | None = None


class ArmNotFoundError(KeyError):
    """No mirror tracks this arm (never heard from, or forgotten already): HTTP 404."""


class ArmNotForgettableError(ValueError):
    """The arm may not be forgotten now (`code`: ARM_NOT_OFFLINE, ARM_CONFIGURED): HTTP 409."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


ARM_NOT_OFFLINE = "arm_not_offline"
ARM_CONFIGURED = "arm_configured"


@dataclass(frozen=True, slots=True)
class EventsRequest:
    """The mirror's events after `after_id` (its own numbering), oldest first: the first EVENTS_PER_ASK of
    them (the next request asks after the last)."""

    after_id: int = 0


@dataclass(frozen=True, slots=True)
class EventsReply:
    """The answer to an EventsRequest: the events, and the time of the newest alarm event the mirror's store
    let go of before it was asked for (None: none was). The agent's store then holds no alarm raise up to
    it as complete (EventStore.alarms_lost_until): a flood faster than the agent collects, for one."""

    events: tuple[Event, ...]
    alarms_lost_until: float | None = None


@dataclass(frozen=True, slots=True)
class FleetRowsRequest:
    """The console's row of each of the mirror's devices (twin.service.console.FleetRow)."""


@dataclass(frozen=True, slots=True)
class ArmRequest:
    """One arm's state and its alarms that are not NORMAL (an ArmReply): the console's arm page, without the
    report of the whole fleet."""

    device: str


@dataclass(frozen=True, slots=True)
class ArmReply:
    """`Mirror.arm`: the arm's state (None: not tracked by this mirror), its alarms, worst first, and whether
    the mirror would forget it now (None: not tracked)."""

    state: DeviceState | None
    alarms: tuple[AlarmInfo, ...]
    forget: ForgetOffer | None = None


@dataclass(frozen=True, slots=True)
class StatusesRequest:
    """The status of each of the mirror's devices, as (device, status) pairs: what /healthz needs, without
    the report (a report of 1,000 arms takes the worker a fleet's holding torques and tool points)."""


@dataclass(frozen=True, slots=True)
class UnheardRequest:
    """The devices the mirror does not track whose every message was refused so far (UnheardArm, the most
    recent first): an arm whose edge sends what the agent refuses has no card, so the Fleet page names it."""


@dataclass(frozen=True, slots=True)
class UnheardArm:
    """One device of an UnheardRequest's answer: its refused messages, the last one's reason, and how long
    ago the last one came."""

    device: str
    rejected: int
    reason: str
    last_s: float


@dataclass(frozen=True, slots=True)
class CalibrationsRequest:
    """Each arm's own calibration from now on (service.calibrations), replacing the previous set: per device
    its source and its LeRobot file as parsed JSON (a Calibration holds a mapping proxy, which does not
    pickle), and why a newer file was refused. Answered with how many arms have one."""

    files: tuple[tuple[str, str, dict[str, dict[str, int]]], ...] = ()
    problems: tuple[tuple[str, str], ...] = ()
    # What `twin calibration` needs to reach the agent's store (calibrations.store_option), so a held arm's
    # refusal names commands that work for this agent, not the stack's store.
    store_option: str = ""
    # The refused arms the store keeps a valid calibration for, whose refusal may offer a restore.
    restorable: tuple[str, ...] = ()


# Events a mirror hands over per request (the agent asks every supervisor round).
EVENTS_PER_ASK = 5000
# ----------------------------------------------------------------------------------- checkpoints (restarts)


@dataclass(frozen=True, slots=True)
class DeviceCheckpoint:
    """What one device's mirror state must carry over a restart of its worker (its twin is rebuilt from the
    last applied pose; health windows, latencies and the alarm engine's last evaluation start again)."""

    health: HealthCheckpoint
    loss: LossState | None = None  # the loss estimator's (`DeviceLoss.from_state`)
    units: Units | None = None  # units=auto's decision, so a restarted mirror rejects none of its messages
    timestamp_ms: int | None = None  # the last applied pose
    targets_rad: dict[str, float] | None = None
    gripper_percent: float | None = None


# One device of a checkpoint as plain values (`PackedDevices`): its id, health, loss estimator (or None),
# units=auto's decision (the units' value, or None), last applied timestamp, targets and gripper percent.
DeviceRow = tuple[
    str, HealthRow, LossState | None, str | None, int | None, dict[str, float] | None, float | None
]


class PackedDevices(Mapping[str, DeviceCheckpoint]):
    """A checkpoint's devices, pickled by the worker thread as plain values (`DeviceRow`) in a few chunks,
    and unpacked only where they are read: by a restarted worker, or for `/state` while one restarts.

    The agent takes each worker's checkpoint every second, and nearly always only keeps it. Built as
    dataclasses with each arm's estimator pickled whole, at 1,000 arms it held the worker thread for 27-99 ms
    (building and pickling it for the pipe) and the receiving process for 27-33 ms more to unpickle it,
    every second (docs/performance.md). As chunks of tuples the pipe carries bytes and nothing is built that
    is not read; the worker takes the chunks between batches (service.capture)."""

    __slots__ = ("_devices", "blobs")

    def __init__(self, blobs: tuple[bytes, ...] = ()) -> None:
        self.blobs = blobs
        self._devices: dict[str, DeviceCheckpoint] | None = None

    @staticmethod
    def pack_chunk(rows: Sequence[DeviceRow]) -> bytes:
        return pickle.dumps(rows, protocol=pickle.HIGHEST_PROTOCOL)

    @classmethod
    def pack(cls, rows: Sequence[DeviceRow]) -> PackedDevices:
        return cls((cls.pack_chunk(rows),) if rows else ())

    def __reduce__(self) -> tuple[type[PackedDevices], tuple[tuple[bytes, ...]]]:
        return PackedDevices, (self.blobs,)  # the chunks alone, whether unpacked here or not

    def _unpacked(self) -> dict[str, DeviceCheckpoint]:
        devices = self._devices
        if devices is None:
            # Written by this agent's own worker process; two threads unpacking at once build equal dicts.
            devices = {}
            for blob in self.blobs:
                rows: list[DeviceRow] = pickle.loads(blob)
                devices.update((row[0], _unpack_device(row)) for row in rows)
            self._devices = devices
        return devices

    def __getitem__(self, device: str) -> DeviceCheckpoint:
        return self._unpacked()[device]

    def __iter__(self) -> Iterator[str]:
        return iter(self._unpacked())

    def __len__(self) -> int:
        return len(self._unpacked())


def _unpack_device(row: DeviceRow) -> DeviceCheckpoint:
    _, health, loss, units, timestamp_ms, targets, gripper = row
    return DeviceCheckpoint(
        health=HealthCheckpoint.from_row(health),
        loss=loss,
        units=Units(units) if units is not None else None,
        timestamp_ms=timestamp_ms,
        targets_rad=targets,
        gripper_percent=gripper,
    )


@dataclass(frozen=True)
class MirrorCheckpoint:
    """A mirror's state between two batches: what a restarted worker takes back (`RestoreRequest`) so its arms
    keep their counters, loss estimates and alarms, and what `/state` shows of its arms while it restarts.
    `taken` is how many messages the mirror had taken from its inbox: the agent sends the new worker every
    message it handed the old one after those (service.shards, `WorkerShard`). Alarms only (no devices)
    when asked for `alarms_only`."""

    taken: int = 0
    errors: int = 0
    batches: int = 0
    at: float = 0.0  # when it was taken (the host's monotonic clock)
    devices: Mapping[str, DeviceCheckpoint] = field(default_factory=PackedDevices)
    untracked_rejected: dict[str, int] = field(default_factory=dict)
    alarms: tuple[AlarmRecord, ...] = ()
    alarm_counters: AlarmCounters = field(default_factory=AlarmCounters)
    history: HistoryState | None = None
    tracking_since: float = 0.0  # when the mirror's health tracking began (for a device never heard from)
    # The fleet's alarm counts as the mirror had them (not with `alarms_only`): `/state` merges them for a
    # worker being started again, so the summary does not dip while its arms show as restarting.
    alarms_summary: AlarmsSummary | None = None
    # The devices the rate watch has reported publishing far above the expected rate (events.RateWatch), so a
    # restarted worker does not report them again.
    crowded: tuple[str, ...] = ()
    # And those it reported sending well under it (a slow edge, or a fixed pattern of loss).
    slow: tuple[str, ...] = ()
    # The arms the loss watch has reported losing messages (events.LossWatch), and those whose edge clocks
    # were reported off (events.ClockWatch), for the same reason.
    losing: tuple[str, ...] = ()
    clocks_off: tuple[str, ...] = ()
    # The status watch's flapping episodes (events.StatusWatch), so a restarted worker neither warns of an arm
    # known to flap a second time nor loses its settle and summary times. A checkpoint pickled without the
    # field reads this default.
    flapping: tuple[FlapRow, ...] = ()
    # The arms listed for the alarms the state file kept though not heard since (FleetHealth.keep): without
    # them a restarted worker would drop those arms from /state and the Fleet page, their alarms still shown.
    kept: tuple[str, ...] = ()
    # The rows handed to history for the messages `taken` counts, over every process of the worker (its
    # restart counts those its dead feed held and nothing sends again: history_feed.resume_point).
    history_rows: int = 0
    # The NORMAL alarms `alarms` leaves out (ServoAlarms.idle), so a restarted worker's NORMAL counts and each
    # alarm's times raised do not drop until its arms are heard again (a moving arm's model check, an arm
    # gone quiet: maybe never). Not with `alarms_only`. A checkpoint pickled without the field reads this.
    idle_alarms: tuple[IdleRow, ...] = ()
    # The devices not tracked whose every message was refused (UnheardArm, `last_s` as of `at`): the Fleet
    # page's notice naming them is read from here, so a console tick asks no worker for them.
    unheard: tuple[UnheardArm, ...] = ()


@dataclass(frozen=True, slots=True)
class CheckpointRequest:
    """The mirror's `MirrorCheckpoint`, taken between two batches; only its alarms with `alarms_only`."""

    alarms_only: bool = False


@dataclass(frozen=True, slots=True)
class RestoreRequest:
    """Take back a checkpoint (a restarted worker, before any message) and alarms (the agent's state file,
    at start): alarms replace what the mirror has for their ids."""

    checkpoint: MirrorCheckpoint | None = None
    alarms: tuple[AlarmRecord, ...] = ()
    # With history on, a restarted worker's: which messages sent again had their rows delivered already.
    history: Resume | None = None


@dataclass(frozen=True, slots=True)
class Restored:
    devices: int
    alarms: int


# A stop report's key for what a queued sink still held, after its name: its samples and status changes.
SINK_UNWRITTEN_SUFFIX = "_items"


@dataclass(frozen=True, slots=True)
class StopReport:
    """What a mirror could not write when it stopped (by sink: `history_rows`, `<sink>_items`), its alarms
    for the agent's state file, and its newest events (at most EVENTS_PER_ASK, oldest first): those the agent
    has not collected yet, made in its last half second or as it handled what was queued at the stop. And
    its USD recording's figures once the recording closed (None: it recorded nothing), which a stopped
    agent's state shows for a worker process that is gone."""

    unwritten: dict[str, int] = field(default_factory=dict)
    alarms: tuple[AlarmRecord, ...] = ()
    events: tuple[Event, ...] = ()
    recording: RecordingState | None = None


Request = (
    ReportRequest
    | AlarmsRequest
    | AckRequest
    | AckManyRequest
    | ForgetRequest
    | EventsRequest
    | FleetRowsRequest
    | ArmRequest
    | StatusesRequest
    | UnheardRequest
    | CalibrationsRequest
    | CheckpointRequest
    | RestoreRequest
)
Reply = (
    MirrorReport
    | tuple[AlarmInfo, ...]
    | AlarmInfo
    | Acknowledged
    | AckedMany
    | ArmForgotten
    | EventsReply
    | tuple[FleetRow, ...]
    | tuple[UnheardArm, ...]
    | ArmReply
    | tuple[tuple[str, str], ...]
    | int
    | MirrorCheckpoint
    | Restored
)


def report_of(reply: Reply) -> MirrorReport:
    """The answer to a ReportRequest; WorkerError for anything else."""
    if not isinstance(reply, MirrorReport):
        raise WorkerError(f"a report was asked for, the answer was {type(reply).__name__}")
    return reply


def alarms_of(reply: Reply) -> tuple[AlarmInfo, ...]:
    """The answer to an AlarmsRequest; WorkerError for anything else."""
    if not isinstance(reply, tuple) or not all(isinstance(a, AlarmInfo) for a in reply):
        raise WorkerError(f"alarms were asked for, the answer was {type(reply).__name__}")
    return tuple(a for a in reply if isinstance(a, AlarmInfo))


def events_of(reply: Reply) -> EventsReply:
    """The answer to an EventsRequest; WorkerError for anything else."""
    if not isinstance(reply, EventsReply):
        raise WorkerError(f"events were asked for, the answer was {type(reply).__name__}")
    return reply


def fleet_rows_of(reply: Reply) -> tuple[FleetRow, ...]:
    """The answer to a FleetRowsRequest; WorkerError for anything else."""
    if not isinstance(reply, tuple) or not all(isinstance(r, FleetRow) for r in reply):
        raise WorkerError(f"fleet rows were asked for, the answer was {type(reply).__name__}")
    return tuple(r for r in reply if isinstance(r, FleetRow))


def arm_reply_of(reply: Reply) -> ArmReply:
    """The answer to an ArmRequest; WorkerError for anything else."""
    if not isinstance(reply, ArmReply):
        raise WorkerError(f"an arm was asked for, the answer was {type(reply).__name__}")
    return reply


def with_dropped(device: DeviceState, dropped: int) -> DeviceState:
    """`device` with `dropped` more messages counted as overwritten (the agent could not hand them over)."""
    counters = device.health.counters
    counters = dataclasses.replace(counters, overwritten=counters.overwritten + dropped)
    return dataclasses.replace(device, health=dataclasses.replace(device.health, counters=counters))


def unheard_of(reply: Reply) -> tuple[UnheardArm, ...]:
    """The answer to an UnheardRequest; WorkerError for anything else."""
    if not isinstance(reply, tuple) or not all(isinstance(a, UnheardArm) for a in reply):
        raise WorkerError(f"unheard arms were asked for, the answer was {type(reply).__name__}")
    return tuple(a for a in reply if isinstance(a, UnheardArm))


def statuses_of(reply: Reply) -> tuple[tuple[str, str], ...]:
    """The answer to a StatusesRequest; WorkerError for anything else."""
    if not isinstance(reply, tuple):
        raise WorkerError(f"statuses were asked for, the answer was {type(reply).__name__}")
    pairs: list[tuple[str, str]] = []
    for pair in reply:
        match pair:
            case (str() as device, str() as status) if isinstance(pair, tuple):
                pairs.append((device, status))
            case _:
                raise WorkerError(f"statuses were asked for, the answer held {pair!r}")
    return tuple(pairs)


def checkpoint_of(reply: Reply) -> MirrorCheckpoint:
    """The answer to a CheckpointRequest; WorkerError for anything else."""
    if not isinstance(reply, MirrorCheckpoint):
        raise WorkerError(f"a checkpoint was asked for, the answer was {type(reply).__name__}")
    return reply


def restored_of(reply: Reply) -> Restored:
    """The answer to a RestoreRequest; WorkerError for anything else."""
    if not isinstance(reply, Restored):
        raise WorkerError(f"a restore was asked for, the answer was {type(reply).__name__}")
    return reply


def applied_of(reply: Reply) -> int:
    """The answer to a CalibrationsRequest; WorkerError for anything else."""
    if not isinstance(reply, int) or isinstance(reply, bool):
        raise WorkerError(f"calibrations were handed over, the answer was {type(reply).__name__}")
    return reply


def alarm_of(reply: Reply) -> AlarmInfo:
    """The answer to an AckRequest; WorkerError for anything else."""
    if not isinstance(reply, AlarmInfo):
        raise WorkerError(f"an acknowledged alarm was asked for, the answer was {type(reply).__name__}")
    return reply


def acknowledged_of(reply: Reply) -> tuple[AlarmInfo, MirrorCheckpoint | None]:
    """The answer to an AckRequest, with or without its checkpoint; WorkerError for anything else."""
    if isinstance(reply, Acknowledged):
        return reply.alarm, reply.checkpoint
    return alarm_of(reply), None


def acked_many_of(reply: Reply) -> AckedMany:
    """The answer to an AckManyRequest; WorkerError for anything else."""
    if not isinstance(reply, AckedMany):
        raise WorkerError(f"several alarms were to be acknowledged, the answer was {type(reply).__name__}")
    return reply


def forgotten_of(reply: Reply) -> ArmForgotten:
    """The answer to a ForgetRequest; WorkerError for anything else."""
    if not isinstance(reply, ArmForgotten):
        raise WorkerError(f"an arm was to be forgotten, the answer was {type(reply).__name__}")
    return reply


# What crosses a worker's control pipe (pickled): the agent's calls, and the worker's answers and refusals,
# matched by call id; when it starts, the worker says once whether it runs.


@dataclass(frozen=True, slots=True)
class Call:
    call_id: int
    request: Request


@dataclass(frozen=True, slots=True)
class Answer:
    call_id: int
    reply: Reply


class Refusal(StrEnum):
    ALARM_NOT_FOUND = "alarm_not_found"
    NOTHING_TO_ACKNOWLEDGE = "nothing_to_acknowledge"
    ARM_NOT_FOUND = "arm_not_found"
    ARM_NOT_OFFLINE = ARM_NOT_OFFLINE
    ARM_CONFIGURED = ARM_CONFIGURED
    ERROR = "error"
    # The process answers, but its mirror thread did not get to the request in time: counted as unanswered
    # (WorkerShard._kill_if_hung), since a mirror thread stuck for good answers nothing else either.
    STUCK = "stuck"
    # As STUCK, but the mirror thread handled batches meanwhile (mirror.MirrorBusyError): slow, not hung. It
    # answers, so the count starts again: killing it would add a restart's replay to the load that slowed it.
    BUSY = "busy"


@dataclass(frozen=True, slots=True)
class Refused:
    call_id: int
    refusal: Refusal
    message: str
    state: str = ""  # NOTHING_TO_ACKNOWLEDGE's: the alarm's state (NothingToAcknowledge.state)


@dataclass(frozen=True, slots=True)
class Ready:
    pid: int


@dataclass(frozen=True, slots=True)
class Farewell:
    """The worker's last word on its control pipe, after its sinks closed: its StopReport."""

    report: StopReport


@dataclass(frozen=True, slots=True)
class StartFailed:
    """The worker could not start; `config_error`: because of a setting (`twin run` exits 2, `message`)."""

    message: str
    config_error: bool


def _raise_refusal(refused: Refused, worker: int) -> None:
    if refused.refusal is Refusal.ALARM_NOT_FOUND:
        raise AlarmNotFound(refused.message)
    if refused.refusal is Refusal.NOTHING_TO_ACKNOWLEDGE:
        raise NothingToAcknowledge(refused.message, refused.state)
    if refused.refusal is Refusal.ARM_NOT_FOUND:
        raise ArmNotFoundError(refused.message)
    if refused.refusal in (Refusal.ARM_NOT_OFFLINE, Refusal.ARM_CONFIGURED):
        raise ArmNotForgettableError(str(refused.refusal), refused.message)
    if refused.refusal is Refusal.BUSY:
        raise AskTimedOutError(f"worker {worker}: {refused.message}")
    raise WorkerError(f"worker {worker}: {refused.message}")


# ------------------------------------------------------------------------------------------------- shards


@dataclass(frozen=True)
class WorkerExit:
    """A worker process that ended: its own pid (not its successor's) and how it ended."""

    pid: int
    exit_code: int | None  # multiprocessing's: negative for the signal that killed it, None if unknown
    server_lost: bool = False  # 255 came from its killed fork server while the worker still ran (`seen`)
    # Seconds it had answered no request when the supervisor killed it as hung; 0 if not ended so.
    hung_s: float = 0.0
    # Found hung, but its exit code says it ended otherwise (exited or crashed before the kill reached it).
    found_hung: bool = False

    @classmethod
    def seen(cls, pid: int, exit_code: int | None) -> WorkerExit:
        """The exit of the worker `pid` as found now. Its code reaches the agent through the fork server that
        started it: with that process gone (killed), multiprocessing reports 255 while the worker may well
        still run, so that is checked now, before the worker is stopped to be started again."""
        return cls(pid, exit_code, exit_code == 255 and pid > 0 and _still_runs(pid))

    def how(self) -> str:
        """What became of it, after its pid: `exited, exit code 1`, `exited, killed by SIGKILL (signal 9)`,
        `exited, exit code unknown`, that the supervisor killed it as hung (its exit code is then only the
        kill's), or that its fork server is gone (a worker that did not exit); `, while found hung` after an
        exit of its own as the supervisor went to kill it."""
        code = self.exit_code
        if self.hung_s:
            return (
                f"answered no request for {self.hung_s:.0f} s (hung) and was killed by the supervisor "
                "with SIGKILL"
            )
        if self.server_lost:
            return "can no longer be watched: the fork server that started it is gone (killed?)"
        if code is None:
            how = "exited, exit code unknown"
        elif code < 0:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = "an unknown signal"
            how = f"exited, killed by {name} (signal {-code})"
        else:
            how = f"exited, exit code {code}"
        return f"{how}, while found hung" if self.found_hung else how


class Shard(Protocol):
    """What the agent needs of one share of the fleet, whether its mirror runs in-process or in a worker."""

    index: int
    restarts: int  # how often its mirror was started again (a worker's process); 0 in-process

    def put(self, key: str, topic: str, payload: bytes, recv_mono: float, recv_wall: float) -> None:
        """Queue one message for the mirror (`key`: its device, or UNTRACKED_KEY); on a CRT thread, never
        blocks for long."""
        ...

    def launch(self) -> None:
        """Begin starting the mirror (a worker: its process; the agent waits for every shard afterwards)."""
        ...

    def await_ready(self) -> None:
        """Return once the mirror runs and answers requests; ConfigError (a setting it cannot work with),
        WorkerError, OSError. It is handed no message before `open()`."""
        ...

    def open(self) -> None:
        """Hand the mirror its messages from now on: what was queued since `launch()` first, in order."""
        ...

    def close(self) -> None:
        """No more messages: the mirror handles what is queued, flushes its sinks and ends."""
        ...

    def join(self, deadline: float) -> StopReport | None:
        """Wait (until `deadline`, time.monotonic) for the mirror to end after `close`; what it could not
        write (None when it had to be killed)."""
        ...

    def supervise(self) -> None:
        """Called every half second while the agent runs: start a dead or hung worker again; an in-process
        mirror's stuck thread makes the shard `failed`."""
        ...

    @property
    def failed(self) -> bool:
        """The mirror stopped for good, or is stuck, while the agent runs (nothing will start it again)."""
        ...

    @property
    def answering(self) -> bool:
        """The mirror can be asked now (a worker being started again cannot)."""
        ...

    def request(self, request: Request) -> Callable[[], Reply]:
        """Send `request`; the returned function (call it exactly once) waits for and returns the reply, or
        raises AlarmNotFound, NothingToAcknowledge, ArmNotFoundError, ArmNotForgettableError or
        WorkerError."""
        ...

    def describe(self, report: MirrorReport | None) -> WorkerInfo | None:
        """This shard as a worker in `agent.workers` (None for an in-process mirror)."""
        ...

    def dropped(self) -> Mapping[str, int]:
        """Messages per device the agent could not hand to this mirror (its queue overflowed, they were lost
        with a worker that died); the most recent devices only."""
        ...

    def forget(self, device: str) -> None:
        """Forget the agent's own per-device counts of `device` (an arm forgotten: `dropped`)."""
        ...

    @property
    def dropped_total(self) -> int:
        """Every message `dropped` counts, also those of devices it no longer lists."""
        ...

    @property
    def restarting(self) -> bool:
        """The mirror's worker process died and is being started again."""
        ...

    @property
    def checkpoint(self) -> MirrorCheckpoint | None:
        """The mirror's latest checkpoint the agent holds (`confirm`)."""
        ...

    def confirm(self, checkpoint: MirrorCheckpoint, *, restarts: int | None = None) -> bool:
        """Keep `checkpoint` as the mirror's latest; with `restarts` (the shard's count when the checkpoint
        was asked for), only if no restart began since (False then: it is the dead process's)."""
        ...

    def restarting_devices(
        self, thresholds: HealthThresholds, now: float, mirror: MirrorStatus = MirrorStatus.RESTARTING
    ) -> dict[str, DeviceState]:
        """While restarting (or once the agent's stop has ended the mirror: `mirror`): the mirror's devices as
        its latest checkpoint left them."""
        ...

    def restarting_alarms(self, now: float, wall: float, *, include_normal: bool) -> list[AlarmInfo]:
        """While restarting: the mirror's alarms as its latest checkpoint left them (`now`, `wall`: the
        host's monotonic and wall clocks, read together)."""
        ...

    def keep_calibrations(self, request: CalibrationsRequest) -> None:
        """The arms' own calibrations the agent last handed over: a worker started again gets them before
        its first message."""
        ...

    def last_exit(self) -> WorkerExit | None:
        """The worker process that ended last: the shard's own while it is dead, else the one its latest
        restart replaced; None in-process or before any ended."""
        ...


_CALL_IDS = itertools.count(1)


class WorkerShard:
    """A share of the fleet mirrored in a worker process: its process, pipes, queue and sender thread.

    The agent keeps what the worker needs to start again where it stopped: the worker's latest checkpoint
    (taken every CHECKPOINT_EVERY_S by the agent's supervisor: counters, loss estimates, alarms, poses) and
    every message it handed the worker since the checkpoint's `taken` (at most MAX_UNCONFIRMED). A worker
    that dies is started again, given the checkpoint, then those messages again, then the queue, which held
    what arrived meanwhile: its arms keep their counts and alarms, and no message is lost unless the queue
    or the kept messages overflowed (counted). While it restarts `/state` shows its arms from the checkpoint,
    marked `restarting`.
    """

    def __init__(
        self,
        index: int,
        config: AgentConfig,
        budget: DeviceBudget,
        context: ForkServerContext,
        history: HistoryLink | None = None,
    ) -> None:
        self.index = index
        self._config = config  # the worker's own (worker_config)
        self._budget = budget
        self._history = history
        self._ctx = context
        self.queue: InboundQueue[tuple[str, bytes, float, float]] = InboundQueue(
            MAX_QUEUED_PER_WORKER, max_bytes=MAX_QUEUED_BYTES_PER_WORKER, size_of=_payload_size
        )
        self.process: ForkServerProcess | None = None
        self.data: Connection | None = None
        self.control: Connection | None = None
        self._control_lock = threading.Lock()
        # The data pipe's one writer at a time (the sender thread, or the supervisor replaying after a
        # restart), and `ready` changes under it.
        self._send_lock = threading.Condition(threading.Lock())
        self.ready = False
        self.pid = 0
        self.started_at = 0.0
        self.restarts = 0
        self._restart_at: float | None = None
        # The last process found dead: once started again, `pid` names its successor.
        self._ended: WorkerExit | None = None
        self._sender: threading.Thread | None = None
        # Messages taken from the queue while the worker was down: sent first once it runs again.
        self._held: list[Message] = []
        # Messages handed to the worker that its latest checkpoint does not count yet, as the pipe messages
        # that carried them (index of the first message in the worker's count of messages taken, how many,
        # the bytes sent), and the next index. Kept as sent, not as per-message tuples: a third less memory
        # and nothing for the garbage collector to walk (1-2 s of the fleet's messages are kept).
        self._unconfirmed: deque[tuple[int, int, bytes]] = deque()
        self._unconfirmed_count = 0
        self._sent = 0
        self._unconfirmed_lock = threading.Lock()
        self.checkpoint: MirrorCheckpoint | None = None
        # Messages lost for good, by device: handed to a worker that died before its checkpoint counted them
        # and no longer kept (MAX_UNCONFIRMED), or still queued when the agent stopped during a restart.
        self._lost: BoundedCounter[str] = BoundedCounter(MAX_OVERFLOW_KEYS)
        self._calibrations: CalibrationsRequest | None = None
        self._closed = False
        # Asks in a row this process let time out (HUNG_AFTER_ASKS), read and reset under the control lock.
        self._unanswered = 0
        self._answered_at = 0.0  # monotonic time of its last answer (the hung one's silence)

    @property
    def alive(self) -> bool:
        return self.ready and self.process is not None and self.process.is_alive()

    @property
    def answering(self) -> bool:
        return self.alive

    @property
    def restarting(self) -> bool:
        """Started once and not running now: being started again (its arms show as restarting)."""
        return self.pid != 0 and not self.alive and not self._closed

    @property
    def failed(self) -> bool:
        return False  # a dead worker is started again

    def last_exit(self) -> WorkerExit | None:
        process, ended = self.process, self._ended
        if process is not None and process.exitcode is not None:
            pid = process.pid or self.pid
            # Judged once, when found dead: a worker its lost fork server left running exits once its pipes
            # close, and judged again it would read as having exited with the server's 255.
            if ended is not None and ended.pid == pid:
                # The supervisor's kill of a hung one is noted before its exit code is known.
                known = ended.exit_code is not None
                return ended if known else dataclasses.replace(ended, exit_code=process.exitcode)
            return WorkerExit.seen(pid, process.exitcode)
        return ended

    def put(self, key: str, topic: str, payload: bytes, recv_mono: float, recv_wall: float) -> None:
        self.queue.put(key, (topic, payload, recv_mono, recv_wall))

    def dropped(self) -> dict[str, int]:
        with self._unconfirmed_lock:
            lost = self._lost.counts()
        return merged_counts(self.queue.overflowed, lost)

    @property
    def dropped_total(self) -> int:
        with self._unconfirmed_lock:
            lost = self._lost.total()
        return self.queue.overflowed_total + lost

    def forget(self, device: str) -> None:
        """A forgotten arm's own counts of messages dropped or lost (the totals keep them): a later arm of
        that name starts from nothing, as its mirror does."""
        self.queue.forget(device)
        with self._unconfirmed_lock:
            self._lost.discard(device)

    # -- lifecycle -----------------------------------------------------------------------------------------

    def launch(self) -> None:
        data_read, data_write = self._ctx.Pipe(duplex=False)
        control, control_child = self._ctx.Pipe()
        process = self._ctx.Process(
            target=worker_main,
            args=(self.index, self._config, data_read, control_child, self._budget),
            kwargs={"history": self._history},
            name=f"twin-worker-{self.index}",
        )
        process.start()
        # The worker holds its own ends now; closing ours lets each side see the other go (EOF).
        data_read.close()
        control_child.close()
        self.process, self.data, self.control = process, data_write, control
        self.started_at = time.monotonic()

    def _await_hello(self) -> None:
        """Wait for the new process to say it runs (its pid), or raise why not."""
        assert self.control is not None and self.process is not None
        if not self.control.poll(START_TIMEOUT_S):
            raise WorkerError(f"worker {self.index} did not start within {START_TIMEOUT_S:.0f} s")
        try:
            hello = self.control.recv()
        except (EOFError, OSError):
            self.process.join(5.0)
            raise WorkerError(
                f"worker {self.index} exited while starting (exit code {self.process.exitcode}); "
                "its log lines above say why"
            ) from None
        if isinstance(hello, StartFailed):
            if hello.config_error:
                raise ConfigError(hello.message)
            raise WorkerError(f"worker {self.index} could not start: {hello.message}")
        if not isinstance(hello, Ready):
            raise WorkerError(f"worker {self.index} said {hello!r} instead of being ready")
        self.pid = hello.pid

    def await_ready(self) -> None:
        self._await_hello()
        with self._send_lock:
            self.ready = True
            self._send_lock.notify_all()

    def open(self) -> None:
        if self._sender is None:
            self._sender = threading.Thread(
                target=self._send_loop, name=f"twin-send-{self.index}", daemon=True
            )
            self._sender.start()

    def supervise(self) -> None:
        """Start the worker again if it died (class doc): its checkpoint, then the messages since."""
        process = self.process
        if process is None or self._closed:
            return
        if process.is_alive():
            self._kill_if_hung(process)
            return
        now = time.monotonic()
        if self._restart_at is None:
            self._restart_at = self._found_dead(process, now)
        if now < self._restart_at:
            return
        self._restart_at = None
        with self._unconfirmed_lock:
            # From here on a checkpoint asked of the dead process is not confirmed (an acknowledgement's,
            # answered just before it died), and this restart starts from the one held now, both in the
            # process's restore and in what it is sent again.
            self.restarts += 1
            start = self.checkpoint
        with self._control_lock:
            for conn in (self.data, self.control):
                if conn is not None:
                    conn.close()
            # Its places in the device budget go with it; the checkpoint's arms take theirs again.
            self._budget.release(self.index)
            try:
                self.launch()
                self._await_hello()
                restored = self._restore(start)
                self._recalibrate()
            except (WorkerError, ConfigError) as exc:
                log.error("worker %d could not be started again: %s", self.index, exc)
                return
        try:
            replayed = self._replay(start)
        except (OSError, ValueError) as exc:
            log.error("worker %d died again while its messages were sent again: %s", self.index, exc)
            return
        log.info(
            "worker %d running again",
            self.index,
            extra={
                "worker": self.index,
                "pid": self.pid,
                "devices_restored": restored.devices,
                "alarms_restored": restored.alarms,
                "messages_sent_again": replayed,
            },
        )

    def _found_dead(self, process: ForkServerProcess, now: float) -> float:
        """Note a dead process (logged, kept for `last_exit`); returns when to start it again."""
        with self._send_lock:
            self.ready = False
        pid, killed = process.pid or self.pid, self._ended
        ended = WorkerExit.seen(pid, process.exitcode)
        if killed is not None and killed.pid == pid and killed.hung_s:
            # Its exit is the supervisor's kill only if the code is the kill's or unknown (None, or the 255
            # multiprocessing reports when its fork server is gone, `seen`): one that exited or crashed
            # (SIGSEGV) between is_alive() and kill() keeps its own code, told as found hung.
            if ended.exit_code in (None, 255, -signal.SIGKILL):
                ended = dataclasses.replace(ended, hung_s=killed.hung_s)
            else:
                ended = dataclasses.replace(ended, found_hung=True)
        self._ended = ended
        quick = now - self.started_at < QUICK_DEATH_S
        pause = min(MAX_RESTART_PAUSE_S, 2.0 ** min(self.restarts, 6)) if quick else 0.0
        log.error(
            "%s; starting it again%s",
            _how_it_ended(self.index, ended),
            f" in {pause:.0f} s" if pause else "",
            extra={"worker": self.index, "exit_code": process.exitcode},
        )
        return now + pause

    def _kill_if_hung(self, process: ForkServerProcess) -> None:
        """A worker process that runs but answers nothing (stopped, or stuck in a native call with the GIL
        held) kept its arms' messages queued with nothing to say so until its queue overflowed: after
        HUNG_AFTER_ASKS unanswered asks it is killed, and the next supervise starts it again from its
        checkpoint with the messages since, as after a crash (WorkerRestarts pages)."""
        if self._unanswered < HUNG_AFTER_ASKS:
            return
        with self._control_lock:
            unanswered, self._unanswered = self._unanswered, 0
        silent_s = time.monotonic() - max(self._answered_at, self.started_at)
        log.error(
            "worker %d (pid %d) runs but answered none of the last %d requests (%.0f s each; nothing for "
            "%.0f s): it is hung; killing it (SIGKILL) to start it again from its checkpoint",
            self.index,
            self.pid,
            unanswered,
            ASK_TIMEOUT_S,
            silent_s,
            extra={"worker": self.index, "pid": self.pid},
        )
        process.kill()
        process.join(ASK_TIMEOUT_S)
        # Said so when it is found dead, in the log and on the Events page: its exit code alone (or none, if
        # the kill is not reaped yet) read as a crash of unknown cause.
        self._ended = WorkerExit(self.pid, None, hung_s=max(silent_s, 1.0))

    def _restore(self, checkpoint: MirrorCheckpoint | None) -> Restored:
        """Hand the new process `checkpoint`, the latest when the restart began (control lock held)."""
        assert self.control is not None
        call_id = next(_CALL_IDS)
        request = RestoreRequest(checkpoint=checkpoint, history=self._history_resume(checkpoint))
        try:
            self.control.send(Call(call_id, request))
        except (OSError, ValueError) as exc:
            raise WorkerError(f"worker {self.index} is not reachable: {exc}") from exc
        return restored_of(self._answer(call_id))

    def _history_resume(self, checkpoint: MirrorCheckpoint | None) -> Resume | None:
        """With history on: where the new process's feed takes up (history_feed.resume_point), so the
        messages sent again whose rows the dead one delivered are not written twice."""
        if self._history is None:
            return None
        from twin.output.history_feed import resume_point  # noqa: PLC0415 - only with history on

        with self._unconfirmed_lock:
            taken, first = self._taken_and_first(checkpoint)
        return resume_point(
            self._history,
            self.index,
            taken=taken,
            taken_rows=checkpoint.history_rows if checkpoint is not None else 0,
            replay_from=max(first, taken),
        )

    def _taken_and_first(self, checkpoint: MirrorCheckpoint | None) -> tuple[int, int]:
        """(the messages `checkpoint` counts, the first one still kept to be sent again), in this worker's
        numbering; the unconfirmed lock held."""
        taken = checkpoint.taken if checkpoint is not None else 0
        return taken, self._unconfirmed[0][0] if self._unconfirmed else self._sent

    def _recalibrate(self) -> None:
        """Hand the new process the arms' own calibrations before the messages it is sent again, so none of
        them decodes with another calibration than the first time (control lock held)."""
        request = self._calibrations
        if request is None:
            return
        assert self.control is not None
        call_id = next(_CALL_IDS)
        try:
            self.control.send(Call(call_id, request))
        except (OSError, ValueError) as exc:
            raise WorkerError(f"worker {self.index} is not reachable: {exc}") from exc
        applied_of(self._answer(call_id))

    def keep_calibrations(self, request: CalibrationsRequest) -> None:
        self._calibrations = request

    def _replay(self, checkpoint: MirrorCheckpoint | None) -> int:
        """Send the new process what `checkpoint` (the one it was restored from) does not count, then what was
        held; then it runs."""
        with self._send_lock:
            with self._unconfirmed_lock:
                again: list[Message] = []
                taken, first = self._taken_and_first(checkpoint)
                if first > taken:
                    # Handed over, not counted by the checkpoint, and no longer kept: lost with the worker.
                    log.error(
                        "worker %d: %d messages it had taken were lost with it (more than %d since its last "
                        "checkpoint)",
                        self.index,
                        first - taken,
                        MAX_UNCONFIRMED,
                    )
                    self._lost.add(UNTRACKED_KEY, first - taken)
                for start, count, raw in self._unconfirmed:
                    skip = max(0, taken - start)
                    if skip < count:
                        again.extend(messages_of(raw)[skip:])
                again.extend(self._held)
                self._held = []
                self._unconfirmed.clear()
                self._unconfirmed_count = 0
                self._sent = taken
                parts = [again[i : i + MAX_BATCH] for i in range(0, len(again), MAX_BATCH)]
                chunks = [(len(part), encode_batch(part)) for part in parts]
                # Kept as unconfirmed before they are sent: if this worker dies too, they go again.
                for count, raw in chunks:
                    self._keep(count, raw)
            conn = self.data
            assert conn is not None
            for _, raw in chunks:
                send_encoded(conn, raw)
            self.ready = True
            self._send_lock.notify_all()
            return len(again)

    def _keep(self, count: int, raw: bytes) -> None:
        """Remember the pipe message `raw` (`count` messages) as handed to the worker (unconfirmed lock held);
        beyond the bound, the oldest go."""
        self._unconfirmed.append((self._sent, count, raw))
        self._sent += count
        self._unconfirmed_count += count
        while len(self._unconfirmed) > 1 and self._unconfirmed_count > MAX_UNCONFIRMED:
            _, oldest, _ = self._unconfirmed.popleft()
            self._unconfirmed_count -= oldest

    def confirm(self, checkpoint: MirrorCheckpoint, *, restarts: int | None = None) -> bool:
        """A checkpoint of the running worker: keep it, and forget the messages it counts. With `restarts`,
        not if a restart began since it was asked for (False)."""
        with self._unconfirmed_lock:
            if restarts is not None and restarts != self.restarts:
                return False
            self.checkpoint = checkpoint
            unconfirmed = self._unconfirmed
            while unconfirmed and unconfirmed[0][0] + unconfirmed[0][1] <= checkpoint.taken:
                _, count, _ = unconfirmed.popleft()
                self._unconfirmed_count -= count
        return True

    def close(self) -> None:
        self._closed = True
        self.queue.close()
        with self._send_lock:
            self._send_lock.notify_all()

    def join(self, deadline: float) -> StopReport | None:
        """Wait until `deadline` for the worker to finish and say what it could not write (its Farewell);
        a worker still running then is killed (None: what it held is lost, its last checkpoint's alarms
        stand for its own). Called once, after `close`."""
        if self._sender is not None:
            self._sender.join(max(0.1, deadline - time.monotonic()))
        elif self.data is not None:
            with contextlib.suppress(OSError, ValueError):
                send_end(self.data)
        report = self._farewell(deadline)
        process = self.process
        if process is not None:
            process.join(max(0.1, deadline - time.monotonic()))
            if process.is_alive():
                log.error(
                    "worker %d did not stop within the shutdown budget; killing it: what it had not written "
                    "is lost",
                    self.index,
                    extra={"worker": self.index},
                )
                process.kill()
                process.join(5.0)
        self.ready = False
        for conn in (self.data, self.control):
            if conn is not None:
                conn.close()
        if self._sender is None:
            # Never opened: the agent's start failed first. Never launched, or it could not start (no
            # Farewell then), or it was killed just now: either way it was never handed a message, so it held
            # nothing to lose (None would be reported as a worker killed with what it held). What the queue
            # held for it since the subscription is lost with the failed start: counted, not dropped unsaid.
            report = report or StopReport()
            if left := len(self.queue):
                report = dataclasses.replace(report, unwritten={**report.unwritten, UNMIRRORED: left})
        return report

    def _farewell(self, deadline: float) -> StopReport | None:
        conn = self.control
        if conn is None or self.process is None:
            return None
        if not self._control_lock.acquire(timeout=max(0.1, deadline - time.monotonic())):
            return None
        try:
            while True:
                remaining = deadline - time.monotonic()
                try:
                    if remaining <= 0 or not conn.poll(remaining):
                        return None
                    message = conn.recv()
                except (EOFError, OSError):
                    return None
                if isinstance(message, Farewell):
                    return message.report
        finally:
            self._control_lock.release()

    def _send_loop(self) -> None:
        """Hand the worker its queue in batches; while it is down, wait (the queue holds what arrives)."""
        name_native_thread()
        queue = self.queue
        window_start, window_count, pause = time.monotonic(), 0, 0.0
        while True:
            with self._send_lock:
                while not self.ready and not self._closed:
                    self._send_lock.wait(0.2)
                if not self.ready:
                    break  # stopping while the worker is down: nothing will take the rest
            items = queue.take_all(0.2)
            if not items:
                if queue.closed:
                    break
                continue
            if pause and len(items) < MAX_BATCH:
                time.sleep(pause)
                items += queue.take_all(0)
            window_count += len(items)
            now = time.monotonic()
            if now - window_start >= 1.0:
                rate = window_count / (now - window_start)
                pause = min(MAX_SEND_PAUSE_S, BATCH_TARGET / rate) if rate > PAUSE_ABOVE_RATE else 0.0
                window_start, window_count = now, 0
            for start in range(0, len(items), MAX_BATCH):
                self._hand_over(items[start : start + MAX_BATCH])
        with self._send_lock:
            if self.data is not None and self.ready:
                with contextlib.suppress(OSError, ValueError):
                    send_end(self.data)
                return
            left = [key for key, _ in self._held] + [key for key, _ in queue.take_all(0)]
            self._held = []
        if left:
            log.error(
                "worker %d was down when the agent stopped: %d messages it was to mirror are lost",
                self.index,
                len(left),
            )
            with self._unconfirmed_lock:
                self._lost.update(left)

    def _hand_over(self, chunk: list[Message]) -> None:
        raw = encode_batch(chunk)  # before the lock: the supervisor may be waiting for it
        with self._send_lock:
            conn = self.data
            if not self.ready or conn is None:
                self._held.extend(chunk)
                return
            with self._unconfirmed_lock:
                self._keep(len(chunk), raw)
            try:
                send_encoded(conn, raw)
            except (OSError, ValueError):
                # The worker died: the chunk is kept as unconfirmed, and goes again after the restart.
                self.ready = False

    # -- requests ------------------------------------------------------------------------------------------

    def request(self, request: Request) -> Callable[[], Reply]:
        if not self.alive:
            raise WorkerError(f"worker {self.index} is not running (it is being started again)")
        self._control_lock.acquire()
        call_id = next(_CALL_IDS)
        try:
            assert self.control is not None
            self.control.send(Call(call_id, request))
        except (OSError, ValueError) as exc:
            self._control_lock.release()
            raise WorkerError(f"worker {self.index} is not reachable: {exc}") from exc
        # From the ask, not from the wait: the agent asks every worker, then waits for each in turn, and
        # this way two workers that hang cost ASK_TIMEOUT_S of a stop's budget, not twice that.
        deadline = time.monotonic() + ASK_TIMEOUT_S

        def wait() -> Reply:
            try:
                return self._answer(call_id, deadline)
            finally:
                self._control_lock.release()

        return wait

    def _answer(self, call_id: int, deadline: float | None = None) -> Reply:
        """The answer to `call_id` (under the control lock) by `deadline` (monotonic; None: ASK_TIMEOUT_S
        from now); late answers to calls that timed out are skipped."""
        conn = self.control
        assert conn is not None
        if deadline is None:
            deadline = time.monotonic() + ASK_TIMEOUT_S
        while True:
            remaining = deadline - time.monotonic()
            try:
                if remaining <= 0 or not conn.poll(remaining):
                    self._unanswered += 1
                    raise AskTimedOutError(f"worker {self.index} did not answer within {ASK_TIMEOUT_S:.0f} s")
                message = conn.recv()
            except (EOFError, OSError) as exc:
                raise WorkerError(f"worker {self.index} went away: {exc}") from exc
            if isinstance(message, Refused) and message.refusal is Refusal.STUCK:
                if message.call_id == call_id:
                    self._unanswered += 1
                    raise AskTimedOutError(f"worker {self.index}: {message.message}")
                continue
            self._unanswered = 0  # it answers, if late
            self._answered_at = time.monotonic()
            if isinstance(message, Answer) and message.call_id == call_id:
                return message.reply
            if isinstance(message, Refused) and message.call_id == call_id:
                _raise_refusal(message, self.index)

    def restarting_devices(
        self, thresholds: HealthThresholds, now: float, mirror: MirrorStatus = MirrorStatus.RESTARTING
    ) -> dict[str, DeviceState]:
        """This worker's arms as its latest checkpoint left them, marked `mirror` (empty without one)."""
        checkpoint = self.checkpoint
        if checkpoint is None:
            return {}
        calibrations = self._calibrations or CalibrationsRequest()
        sources = {device: source for device, source, _ in calibrations.files}
        problems = dict(calibrations.problems)
        devices = {}
        for device, saved in checkpoint.devices.items():
            since = checkpoint.tracking_since
            state = checkpoint_device(device, saved, thresholds, now, since, mirror=mirror)
            source = sources.get(device) or self._config.telemetry.calibration
            devices[device] = dataclasses.replace(
                state,
                calibration=source,
                uncalibrated=uncalibrated(source, state.units),
                calibration_problem=problems.get(device, ""),
            )
        return devices

    def restarting_alarms(self, now: float, wall: float, *, include_normal: bool) -> list[AlarmInfo]:
        """This worker's alarms as its latest checkpoint left them (empty without one): an ACKNOWLEDGED or
        LATCHED alarm stays listed while its worker is started again."""
        checkpoint = self.checkpoint
        if checkpoint is None:
            return []
        thresholds = self._config.alarms
        return [
            alarm_info(record_view(record, thresholds), now, wall)
            for record in checkpoint.alarms
            if include_normal or record.state is not AlarmState.NORMAL
        ]

    def describe(self, report: MirrorReport | None) -> WorkerInfo:
        return WorkerInfo(
            index=self.index,
            pid=self.pid,
            # Running and answering: a worker being started again has no report to merge yet.
            alive=self.alive and report is not None,
            restarts=self.restarts,
            devices=len(report.devices) if report is not None else 0,
            queued=len(self.queue),
            dropped=self.dropped_total,
            processed=report.worker.processed if report is not None else 0,
            errors=report.worker.errors if report is not None else 0,
            recording=report.recording.path if report is not None and report.recording else "",
            restarting=self.restarting,
        )


def _how_it_ended(index: int, ended: WorkerExit) -> str:
    """What the log says of a worker no longer seen running. One whose fork server was killed is started
    again all the same (the agent has lost sight of it, and it stops once the agent closes its pipes), but
    the log must not blame a worker that did not exit (WorkerExit.seen)."""
    told = f"worker {index} (pid {ended.pid}) {ended.how()}"
    if ended.server_lost:
        return f"{told}; the worker is stopped and a new fork server starts"
    return told


def _still_runs(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except OSError:  # gone; or another user's, so not our worker (its pid was reused)
        return False
    return True


def _payload_size(message: tuple[str, bytes, float, float]) -> int:
    return len(message[1])


def calibration_in_use(calibration: str, units: Units) -> str:
    """The calibration an arm's angles are decoded with, as /state shows it: none for degrees, which are
    already relative to the arm's calibrated middle and ignore any file (its own in the store included)."""
    return "" if units is Units.DEGREES else calibration


def uncalibrated(calibration: str, units: Units) -> bool:
    """No calibration while the units need one: degrees are already relative to the arm's calibrated
    middle, ticks and range100 are not."""
    return not calibration and units in (Units.TICKS, Units.RANGE100)


def alarm_info(view: AlarmView, now_mono: float, now_wall: float) -> AlarmInfo:
    """An alarm as GET /alarms lists it; `now_mono` and `now_wall` are the same instant on both clocks."""
    return AlarmInfo(
        alarm_id=view.alarm_id,
        device=view.device,
        joint=view.joint,
        kind=str(view.kind),
        severity=str(view.severity),
        state=str(view.state),
        value=view.value,
        threshold=view.threshold,
        unit=view.unit,
        # The engine keeps monotonic times; people want wall time.
        changed_at=now_wall - (now_mono - view.since),
        raised=view.raised,
        message=view.message,
        advice=what_to_do(str(view.kind), view.joint, view.value, view.message),
    )


def checkpoint_device(
    device: str,
    saved: DeviceCheckpoint,
    thresholds: HealthThresholds,
    now: float,
    since: float,
    *,
    mirror: MirrorStatus = MirrorStatus.RESTARTING,
) -> DeviceState:
    """A device's state as a checkpoint knows it (its mirror is being started again, or has stopped)."""
    loss = DeviceLoss.from_state(saved.loss).snapshot(now) if saved.loss is not None else LossSnapshot()
    return DeviceState(
        device_id=device,
        health=saved.health.snapshot(thresholds, now, since),
        units=saved.units or Units.AUTO,
        timestamp_ms=saved.timestamp_ms,
        joints_rad=saved.targets_rad,
        targets_rad=saved.targets_rad,
        gripper_percent=saved.gripper_percent,
        loss=loss,
        mirror=mirror,
    )


# ------------------------------------------------------------------------------------------ worker process


class _WorkerLogFilter(logging.Filter):
    def __init__(self, index: int) -> None:
        super().__init__()
        self.index = index

    def filter(self, record: logging.LogRecord) -> bool:
        record.worker = self.index
        return True


# A worker's control pipe has two writers once it stops (the answering thread, and the main thread's
# Farewell); a Connection must not be written from two threads at once.
_CONTROL_SEND = threading.Lock()


def worker_main(
    index: int,
    config: AgentConfig,
    data: Connection,
    control: Connection,
    budget: DeviceBudget,
    *,
    history: HistoryLink | None = None,
) -> None:
    """A worker process: a Mirror fed from `data`, answering `control` (module doc); with history on it
    feeds the agent's history writer process at `history`."""
    # The agent decides when workers stop (the rest of the queue first, then the sinks flush); a Ctrl-C in a
    # terminal or systemd's SIGTERM reaches the whole process group.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from twin.output.sinks import TwinSink  # noqa: PLC0415
    from twin.service.logs import setup_logging  # noqa: PLC0415
    from twin.service.mirror import Mirror, PipeInbox  # noqa: PLC0415 - MuJoCo loads in the worker only
    from twin.service.outputs import close_sinks, configured_sinks, unwritable_fix  # noqa: PLC0415

    setup_logging(config.log.level)
    for handler in logging.getLogger().handlers:
        handler.addFilter(_WorkerLogFilter(index))
    sinks: list[TwinSink] = []
    try:
        sinks = configured_sinks(config)
        mirror = Mirror(
            config, inbox=PipeInbox(data), budget=budget, slot=index, sinks=sinks, history=history
        )
        mirror.start()
    except ConfigError as exc:
        # A setting the worker cannot work with (the ros2 extra missing, say): the agent exits as for any
        # configuration error, with this message.
        close_sinks(sinks)
        control.send(StartFailed(str(exc), config_error=True))
        return
    except Exception as exc:
        close_sinks(sinks)
        log.exception("worker %d could not start", index)
        control.send(StartFailed(f"{type(exc).__name__}: {exc}{unwritable_fix(exc)}", config_error=False))
        return
    control.send(Ready(os.getpid()))
    threading.Thread(target=_serve_control, args=(mirror, control), name="twin-control", daemon=True).start()
    # The worker thread reads the pipe until the end marker (or the agent is gone), then ends.
    mirror.join()
    # Within the agent's shutdown budget, less what it keeps for itself (it kills a worker at the budget).
    report = mirror.stop(timeout=max(5.0, config.twin.shutdown_budget_s - WORKER_BUDGET_MARGIN_S))
    with contextlib.suppress(OSError, ValueError), _CONTROL_SEND:
        control.send(Farewell(report))
    # Not "agent stopped": that is the agent's own line, the one that says a run stopped; a worker's came
    # after the agent was killed too, and read as a clean stop.
    log.info(
        "worker stopped",
        extra={"processed": mirror.processed, "errors": mirror.errors, "unwritten": report.unwritten},
    )


def _serve_control(mirror: Mirror, control: Connection) -> None:
    """Answer the agent's calls, one at a time, in the order they come."""
    from twin.service.mirror import MirrorBusyError  # noqa: PLC0415 - MuJoCo loads in the worker only

    name_native_thread()
    while True:
        try:
            call = control.recv()
        except (EOFError, OSError):
            return
        if not isinstance(call, Call):
            log.error("worker control: %r is not a call", call)
            continue
        reply: Answer | Refused
        try:
            reply = Answer(call.call_id, mirror.answer(call.request))
        except AlarmNotFound as exc:
            reply = Refused(call.call_id, Refusal.ALARM_NOT_FOUND, str(exc.args[0]) if exc.args else "")
        except NothingToAcknowledge as exc:
            reply = Refused(call.call_id, Refusal.NOTHING_TO_ACKNOWLEDGE, str(exc), exc.state)
        except ArmNotFoundError as exc:
            reply = Refused(call.call_id, Refusal.ARM_NOT_FOUND, str(exc.args[0]) if exc.args else "")
        except ArmNotForgettableError as exc:
            reply = Refused(call.call_id, Refusal(exc.code), str(exc))
        except MirrorBusyError as exc:  # the mirror thread is working, slower than the ask's timeout
            reply = Refused(call.call_id, Refusal.BUSY, str(exc))
        except TimeoutError as exc:  # the mirror's worker thread did not get to it (Mirror._between_batches)
            reply = Refused(call.call_id, Refusal.STUCK, str(exc))
        except Exception as exc:
            log.exception("worker request %s failed", type(call.request).__name__)
            reply = Refused(call.call_id, Refusal.ERROR, f"{type(exc).__name__}: {exc}")
        try:
            with _CONTROL_SEND:
                control.send(reply)
        except (OSError, ValueError):
            return


# ------------------------------------------------------------------------------------------------ merging


def merge_reports(
    info: AgentInfo,
    reports: Sequence[MirrorReport],
    workers: tuple[WorkerInfo, ...],
    *,
    dropped: Mapping[str, int],
    dropped_total: int | None = None,
    restarting: Mapping[str, DeviceState] | None = None,
    restarting_untracked: Sequence[Mapping[str, int]] = (),
    restarting_alarms: Sequence[AlarmsSummary] = (),
    stopped_recordings: Sequence[RecordingState] = (),
) -> AgentState:
    """One fleet state from the mirrors' reports. `info` is the agent's own part (process, broker); `workers`
    its worker processes (empty when the mirror runs in-process); `dropped` the messages of each device it
    could not hand to a mirror, counted with the mirror's own queue drops (`overwritten`), and
    `dropped_total` all of them (per device only the most recent devices are kept; default: their sum).
    `restarting` are the devices of workers being started again, as their last checkpoints left them, and
    `restarting_untracked` those checkpoints' rejections of no device, `restarting_alarms` their alarm
    counts. `stopped_recordings` are the recordings of mirrors that stopped and answer no more, as their stop
    reports left them.
    """
    devices, untracked = _merge_devices(reports, dropped, restarting or {}, restarting_untracked)
    workers_alive = all(w.alive for w in workers)
    return AgentState(
        agent=dataclasses.replace(
            info,
            running=info.running and workers_alive,
            mailbox=_merge_mailbox(reports, workers, dropped, dropped_total),
            latency=_merge_latency(reports),
            worker=_merge_worker(reports, workers_alive=workers_alive),
            recording=_merge_recording(
                [*(r.recording for r in reports if r.recording is not None), *stopped_recordings]
            ),
            history=_merge_history([r.history for r in reports if r.history is not None]),
            sinks=_merge_sinks([r.sinks for r in reports]),
            alarms=_merge_alarms([r.alarms for r in reports] + list(restarting_alarms)),
            loss=fleet_loss(d.loss for d in devices.values()),
            workers=workers,
        ),
        devices=dict(sorted(devices.items())),
        untracked_rejected=dict(sorted(untracked.items())),
    )


def _merge_devices(
    reports: Sequence[MirrorReport],
    dropped: Mapping[str, int],
    restarting: Mapping[str, DeviceState],
    restarting_untracked: Sequence[Mapping[str, int]],
) -> tuple[dict[str, DeviceState], Counter[str]]:
    """Every device, with the messages the agent dropped for it, and the rejections of no device: those of
    workers being started again (their last checkpoints) first, then each mirror's."""
    devices = {}
    untracked: Counter[str] = Counter()
    for device, d in restarting.items():
        extra = dropped.get(device, 0)
        devices[device] = with_dropped(d, extra) if extra else d
    for part in restarting_untracked:
        untracked.update(part)
    for report in reports:
        for device, d in report.devices.items():
            extra = dropped.get(device, 0)
            devices[device] = with_dropped(d, extra) if extra else d
        untracked.update(report.untracked_rejected)
    return devices, untracked


def _merge_mailbox(
    reports: Sequence[MirrorReport],
    workers: tuple[WorkerInfo, ...],
    dropped: Mapping[str, int],
    dropped_total: int | None,
) -> MailboxState:
    """The mirrors' queues with the agent's hand-over: what either dropped, and what is pending in either."""
    return MailboxState(
        overwritten_total=sum(r.mailbox.overwritten_total for r in reports)
        + (sum(dropped.values()) if dropped_total is None else dropped_total),
        refused_keys=0,
        pending=sum(r.mailbox.pending for r in reports) + sum(w.queued for w in workers),
    )


def _merge_latency(reports: Sequence[MirrorReport]) -> FleetLatency:
    internal, end_to_end = LatencyHistogram(), LatencyHistogram()
    for report in reports:
        internal.merge(report.internal)
        end_to_end.merge(report.end_to_end)
    return FleetLatency(internal_s=internal.summary(), end_to_end_s=end_to_end.summary())


def _merge_worker(reports: Sequence[MirrorReport], *, workers_alive: bool) -> WorkerState:
    return WorkerState(
        alive=bool(reports) and workers_alive and all(r.worker.alive for r in reports),
        batches=sum(r.worker.batches for r in reports),
        processed=sum(r.worker.processed for r in reports),
        errors=sum(r.worker.errors for r in reports),
        stage_cpu_s=_merge_seconds([r.worker.stage_cpu_s for r in reports]),
        stage_timed_batches=sum(r.worker.stage_timed_batches for r in reports),
        alarm_rows=sum(r.worker.alarm_rows for r in reports),
        behind_s=max((r.worker.behind_s for r in reports), default=0.0),
    )


def _merge_recording(parts: list[RecordingState]) -> RecordingState | None:
    if not parts:
        return None
    # Each worker records its own devices into its own session file; `agent.workers` lists every path. A
    # worker whose session was removed as empty names none ("").
    return RecordingState(
        path=next((p.path for p in parts if p.path), ""),
        samples_written=sum(p.samples_written for p in parts),
        samples_dropped=sum(p.samples_dropped for p in parts),
        flushes=sum(p.flushes for p in parts),
        flush_errors=sum(p.flush_errors for p in parts),
        rotations=sum(p.rotations for p in parts),
        files_deleted=sum(p.files_deleted for p in parts),
    )


def _storage_ok(parts: Iterator[bool | None]) -> bool | None:
    """False if any part's commit failed, True if any worked, None while none was attempted."""
    seen = set(parts)
    return False if False in seen else True if True in seen else None


def _merge_history(parts: list[HistoryState]) -> HistoryState | None:
    if not parts:
        return None
    return HistoryState(
        uri=parts[0].uri,
        storage_ok=_storage_ok(p.storage_ok for p in parts),
        rows_committed=sum(p.rows_committed for p in parts),
        commits=sum(p.commits for p in parts),
        commit_failures=sum(p.commit_failures for p in parts),
        rows_dropped=sum(p.rows_dropped for p in parts),
        rows_buffered=sum(p.rows_buffered for p in parts),
        rejected_rows_committed=sum(p.rejected_rows_committed for p in parts),
        maintenance_runs=sum(p.maintenance_runs for p in parts),
        maintenance_failures=sum(p.maintenance_failures for p in parts),
        rows_expired=sum(p.rows_expired for p in parts),
        log_entries_set_aside=sum(p.log_entries_set_aside for p in parts),
        last_error=next((p.last_error for p in parts if p.last_error), ""),
        writer_restarts=sum(p.writer_restarts for p in parts),
        rows_received=sum(p.rows_received for p in parts),
        rows_lost=sum(p.rows_lost for p in parts),
        lag_s=max(p.lag_s for p in parts),
    )


def _merge_sinks(parts: list[tuple[SinkStats, ...]]) -> tuple[SinkStats, ...]:
    by_name: dict[str, list[SinkStats]] = {}
    for stats in parts:
        for sink in stats:
            by_name.setdefault(sink.name, []).append(sink)
    return tuple(
        SinkStats(
            name=name,
            delivered=sum(s.delivered for s in group),
            dropped=sum(s.dropped for s in group),
            errors=sum(s.errors for s in group),
            pending=sum(s.pending for s in group),
            last_error=next((s.last_error for s in group if s.last_error), ""),
            skipped=sum(s.skipped for s in group),
        )
        for name, group in by_name.items()
    )


def _merge_counts(parts: Sequence[dict[str, int]]) -> dict[str, int]:
    total: Counter[str] = Counter()
    for part in parts:
        total.update(part)
    return dict(sorted(total.items()))


def _merge_seconds(parts: Sequence[dict[str, float]]) -> dict[str, float]:
    total: dict[str, float] = {}
    for part in parts:
        for key, seconds in part.items():
            total[key] = total.get(key, 0.0) + seconds
    return total


def _merge_alarms(parts: list[AlarmsSummary]) -> AlarmsSummary:
    severities = sorted({s for p in parts for s in p.by_state})
    return AlarmsSummary(
        present=_merge_counts([p.present for p in parts]),
        by_state={s: _merge_counts([p.by_state.get(s, {}) for p in parts]) for s in severities},
        raised_total=_merge_counts([p.raised_total for p in parts]),
        cleared_total=_merge_counts([p.cleared_total for p in parts]),
        acknowledged_total=_merge_counts([p.acknowledged_total for p in parts]),
    )


__all__ = [
    "ACK_MANY_MAX",
    "ARM_CONFIGURED",
    "ARM_NOT_OFFLINE",
    "AckManyRequest",
    "AckOutcome",
    "AckRequest",
    "AckResult",
    "AckedMany",
    "Acknowledged",
    "AlarmsRequest",
    "ArmForgotten",
    "ArmNotForgettableError",
    "ArmNotFoundError",
    "CalibrationsRequest",
    "CheckpointRequest",
    "DeviceCheckpoint",
    "DeviceRow",
    "EventsReply",
    "EventsRequest",
    "FleetRowsRequest",
    "ForgetRequest",
    "MirrorCheckpoint",
    "MirrorReport",
    "PackedDevices",
    "Reply",
    "ReportRequest",
    "Request",
    "RestoreRequest",
    "Restored",
    "Shard",
    "StatusesRequest",
    "StopReport",
    "UnheardArm",
    "UnheardRequest",
    "WorkerError",
    "WorkerPlan",
    "WorkerShard",
    "acked_many_of",
    "acknowledged_of",
    "alarm_of",
    "alarms_of",
    "applied_of",
    "checkpoint_of",
    "forgotten_of",
    "merge_reports",
    "report_of",
    "restored_of",
    "statuses_of",
    "uncalibrated",
    "unheard_of",
    "worker_config",
]
