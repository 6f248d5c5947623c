"""The mirror: one share of the fleet's telemetry in, one MuJoCo twin per device, health, loss, alarms, sinks.

The agent (service.agent) receives every message and hands it to one of its shards (service.shards); each
shard runs one Mirror, in the agent's own process (`LocalShard`) or in a worker process fed through a pipe
(`PipeInbox`). The mirror is the same code either way:

    the shard's inbox (an InboundQueue, or the worker's pipe)
      --take: a batch, as columns--> worker thread, stage by stage over the batch:
        decode (and admit each new device) -> twin (DeviceTwin.apply, clock-jump check)
        -> health, latency, loss estimate, servo alarms -> sinks (USD recording, history, ...)
    the agent's threads read the twins, health and alarms under one short lock (`report()`).

Every message is decoded and counted, in arrival order, before anything is coalesced: a garbage message never
displaces a good one, and every valid message is applied (the twin computes kinematics and dynamics when they
are read, so applying costs microseconds). A batch goes through the stages one after the other (each stage
over all its messages) rather than message by message: each stage's CPU time is measured per batch, not per
message (`WorkerState.stage_cpu_s`, what `twin bench cost` splits the agent's cost by; on a sample of the
batches, scaled, since reading the thread's CPU clock costs more than a small batch: service.stagetiming), and
the lock is taken once per batch instead of once per message. A device's messages keep their order in every
stage; a batch holding two of one device's messages goes through the twin and health stages in rounds (each
device at most once a round), so its alarms see the pose of the message they evaluate. The worker owns the
decoder (not thread-safe: auto-units state) and every DeviceTwin; other threads see the twins only under the
lock. Any exception while handling one message is caught, logged (rate-limited) and counted: a bad message
never stops the mirror.

A device is admitted (gets a twin) on its first valid message, while the fleet's device budget has a place
(service.admission, `telemetry.max_devices`, shared by every mirror of the agent); a message that does not
decode takes no place.

Sinks (twin.output.sinks) receive every applied message as an `AppliedSample` and every rejected one as a
`RejectedSample`, on the worker thread, and each change of an arm's status its sweep reads as a `StatusChange`
(`_hand_statuses`); each returns at once (I/O sinks queue to a thread of their own). The history sink also
gets the valid messages the twin did not apply (late or duplicate), so it holds every decoded message. The
USD recording is one such sink; `AgentService(..., sinks=[...])` adds more.

Ordering uses the edge timestamp (DeviceTwin.apply ignores anything not newer), liveness uses the agent's
monotonic receive time (twin.core.health). The two meet in one place: when a device keeps sending valid
messages that are all older than the last applied one for a while, its edge clock has jumped backwards (an
edge without NTP rebooting, say); waiting for the clock to catch up would freeze the twin for as long as the
jump, so the device's twin is rebuilt on the new timeline and the reset is counted and logged.

Time: every reading of the clock goes through the injected `clock` (monotonic seconds: ages, latencies,
physics steps) and `wall_clock` (epoch seconds: alarm times, the recording's name); the receive stamps come
with each message. A twin counts as updated when its batch's twin stage ends (one clock reading per round).
Tests drive the mirror on a timeline of their own through the agent.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import chain
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from twin.core.alarms import (
    WAITING_STATES,
    AlarmCounters,
    AlarmEvent,
    AlarmNotFound,
    AlarmRecord,
    AlarmState,
    JointHealth,
    NothingToAcknowledge,
    ServoAlarms,
    Severity,
    what_to_do,
)
from twin.core.health import (
    DeviceHealth,
    DeviceStatus,
    FleetHealth,
    HealthReading,
    HealthSnapshot,
    HealthThresholds,
    Unheard,
)
from twin.core.latency import LatencyHistogram
from twin.core.loss import DeviceLoss, LossSnapshot
from twin.core.modes import TwinMode
from twin.core.telemetry import (
    DecoderConfig,
    JointDiagnostics,
    RejectReason,
    Telemetry,
    TelemetryDecoder,
    TelemetryRejected,
    Units,
    diagnostic_columns,
)
from twin.core.throttle import Throttle
from twin.core.twin import DeviceTwin, TwinSnapshot, holding_torques_of
from twin.output.sinks import AppliedSample, RejectedSample, StatusChange, TwinSink, rejected_sample

# This module is the heavy end of the agent (MuJoCo, USD): the agent imports it only for an in-process
# mirror, and worker processes import it; the agent with worker processes never does.
from twin.robot import so101, sts3215
from twin.robot.calibration import Calibration, load_calibration
from twin.robot.model import ModelError, RobotModel
from twin.service.admission import TOO_MANY_DEVICES, DeviceBudget
from twin.service.capture import CHUNK as CAPTURE_CHUNK
from twin.service.capture import Capture
from twin.service.config import AgentConfig, ConfigError
from twin.service.console import FleetRow, ForgetOffer, card_uncalibrated, fleet_row
from twin.service.events import Event, EventQuery, EventStore, FleetWatch, RejectionThrottle, alarm_level
from twin.service.logs import RateLimitedLog, name_native_thread, thread_stack
from twin.service.shards import (
    ALARM_NOT_FOUND_DETAIL,
    ARM_CONFIGURED,
    ARM_NOT_OFFLINE,
    EVENTS_PER_ASK,
    SINK_UNWRITTEN_SUFFIX,
    AckedMany,
    AckManyRequest,
    Acknowledged,
    AckOutcome,
    AckRequest,
    AckResult,
    AlarmsRequest,
    ArmForgotten,
    ArmNotForgettableError,
    ArmNotFoundError,
    ArmReply,
    ArmRequest,
    CalibrationsRequest,
    CheckpointRequest,
    DeviceCheckpoint,
    DeviceRow,
    EventsReply,
    EventsRequest,
    FleetRowsRequest,
    ForgetRequest,
    MirrorCheckpoint,
    MirrorReport,
    Reply,
    ReportRequest,
    Request,
    Restored,
    RestoreRequest,
    StatusesRequest,
    StopReport,
    UnheardArm,
    UnheardRequest,
    WorkerExit,
    alarm_info,
    calibration_in_use,
    uncalibrated,
)
from twin.service.stagetiming import StageSampler
from twin.service.stall import StallWatch
from twin.service.state import (
    AlarmInfo,
    AlarmsSummary,
    DeviceState,
    MailboxState,
    MirrorStatus,
    RecordingState,
    ServoState,
    WorkerInfo,
    WorkerState,
)
from twin.transport.mailbox import UNTRACKED_KEY, InboundQueue
from twin.transport.pipe import EMPTY, Batch, batch_of, read_batch
from twin.transport.plan import connection_limit

if TYPE_CHECKING:
    # pyarrow and deltalake (~70 MB resident) load only when history is on, usd-core (~80 MB) only when
    # recording: every worker process pays for what it imports.
    from twin.output.history_feed import HistoryFeed, HistoryLink, Resume, TelemetryRow
    from twin.output.recorder import SessionRecorder
    from twin.output.recording import RecordingSink

log = logging.getLogger(__name__)

Clock = Callable[[], float]
_SampleT = TypeVar("_SampleT", AppliedSample, RejectedSample, StatusChange)
_T = TypeVar("_T")

# A device whose valid messages have all been older than its last applied one for this long (and this many
# messages) has had its edge clock jump backwards: rebuild its twin on the new timeline. Reordering and
# duplicates interleave with newer messages, which end a streak long before this.
CLOCK_RESET_AFTER_S = 2.0
# A clock that stands still is rebuilt on every CLOCK_RESET_AFTER_S: its warning and event at most this often
# per device, naming how many rebuilds came between (clock_resets counts each).
CLOCK_RESET_TELL_EVERY_S = 60.0
CLOCK_RESET_MIN_MESSAGES = 5
# physics mode: at most this much simulated time per worker wake-up, so a stalled worker catches up smoothly
# instead of running seconds of simulation in one go.
MAX_PHYSICS_STEP_S = 0.1
# How often the worker wakes with nothing to do (kinematic mode): bounds the stop latency.
IDLE_WAKE_S = 0.2
# The worker thread turns its loop after every batch and, idle, every IDLE_WAKE_S (a physics step in physics
# mode), so one in-process that has not turned for this long is stuck: a sink or native call that never
# returns. The shard then counts as failed, and `twin run` exits for systemd to start it again (StallWatch).
STALL_AFTER_S = 60.0
# How long the stop of an agent with such a mirror waits for it to finish (it may have come free meanwhile).
STALLED_STOP_S = 5.0
# Python's cyclic garbage collector walks every tracked object in a full pass. At fleet scale most of them are
# the arms' own state (twins, health windows, alarm records), alive for the whole run, and a full pass held
# the worker for 60 ms at 1,000 arms (docs/performance.md). So this often the worker collects the young
# generations (their cyclic garbage, which must not be frozen) and freezes what is left (`gc.freeze`): later
# passes walk only what was allocated since. What is frozen is still freed by reference counting. New arms
# bring new state, so a batch that admitted some is followed by a freeze sooner (FREEZE_AFTER_NEW_S).
FREEZE_EVERY_S = 10.0
FREEZE_AFTER_NEW_S = 0.25
# When the oldest message of a batch has waited longer than this, the worker is behind: it still decodes and
# counts every message, but applies only each arm's newest valid one, so the twin shows the present instead
# of replaying a backlog seconds old (docs/agent.md, "Catching up").
CATCH_UP_AFTER_S = 0.05
# The queue between the MQTT threads and the worker holds at most this many messages (about 40 MB of edge
# payloads); beyond it the oldest are dropped and counted, so a stalled worker cannot exhaust memory.
MAX_QUEUED_MESSAGES = 50_000
# ... and at most this many bytes of payloads: fewer messages when they are large.
MAX_QUEUED_BYTES = 64 * 2**20


# A message in the shard queue of an in-process mirror: topic, payload, receive monotonic and wall time.
QueuedMessage = tuple[str, bytes, float, float]
# The stages of a batch, in order (module doc); `WorkerState.stage_cpu_s` has the CPU seconds of each.
STAGES = ("hand_over", "decode", "twin", "health_alarms", "sinks")


def _no_cpu_clock() -> float:
    """The stage timers' clock on a batch that is not timed: reads nothing (the real one is a system call)."""
    return 0.0


def _span(start: float, end: float, read: float) -> float:
    """CPU seconds between two readings of the stage timers' clock, less one reading's own cost (`read`,
    measured by two readings in a row), never below 0. Under load the thread can be charged CPU between those
    two readings (an accounting tick, an interrupt), so `read` can exceed a short span; scaled by the sampling
    weight, one such span outweighed a short run's whole stage (`twin bench cost` reported negative CPU)."""
    spent = end - start - read
    return spent if spent > 0.0 else 0.0


class _Device:
    """What the worker keeps per admitted device, in one place so a message finds all of it in one lookup:
    its twin, health record and loss estimator, the clock-jump streak, and what /state shows of its last
    message. Written by the worker under the mirror's lock; read by `report()` under it."""

    __slots__ = (
        "device",
        "diagnostics",
        "gripper_percent",
        "health",
        "loss",
        "reset_how",
        "reset_words",
        "stale_since",
        "stale_streak",
        "twin",
        "units",
    )

    def __init__(self, device: str, twin: DeviceTwin, health: DeviceHealth, loss: DeviceLoss) -> None:
        self.device = device
        self.twin = twin
        self.health = health
        self.loss = loss
        self.stale_streak = 0
        self.stale_since = 0.0
        # The clock reset's word (CLOCK_RESET_TELL_EVERY_S), made at the first reset, and its kind.
        self.reset_words: Throttle | None = None
        self.reset_how = ""
        self.gripper_percent: float | None = None
        self.units: Units | None = None
        self.diagnostics: Mapping[str, JointDiagnostics] | None = None


# One decoded message of a batch: its index in the batch, its telemetry, its device's record.
_Decoded = tuple[int, Telemetry, _Device]


# A device's last diagnostics, the alarm engine's JointHealth and worst (severity, state) per joint.
_ServoReadout = tuple[
    Mapping[str, JointDiagnostics], dict[str, JointHealth], dict[str, tuple[Severity, AlarmState]]
]


@dataclass(frozen=True, slots=True)
class _Readout:
    """Everything `report()` copies under the lock, to build the typed report outside it."""

    now: float
    health: dict[str, HealthReading]
    snapshots: dict[str, TwinSnapshot]
    units: dict[str, Units]
    gripper: dict[str, float | None]
    untracked: dict[str, int]
    batches: int
    processed: int
    stage_cpu_s: dict[str, float]
    stage_timed_batches: int
    alarm_rows: int
    internal: LatencyHistogram
    end_to_end: LatencyHistogram
    servos: dict[str, _ServoReadout]
    alarms: AlarmsSummary
    loss: dict[str, LossSnapshot]
    # An arm page's (`_read` of one device): whether it may be forgotten, on the clock its status was read on.
    forget: ForgetOffer | None = None


class _Job:
    """Work another thread hands the worker thread, done between two batches (a checkpoint, a restore), so it
    sees the mirror exactly as the messages taken so far left it."""

    def __init__(self, fn: Callable[[], object]) -> None:
        self.fn = fn
        self.done = threading.Event()
        self.result: object = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self.result = self.fn()
        except BaseException as exc:  # handed back to the caller, on its own thread
            self.error = exc
        finally:
            self.done.set()


# How long a checkpoint or a restore may wait for the worker thread to finish its batch.
JOB_TIMEOUT_S = 10.0


class MirrorBusyError(TimeoutError):
    """A wait for the worker thread timed out while it went on handling batches: slow (a starved host, a
    checkpoint taken over many batches), not stuck. The agent does not count it towards killing the worker
    as hung (service.shards, Refusal.BUSY), which would add a restart's replay to the load that slowed it."""


def _timed_out(what: str, batches: tuple[int, int], timeout: float = JOB_TIMEOUT_S) -> TimeoutError:
    """The error of a wait for the worker thread that ran out after `timeout`: MirrorBusyError when it
    handled batches meanwhile (`batches`: its count when the wait began, and now)."""
    before, now = batches
    if now != before:
        return MirrorBusyError(
            f"{what} within {timeout:.0f} s; it handled {now - before} batches meanwhile: busy, not stuck"
        )
    return TimeoutError(f"{what} within {timeout:.0f} s")


# Arms of the console's Fleet page read per hold of the mirror's lock (Mirror.fleet_rows): about 2-6 ms.
FLEET_ROWS_CHUNK = 100
# How long an acknowledgement or a forget waits for the checkpoint taken with it: well inside the agent's wait
# for the answer (shards.ASK_TIMEOUT_S), so the act, done by then, is answered as done. Without it the act is
# still in the state file, and the supervisor's next checkpoint holds it.
ACT_CHECKPOINT_S = 5.0


class QueueInbox:
    """An in-process mirror's inbox: the shard's InboundQueue, taken as batches. Made with `opened=False`
    it hands over nothing until `open()` (or `close()`, which drains): messages wait in the queue."""

    def __init__(self, queue: InboundQueue[QueuedMessage], *, opened: bool = True) -> None:
        self.queue = queue
        self._opened = threading.Event()
        if opened:
            self._opened.set()

    def take(self, timeout: float | None = None) -> Batch:
        opened = self._opened
        if not opened.is_set() and not opened.wait(timeout):
            return EMPTY  # the worker loop runs its jobs (a restore, say) meanwhile
        return batch_of(self.queue.take_all(timeout))

    def open(self) -> None:
        self._opened.set()

    def close(self) -> None:
        self.queue.close()
        self._opened.set()

    @property
    def closed(self) -> bool:
        return self.queue.closed

    def __len__(self) -> int:
        return len(self.queue)

    @property
    def overflowed(self) -> dict[str, int]:
        return self.queue.overflowed

    def forget(self, device: str) -> None:
        self.queue.forget(device)

    @property
    def overflowed_total(self) -> int:
        return self.queue.overflowed_total


class PipeInbox:
    """A worker process's inbox: the batches the agent wrote to its pipe (service.shards), read by the worker
    thread itself, so no thread or queue sits between.

    The batches' format is transport.pipe's. The agent's queue for this worker is bounded and counts what it
    drops, so nothing here overflows (the pipe holds back the writer instead)."""

    # Read at most this many messages per take: a backlog reaches the worker's catch-up check in pieces.
    MAX_TAKE = 5_000

    def __init__(self, conn: Connection) -> None:
        self._conn = conn
        self._closed = False

    def take(self, timeout: float | None = None) -> Batch:
        if self._closed:
            return EMPTY
        conn = self._conn
        batches: list[Batch] = []
        taken = 0
        try:
            if not conn.poll(timeout):
                return EMPTY
            while True:
                batch = read_batch(conn.recv_bytes())
                if batch is None:
                    self._closed = True
                    break
                batches.append(batch)
                taken += len(batch.payloads)
                if taken >= self.MAX_TAKE or not conn.poll(0):
                    break
        except (EOFError, OSError):
            log.warning("the agent went away; worker stopping")
            self._closed = True
        if len(batches) == 1:
            return batches[0]
        if not batches:
            return EMPTY
        return Batch(*(tuple(chain.from_iterable(columns)) for columns in zip(*batches, strict=True)))

    def close(self) -> None:
        self._closed = True

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        return 0  # what waits in the pipe is the agent's to count (its queue for this worker)

    @property
    def overflowed(self) -> dict[str, int]:
        return {}

    def forget(self, device: str) -> None:
        return  # the agent's queue for this worker counts the drops (WorkerShard.forget)

    @property
    def overflowed_total(self) -> int:
        return 0


Inbox = QueueInbox | PipeInbox


class Mirror:
    """The mirror path for one share of the fleet (module doc), on a worker thread of its own.

    `start()` opens the sinks and starts the worker thread; the thread ends once the inbox is closed and
    drained; `stop()` (idempotent) closes the inbox, waits for the thread and closes the sinks (the USD
    recording's last save, the rows still for history handed to its writer process). `report()`, `alarms()`
    and `acknowledge_alarm()` may be called from any thread. `sinks` are extra outputs; the mirror closes
    them in `stop()`. `slot` is this mirror's slot in the device budget (its shard's index). `history` is
    where the agent's history writer process listens (needed when the config turns history on).
    `cpu_clock` (the worker thread's CPU time) and `stage_sampler` are the stage timers' clock and which
    batches read it (service.stagetiming); tests inject them.
    """

    def __init__(
        self,
        config: AgentConfig,
        *,
        inbox: Inbox,
        budget: DeviceBudget,
        slot: int = 0,
        clock: Clock = time.monotonic,
        wall_clock: Clock = time.time,
        sinks: Sequence[TwinSink] = (),
        history: HistoryLink | None = None,
        cpu_clock: Clock = time.thread_time,
        stage_sampler: StageSampler | None = None,
    ) -> None:
        if config.history.enabled and history is None:
            raise ValueError("history is on: the mirror needs the link to the agent's history writer process")
        # Everything that can be wrong with the configuration is found here, before any thread.
        self.config = config
        self._clock = clock
        self._wall_clock = wall_clock
        # The stage timers' clock (the worker thread's CPU time) and which turns read it (tests inject both).
        self._cpu_clock = cpu_clock
        self._stage_sampler = stage_sampler if stage_sampler is not None else StageSampler()
        self._decoder = TelemetryDecoder(self._decoder_config(config))
        # Each arm's own calibration (the agent hands them over: set_calibrations): where it came from, and
        # why a newer file of it was refused; the config's file is every other arm's.
        self._calibration_sources: dict[str, str] = {}
        self._calibration_problems: dict[str, str] = {}
        # The edge stamp of each held arm's newest servo readings judged (_watch_held); at most one entry an
        # arm with a refused file in the store.
        self._held_stamps: dict[str, int] = {}
        self.mode = TwinMode(config.twin.mode)
        self.robot = self._load_robot(config, self.mode)
        # The alarm engine takes a round's poses as rows in the contract's joint order (so101.JOINT_NAMES):
        # the bundled model's. A model of its own order is evaluated message by message.
        self._joint_order_is_the_contracts = tuple(self.robot.joint_names) == tuple(so101.JOINT_NAMES)
        self._history_link = history if config.history.enabled else None
        self._budget = budget
        self._slot = slot
        self._init_fleet_state(config, clock)
        self._mailbox = inbox
        self._recording: RecordingSink | None = None
        self._history: HistoryFeed | None = None
        # The feed the stages hand rows to (worker thread only): the history feed, or None while the batch
        # holds messages sent again after a restart whose rows the dead worker delivered, which end at
        # stream position `_history_from` (`_handle_batch`).
        self._rows: HistoryFeed | None = None
        self._history_from = 0
        self._extra_sinks: tuple[TwinSink, ...] = tuple(sinks)
        self._sinks: tuple[TwinSink, ...] = ()
        # The sinks' `status` methods, and each arm's status as last handed to them (worker thread only).
        self._status_sinks: tuple[tuple[TwinSink, Callable[[StatusChange], None]], ...] = ()
        self._sinks_saw: dict[str, DeviceStatus] = {}
        self._worker: threading.Thread | None = None
        self._stopped = False
        self._stop_lock = threading.Lock()
        self._jobs: deque[_Job] = deque()
        self._capture: Capture | None = None  # a checkpoint being taken (worker thread only)

    def _init_fleet_state(self, config: AgentConfig, clock: Clock) -> None:
        """What the worker writes per device and the agent's threads read, and the lock that guards it."""
        t = config.telemetry
        self._fleet = FleetHealth(config.health, () if t.all_devices else t.devices, clock=clock)
        self._devices: dict[str, _Device] = {}
        # The arms listed for their kept alarms that hold a place in the device budget though not heard since
        # (`_hold_place`): a first message of one takes no second place, forgetting it gives that one back.
        self._kept_places: set[str] = set()
        # Servo alarms: evaluated by the worker, read (and acknowledged) by the agent's threads, all under the
        # lock.
        self._alarms = ServoAlarms(config.alarms)
        self._alarms_on = config.alarms.enabled
        # Loss estimators by device: an admitted device's is also in its record; a configured device that
        # only sent rejected messages has one too (its rejections offset the holes they leave).
        self._loss: dict[str, DeviceLoss] = {}
        self._lock = threading.Lock()
        self._stage_cpu = dict.fromkeys(STAGES, 0.0)
        self._stage_timed_batches = 0
        self._reject_log = RateLimitedLog(log, interval_s=10.0, clock=clock)
        self._error_log = RateLimitedLog(log, interval_s=10.0, clock=clock)
        # The twin's events (the console's Events page): this mirror's, which the agent collects.
        self._events = EventStore(config.twin.events_capacity, wall_clock=self._wall_clock)
        self._watch = FleetWatch(
            self._events,
            health=config.health,
            connection_limit=connection_limit(config.broker),
        )
        self._rejections = RejectionThrottle(self._events, clock=clock)
        self.batches = 0
        # Loop turns of the worker thread, idle ones too: whether it is stuck (LocalShard.supervise).
        self.turns = 0
        # Fleet-wide distributions since start (every applied message of every device), for `twin bench`
        # and capacity questions; the per-device windows in health answer "how is this arm doing now".
        self._internal_hist = LatencyHistogram()
        self._end_to_end_hist = LatencyHistogram()
        self.processed = 0
        self.alarm_rows = 0
        self.errors = 0
        # How far behind its input the worker stood at its last status sweep (_watch_statuses): the readers
        # read the arms' statuses and rates there too, so a host short of CPU shows no arm STALE whose
        # messages are only waiting. And the receive time of the oldest message of the batch it is handling
        # (None between batches): the lag shown (`behind_s`) is read from both when asked, so a worker stuck
        # in one batch shows it growing, not the figure of the sweep before it. Written by the worker thread
        # alone: the first at each sweep, the second as each batch begins and ends. A reader reads each one
        # whole (a float or None), so no lock is needed.
        self._swept_behind_s = 0.0
        self._handling_since: float | None = None

    @staticmethod
    def _load_robot(config: AgentConfig, mode: TwinMode) -> RobotModel:
        try:
            robot = RobotModel.load(config.twin.model or None)
            if mode is TwinMode.PHYSICS:
                robot.require_actuators()
        except ModelError as exc:
            raise ConfigError(f"twin.model = {config.twin.model!r}: {exc}") from exc
        return robot

    @staticmethod
    def _decoder_config(config: AgentConfig) -> DecoderConfig:
        t = config.telemetry
        try:
            calibration = load_calibration(t.calibration) if t.calibration else None
        except ValueError as exc:
            raise ConfigError(f"telemetry.calibration = {t.calibration!r}: {exc}") from exc
        try:
            return DecoderConfig(
                units=Units(t.units), calibration=calibration, max_payload_bytes=t.max_payload_bytes
            )
        except ValueError as exc:
            raise ConfigError(f"[telemetry]: {exc}") from exc

    # -------------------------------------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Open the sinks, then start the worker thread. OSError when history cannot open its table."""
        if self._worker is not None:
            return
        self._open_sinks()
        self._worker = threading.Thread(target=self._work, name="twin-worker", daemon=True)
        self._worker.start()
        log.info(
            "mirror started",
            extra={
                "mode": self.mode,
                "units": self.config.telemetry.units,
                "recording": str(self._recording.path) if self._recording else None,
                "history": self.config.history.uri if self._history else None,
                "sinks": [sink.name for sink in self._sinks],
            },
        )

    def _open_sinks(self) -> None:
        """The service's own sinks (the USD recording) before the extra ones, and the feed of the history
        writer process."""
        if self.config.twin.record_dir:
            # usd-core only when recording
            from twin.output.recording import RecordingLimits, RecordingSink  # noqa: PLC0415

            tw = self.config.twin
            directory = Path(tw.record_dir)
            self._recording = RecordingSink(
                self._first_recorder(directory),
                self.robot,
                limits=RecordingLimits(
                    max_bytes=int(tw.record_max_mb * 2**20),
                    max_age_s=tw.record_max_age_s,
                    budget_bytes=int(tw.record_budget_mb * 2**20),
                    rate_hz=tw.record_rate_hz,
                ),
                open_next=lambda n: self._open_recorder(directory, n),
            )
        if self._history_link is not None:
            from twin.output.history_feed import REJECTED_PAYLOAD_MAX_BYTES, HistoryFeed  # noqa: PLC0415

            self._history = HistoryFeed(
                self._history_link,
                max_pending=self.config.history.queue_max,
                payload_max_bytes=REJECTED_PAYLOAD_MAX_BYTES,
                slot=self._slot,
            )
            self._rows = self._history
            # Marked from the start: the feed never hands over part of a batch unrecorded (HistoryFeed.mark).
            self._history.mark(self.processed)
        self._sinks = (*((self._recording,) if self._recording else ()), *self._extra_sinks)
        # Looked up, not assumed: a sink written before statuses were handed over has no `status`.
        self._status_sinks = tuple(
            (sink, method) for sink in self._sinks if (method := getattr(sink, "status", None)) is not None
        )

    def _first_recorder(self, directory: Path) -> SessionRecorder:
        """The first session; on a disk with no room for it, one set aside that the sink replaces once
        there is room (the recording must not keep the worker, and its arms, from starting)."""
        from twin.output.recorder import MIN_FREE_FOR_SAVE_BYTES, SessionRecorder  # noqa: PLC0415

        try:
            return self._open_recorder(directory)
        except OSError as exc:
            try:
                st = os.statvfs(directory)
            except OSError:
                raise exc from None
            if st.f_bavail * st.f_frsize >= MIN_FREE_FOR_SAVE_BYTES:
                raise  # not a full disk: a setting to fix, said at the start
            log.error(
                "recording: no session could be begun (%s); mirroring goes on, its samples are dropped and "
                "counted, and the recording begins once %s has room",
                exc,
                directory.absolute(),
            )
            return SessionRecorder.not_begun(self._session_path(directory))

    def _session_path(self, directory: Path, rotation: int = 0) -> Path:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(self._wall_clock()))
        suffix = f"-{rotation}" if rotation else ""
        return directory / f"session-{stamp}-{os.getpid()}{suffix}.{self.config.twin.record_format}"

    def _open_recorder(self, directory: Path, rotation: int = 0) -> SessionRecorder:
        """A new session file: session-<UTC time>-<pid>.<format>, and -<n> after it for the n-th rotation."""
        from twin.output.recorder import SessionRecorder  # noqa: PLC0415 - usd-core only when recording

        path = self._session_path(directory, rotation)
        return SessionRecorder(path, flush_interval_s=self.config.twin.record_flush_s)

    def join(self, timeout: float | None = None) -> None:
        """Wait until the worker thread has ended (the inbox closed and drained)."""
        if self._worker is not None:
            self._worker.join(timeout)

    def stop(self, timeout: float = 30.0) -> StopReport:
        """Close the inbox, let the worker handle what it holds, close the sinks (final USD save, the rows
        for history handed to its writer process), all within `timeout` seconds; returns what could not be
        written. Idempotent."""
        deadline = time.monotonic() + timeout
        with self._stop_lock:
            if self._stopped:
                return self.stop_report()
            self._stopped = True
        self._mailbox.close()
        if self._worker is not None:
            # The worker takes what is left, then sees the closed, empty inbox and returns.
            self._worker.join(max(0.1, deadline - time.monotonic()))
            if self._worker.is_alive():
                log.error("twin worker did not finish within %.1f s", timeout)
        self._close_sinks(deadline)
        return self.stop_report()

    def _close_sinks(self, deadline: float) -> None:
        """Close every sink, the recording first, each with what is left of the time until `deadline`; then
        the history feed (its rows go to the writer process, which commits them once every feed has
        closed)."""
        sinks = self._sinks or (*((self._recording,) if self._recording else ()), *self._extra_sinks)
        for sink in sinks:
            try:
                sink.close(max(1.0, deadline - time.monotonic()))
            except Exception:
                log.exception("closing sink %s failed", sink.name)
        if self._history is not None:
            self._history.close(max(1.0, deadline - time.monotonic()))

    def stop_report(self) -> StopReport:
        """After `stop`: what the sinks could not write (every sink's queued items, the rows for history
        the feed could not hand to the writer process) and the alarms a restart must not forget. The writer
        process says itself what it could not commit (service.agent)."""
        unwritten: dict[str, int] = {}
        for sink in self._sinks:
            pending = sink.stats().pending
            if pending:
                unwritten[sink.name + SINK_UNWRITTEN_SUFFIX] = pending  # samples and status changes
        if self._history is not None:
            pending = self._history.stats().pending
            if pending:
                unwritten["history_rows"] = pending
        with self._lock:
            alarms = tuple(self._alarms.records())
        events = tuple(self._events.after(max(0, self._events.last_id - EVENTS_PER_ASK)))
        return StopReport(
            unwritten=unwritten, alarms=alarms, events=events, recording=self._recording_state()
        )

    @property
    def running(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    @property
    def wake_s(self) -> float:
        """How long the worker thread waits for a batch before it turns its loop anyway: a physics step, or
        IDLE_WAKE_S."""
        return 1.0 / self.config.twin.physics_rate_hz if self.mode is TwinMode.PHYSICS else IDLE_WAKE_S

    def worker_stack(self) -> str:
        """Where the worker thread is now, as a traceback prints it ("" when it does not run): what a stuck
        one waits in."""
        return thread_stack(self._worker)

    @property
    def recording_path(self) -> Path | None:
        """The newest session file on disk (None once none is: one with no sample is removed at close)."""
        path = self._recording.totals().path if self._recording is not None else ""
        return Path(path) if path else None

    @property
    def sinks(self) -> tuple[TwinSink, ...]:
        """The sinks in use (the recording first, when there is one); empty before start()."""
        return self._sinks

    # ------------------------------------------------------------------------------------------ worker

    def _work(self) -> None:
        name_native_thread()
        physics = self.mode is TwinMode.PHYSICS
        wake = self.wake_s
        last_step = last_freeze = self._clock()
        frozen_devices = 0
        inbox = self._mailbox
        stage_cpu = self._stage_cpu
        sampler = self._stage_sampler
        cpu = self._cpu_clock
        while True:
            self.turns += 1
            # The stage timers read the thread's CPU clock (a system call here) only on sampled turns
            # (service.stagetiming); the others read no clock for them at all.
            sampled = sampler.sample()
            if sampled:
                # Each timed span holds one reading's own cost (_handle says why it is taken off).
                before = cpu()
                started = cpu()
                batch = inbox.take(wake)
                stage_cpu["hand_over"] += _span(started, cpu(), started - before) * sampler.weight
            else:
                batch = inbox.take(wake)
            count = len(batch.payloads)
            if not count and inbox.closed:
                self._run_jobs()
                self._finish_capture()
                return
            if count:
                # The oldest message not yet handled, until the batch is (`behind_s`): no clock read here.
                self._handling_since = batch.recv_mono[0]
                try:
                    self._handle_batch(batch, sampler.batch_weight(sampled, count))
                except Exception:  # every stage guards its messages; this guards the mirror itself
                    self._count_error(None, "handling a batch failed")
                finally:
                    self._handling_since = None
            if physics:
                now = self._clock()
                self._step_physics(min(now - last_step, MAX_PHYSICS_STEP_S))
                last_step = now
            self._publish(count)
            # Where the worker stands in its input: its newest receive time (_watch_statuses).
            self._watch_statuses(batch.recv_mono)
            if self._jobs:
                self._run_jobs()
            if self._capture is not None:
                # With nothing arriving, the rest at once; otherwise a chunk a turn (service.capture).
                self._step_capture(self._capture, CAPTURE_CHUNK if count else None)
            since = self._clock() - last_freeze
            grown = len(self._devices) != frozen_devices
            if since >= FREEZE_EVERY_S or (grown and since >= FREEZE_AFTER_NEW_S):
                gc.collect(1)
                gc.freeze()
                last_freeze = self._clock()
                frozen_devices = len(self._devices)

    def _run_jobs(self) -> None:
        while self._jobs:
            self._jobs.popleft().run()

    def _between_batches(self, fn: Callable[[], _T], timeout: float = JOB_TIMEOUT_S) -> _T:
        """`fn()` on the worker thread between two batches (at once when it does not run, or when called on
        it); TimeoutError when the worker does not get to it within `timeout`."""
        worker = self._worker
        if worker is None or not worker.is_alive() or threading.current_thread() is worker:
            return fn()
        job = _Job(fn)
        batches = self.batches
        self._jobs.append(job)
        if not job.done.wait(timeout):
            what = "the mirror's worker did not get to the request"
            raise _timed_out(what, (batches, self.batches), timeout)
        if job.error is not None:
            raise job.error
        return job.result  # type: ignore[return-value]

    # --------------------------------------------------------------------------------------- checkpoints

    def checkpoint(self, *, alarms_only: bool = False) -> MirrorCheckpoint:
        """The mirror's state between two batches (service.shards, `MirrorCheckpoint`). The arms' rows are
        taken over the batches that follow, each as it was at that point (service.capture); this returns
        once the last is taken, within JOB_TIMEOUT_S."""
        if alarms_only:
            return self._between_batches(self._alarms_checkpoint)
        deadline = time.monotonic() + JOB_TIMEOUT_S
        batches = self.batches
        return self._captured(self._between_batches(self._begin_capture), deadline, batches)

    def _captured(self, capture: Capture, deadline: float, batches: int | None = None) -> MirrorCheckpoint:
        """The checkpoint `capture` takes over the batches that follow, once taken (by `deadline`; `batches`:
        the worker's count when the wait began, None for now)."""
        before = self.batches if batches is None else batches
        if not capture.done.wait(max(0.0, deadline - time.monotonic())):
            raise _timed_out("the mirror's worker did not take its checkpoint", (before, self.batches))
        if capture.error is not None:
            raise capture.error
        assert capture.result is not None  # set with done, unless error is
        return capture.result

    def _alarms_checkpoint(self) -> MirrorCheckpoint:
        with self._lock:
            alarms = tuple(self._alarms.records())
            counters = _copy_counters(self._alarms.counters)
        return MirrorCheckpoint(alarms=alarms, alarm_counters=counters, at=self._clock())

    def _begin_capture(self, *, spread: bool | None = None) -> Capture:
        """Between two batches (or with the worker stopped): fix `taken` and copy what is not per arm. With
        `spread` (None: when called on the running worker thread) the worker takes the arms' rows over the
        batches that follow (`_step_capture`, `_before_batch`), otherwise all of them now. A checkpoint asked
        for while one is being taken is that one."""
        if self._capture is not None:
            return self._capture
        with self._lock:
            alarms = tuple(self._alarms.records())
            counters = _copy_counters(self._alarms.counters)
            decided = self._decoder.decided_units()
            head = MirrorCheckpoint(
                taken=self.processed,
                errors=self.errors,
                batches=self.batches,
                at=self._clock(),
                untracked_rejected=dict(self._fleet.untracked_rejected),
                alarms=alarms,
                alarm_counters=counters,
                tracking_since=self._fleet.started,
                alarms_summary=self._alarms_summary(),
                crowded=self._watch.crowded,
                slow=self._watch.slow,
                losing=self._watch.losing,
                clocks_off=self._watch.clocks_off,
                flapping=self._watch.flapping,
                kept=self._fleet.kept,
                history_rows=self._history.handed_in_all if self._history is not None else 0,
                idle_alarms=tuple(self._alarms.idle()),
                unheard=self._unheard_locked(),
            )
            capture = Capture(
                head, list(self._fleet.devices), lambda device: self._checkpoint_row(device, decided)
            )
        if spread is None:
            worker = self._worker
            spread = worker is not None and worker.is_alive() and threading.current_thread() is worker
        if spread:
            self._capture = capture
        else:
            self._step_capture(capture, None)
        return capture

    def _finish_capture(self) -> None:
        """On the worker thread: take the rest of the checkpoint being taken, if there is one, now."""
        if self._capture is not None:
            self._step_capture(self._capture, None)

    def _step_capture(self, capture: Capture, limit: int | None) -> None:
        """On the worker thread: take `limit` more rows of `capture` (None: all that are left)."""
        try:
            with self._lock:
                done = capture.step(limit)
        except Exception as exc:  # handed to the caller waiting for the checkpoint
            log.exception("taking a checkpoint failed")
            capture.fail(exc)
            done = True
        if done and self._capture is capture:
            self._capture = None

    def _checkpoint_row(self, device: str, decided: Mapping[str, Units]) -> DeviceRow:
        """One arm's row as it is now (plain values, copies: nothing the worker changes next reaches them)."""
        health = self._fleet.devices[device]
        record = self._devices.get(device)
        loss = self._loss.get(device)
        units = decided.get(device)
        return (
            device,
            health.checkpoint_row(),
            loss.state() if loss is not None else None,
            units.value if units is not None else None,
            record.twin.last_timestamp_ms if record is not None else None,
            record.twin.targets if record is not None else None,
            record.gripper_percent if record is not None else None,
        )

    def restore(
        self,
        checkpoint: MirrorCheckpoint | None,
        alarms: Sequence[AlarmRecord] = (),
        history: Resume | None = None,
    ) -> Restored:
        """Take back a checkpoint of this mirror's previous process and alarms kept over a restart of the
        agent, and where its history takes up (`history`: the messages sent again whose rows the previous
        process delivered), before the first message; between batches on the worker thread."""
        return self._between_batches(lambda: self._restore(checkpoint, tuple(alarms), history))

    def _restore(
        self, checkpoint: MirrorCheckpoint | None, alarms: tuple[AlarmRecord, ...], history: Resume | None
    ) -> Restored:
        if history is not None and self._history is not None:
            self._history.resume(history.rows)
            self._history_from = history.skip_to
        devices = 0
        with self._lock:
            if checkpoint is not None:
                self.processed = checkpoint.taken
                self.errors = checkpoint.errors
                self.batches = checkpoint.batches
                self._fleet.untracked_rejected.update(checkpoint.untracked_rejected)
                # Processes of one host share the monotonic clock: `last_s` was counted back from `at`.
                self._fleet.restore_unheard(
                    (a.device, Unheard(a.rejected, a.reason, checkpoint.at - a.last_s))
                    for a in reversed(checkpoint.unheard)
                )
                self._alarms.restore_counters(checkpoint.alarm_counters)
                for device, saved in checkpoint.devices.items():
                    self._restore_device(device, saved)
                    devices += 1
                restored = self._alarms.restore(checkpoint.alarms)
                self._alarms.restore_idle(checkpoint.idle_alarms, checkpoint.at)
                self._watch.crowded_restored(checkpoint.crowded, self._clock(), checkpoint.slow)
                self._watch.losing_restored(checkpoint.losing)
                self._watch.clocks_restored(checkpoint.clocks_off)
                self._watch.flapping_restored(checkpoint.flapping)
            else:
                restored = 0
            restored += self._alarms.restore(alarms)
            # An arm with alarms kept by the state file is listed before it is heard again (FleetHealth.keep),
            # also by a worker started again after it died (its checkpoint names them).
            kept = checkpoint.kept if checkpoint is not None else ()
            for device in sorted({r.device for r in alarms}.union(kept)):
                self._fleet.keep(device)
                self._hold_place(device)
        if checkpoint is not None:
            self._decoder.restore_units(
                {device: saved.units for device, saved in checkpoint.devices.items() if saved.units}
            )
        if devices or restored:
            log.info("mirror state restored", extra={"devices": devices, "alarms": restored})
        return Restored(devices=devices, alarms=restored)

    def _hold_place(self, device: str) -> None:
        """Under the lock: a place in the device budget for an arm listed for its kept alarms, as an arm heard
        holds one. Without it every restart under a churning fleet let up to `telemetry.max_devices` new
        arms in beside the ones the state file kept, whose alarms the next state file kept again: the
        tables and the file grew with every id ever seen. With no place left it is listed all the same (its
        alarms are for a person to see), and takes a place when it is heard, as a new arm does."""
        if device in self._devices or device in self._kept_places:
            return
        if self._budget.take(self._slot):
            self._kept_places.add(device)

    def _restore_device(self, device: str, saved: DeviceCheckpoint) -> None:
        """Under the lock: one device's counters, loss estimate and twin (from its last applied pose)."""
        health = self._fleet.device(device)
        health.restore(saved.health)
        self._watch.restored(device)
        if saved.loss is not None:
            self._loss[device] = DeviceLoss.from_state(saved.loss, self._clock)
        if saved.timestamp_ms is None or saved.targets_rad is None or device in self._devices:
            return
        if not self._budget.take(self._slot):
            return  # the place went to another worker's device meanwhile: it is admitted anew, if at all
        twin = DeviceTwin(self.robot, device, self.mode)
        twin.apply(saved.targets_rad, saved.timestamp_ms)
        record = self._devices[device] = _Device(device, twin, health, self._loss_of(device))
        record.gripper_percent = saved.gripper_percent
        record.units = saved.units

    def _step_physics(self, elapsed: float) -> None:
        with self._lock:
            for device, record in self._devices.items():
                try:
                    record.twin.step(elapsed)
                except Exception:
                    self._count_error(device, "physics step failed", locked=True)

    def _publish(self, count: int) -> None:
        """The batch's message count, and the queue's drop counts, for the readers (after every stage, so a
        reader that sees `processed` grow sees all those messages handled)."""
        # Only devices whose messages the queue dropped have a count to copy (a full queue is rare).
        overwritten = self._mailbox.overflowed if self._mailbox.overflowed_total else {}
        with self._lock:
            for key, n in overwritten.items():
                health = self._fleet.get(key)
                if health is not None:
                    health.overwritten = n
            if count:
                self.batches += 1
                self.processed += count

    # ------------------------------------------------------------------------------------- the stages

    def _handle_batch(self, batch: Batch, weight: float) -> None:
        """One batch (`_handle`), then its mark in the history feed (once per batch: HistoryFeed.mark). After
        a restart, the messages sent again up to `_history_from` go through every stage but history's: the
        dead worker's feed delivered their rows (a batch reaching past it is handled in two parts)."""
        start = self.processed
        count = len(batch.payloads)
        delivered = self._history_from - start
        if delivered <= 0:
            self._handle(batch, weight)
        else:
            rows, self._rows = self._rows, None
            try:
                self._handle(_sliced(batch, 0, delivered) if delivered < count else batch, weight)
            finally:
                self._rows = rows
            if delivered < count:
                self._handle(_sliced(batch, delivered, count), weight)
        history = self._history
        if history is not None:
            history.mark(start + count)

    def _handle(self, batch: Batch, weight: float) -> None:
        """One batch through the stages (module doc). Never raises. Its stages are timed when `weight` is not
        0, each figure counting `weight` times (service.stagetiming); otherwise no CPU clock is read."""
        if weight:
            cpu = self._cpu_clock
            self._stage_timed_batches += 1
        else:
            cpu = _no_cpu_clock
        stage_cpu = self._stage_cpu
        # Every timed span holds about one clock reading's own cost (the end of the reading that opens it and
        # the start of the one that closes it). Timing every batch paid it every time; a sampled batch's
        # figures are scaled up, and with them that cost, which the untimed batches no longer pay: left in,
        # the scaled stages overstated the worker's CPU at batches of one (docs/performance.md). Two
        # readings in a row measure it; it is taken off each span.
        capture = self._capture
        if capture is not None:
            self._before_batch(capture, batch.keys)
        before = cpu()
        started = cpu()
        read = started - before
        admitted: set[int] = set()
        # The loss estimators see the batch in arrival order, valid and rejected messages alike (a rejection
        # only offsets a hole after the device's first valid sample), so they are fed here, once decoding has
        # found which is which, under one hold of the lock.
        losses: list[tuple[DeviceLoss, int | None]] = []
        decoded = self._decode_all(batch, admitted, losses)
        behind = self._clock() - batch.recv_mono[0] > CATCH_UP_AFTER_S
        if behind and len(decoded) > 1:
            decoded = self._catch_up(decoded, batch, admitted)
        decoded_at = cpu()
        stage_cpu["decode"] += _span(started, decoded_at, read) * weight
        if losses:
            with self._lock:
                now = self._clock()
                for loss, timestamp_ms in losses:
                    if timestamp_ms is None:
                        loss.record_rejected()
                    else:
                        loss.observe(timestamp_ms, now)
            stage_cpu["health_alarms"] += _span(decoded_at, cpu(), read) * weight
        for entries in _rounds(decoded):
            started = cpu()
            with self._lock:
                applied = self._apply_all(entries, batch)
                updated = self._clock()
                twin_done = cpu()
                stage_cpu["twin"] += _span(started, twin_done, read) * weight
                events = self._record_all(entries, applied, updated, batch)
            started = cpu()
            stage_cpu["health_alarms"] += _span(twin_done, started, read) * weight
            for message_events in events:
                for event in message_events:
                    self._tell_alarm(event)
            if self._sinks or self._rows is not None:
                self._hand_all(entries, applied, events, batch)
                stage_cpu["sinks"] += _span(started, cpu(), read) * weight

    def _before_batch(self, capture: Capture, keys: Sequence[str]) -> None:
        """Copy before write: the checkpoint rows of the batch's arms that are still to take. A message on a
        topic the mailbox did not key may be any arm's (its payload says which): then all rows now."""
        try:
            with self._lock:
                if UNTRACKED_KEY in keys:
                    capture.step(None)
                else:
                    capture.before(keys)
        except Exception as exc:
            log.exception("taking a checkpoint failed")
            capture.fail(exc)
        if capture.done.is_set() and self._capture is capture:
            self._capture = None

    def _decode_all(
        self, batch: Batch, admitted: set[int], losses: list[tuple[DeviceLoss, int | None]]
    ) -> list[_Decoded]:
        """Decode every message in arrival order: a rejection is counted and handed to the sinks at once; a
        valid message's device is admitted (or refused) here, in arrival order too (the ids of the records
        this batch admitted are added to `admitted`). What the loss estimators are to see is added to
        `losses`, in order: (estimator, edge timestamp) for a valid message, (estimator, None) for a
        rejected one."""
        keys, _, payloads, _, _ = batch
        decode = self._decoder.decode
        devices = self._devices
        out: list[_Decoded] = []
        for i, payload in enumerate(payloads):
            key = keys[i]
            topic_device = None if key == UNTRACKED_KEY else key
            try:
                telemetry = decode(payload, topic_device=topic_device)
            except TelemetryRejected as exc:
                loss = self._rejected(topic_device, exc, batch, i)
                if loss is not None:
                    losses.append((loss, None))
                continue
            except Exception:
                self._count_error(topic_device, "processing a message failed", topic=batch.topics[i])
                continue
            record = devices.get(telemetry.device_id)
            if record is None:
                record = self._admit(telemetry.device_id)
                if record is None:
                    continue
                admitted.add(id(record))
            out.append((i, telemetry, record))
            losses.append((record.loss, telemetry.timestamp_ms))
        return out

    def _catch_up(self, decoded: list[_Decoded], batch: Batch, admitted: set[int]) -> list[_Decoded]:
        """A batch taken while behind: every message was decoded (rejections counted as always); of each arm
        only the newest valid message is kept for the twin, the older valid ones are counted as coalesced and
        still reach history. A garbage message never displaces a good one: only valid messages compete. Arms
        this batch admitted keep every message (they had no twin to show a backlog on)."""
        newest = {id(record): j for j, (_, _, record) in enumerate(decoded)}
        keep = []
        coalesced = []
        for j, entry in enumerate(decoded):
            key = id(entry[2])
            if key in admitted or newest[key] == j:
                keep.append(entry)
            else:
                coalesced.append(entry)
        if coalesced:
            self._coalesce(coalesced, batch)
        return keep

    def _coalesce(self, coalesced: list[_Decoded], batch: Batch) -> None:
        # Received and valid: the device is alive and this sample is no transit loss, only not shown.
        _, _, _, monos, walls = batch
        with self._lock:
            for i, telemetry, record in coalesced:
                health = record.health
                health.record_received()
                health.record_decoded(monos[i], walls[i], telemetry.timestamp_ms)
                health.record_coalesced()
        history = self._rows
        if history is not None:
            for i, telemetry, _ in coalesced:
                history.telemetry(_history_row(telemetry, batch, i))

    def _apply_all(self, entries: list[_Decoded], batch: Batch) -> list[bool]:
        """The twin stage (under the lock): each message applied to its device's twin, or not (stale)."""
        applied = []
        for i, telemetry, record in entries:
            try:
                ok = self._apply(record, telemetry, batch.recv_mono[i])
            except Exception:
                self._count_error(record.device, "applying a message failed", locked=True)
                ok = False
            applied.append(ok)
        return applied

    def _apply(self, record: _Device, telemetry: Telemetry, recv_mono: float) -> bool:
        """Apply to the twin. A long run of only-older messages means the edge clock jumped back (module doc):
        the twin is then rebuilt on the new timeline."""
        twin = record.twin
        clamped_before = twin.clamped
        if twin.apply(telemetry.angles_rad, telemetry.timestamp_ms):
            record.stale_streak = 0
            if twin.clamped != clamped_before:
                record.health.clamped += twin.clamped - clamped_before
            return True
        if record.stale_streak == 0:
            record.stale_since = recv_mono
        record.stale_streak += 1
        if (
            record.stale_streak < CLOCK_RESET_MIN_MESSAGES
            or recv_mono - record.stale_since < CLOCK_RESET_AFTER_S
        ):
            return False
        device = record.device
        previous = twin.last_timestamp_ms
        twin = record.twin = DeviceTwin(self.robot, device, self.mode)
        record.stale_streak = 0
        applied = twin.apply(telemetry.angles_rad, telemetry.timestamp_ms)
        record.health.clock_resets += 1
        record.health.clamped += twin.clamped
        how = "stands still" if previous == telemetry.timestamp_ms else "jumped backwards"
        words = record.reset_words = record.reset_words or Throttle(CLOCK_RESET_TELL_EVERY_S)
        # A jump during a standstill is named at once, not counted under the standstill's word.
        carried = words.clear() if how != record.reset_how else 0
        record.reset_how = how
        since = words.due(now=recv_mono)
        if since is None:
            return applied
        untold = since - 1 + carried
        more = f" ({untold} more rebuilds since the last word)" if untold else ""
        log.warning(
            "edge clock of %s %s; twin rebuilt on the new timeline%s; fix: set the edge's clock by NTP",
            device,
            how,
            more,
            extra={"device": device, "last_ms": previous, "now_ms": telemetry.timestamp_ms},
        )
        self._watch.clock_reset(device, previous, telemetry.timestamp_ms, how=how, untold=untold)
        return applied

    def _record_all(
        self, entries: list[_Decoded], applied: list[bool], updated: float, batch: Batch
    ) -> list[tuple[AlarmEvent, ...]]:
        """The health and alarms stage (under the lock): health and latency of every message (its loss
        estimate was fed in arrival order after decoding), servo alarms of every applied one (the round's at
        once: ServoAlarms.evaluate_batch); returns each message's alarm events."""
        _, _, _, monos, walls = batch
        internal: list[float] = []
        end_to_end: list[float] = []
        events: list[tuple[AlarmEvent, ...]] = [()] * len(entries)
        evaluate: list[int] = []  # positions in `entries` of the applied messages
        for n, ((i, telemetry, record), ok) in enumerate(zip(entries, applied, strict=True)):
            recv = monos[i]
            timestamp_ms = telemetry.timestamp_ms
            try:
                record.health.record_message(recv, walls[i], timestamp_ms, ok, updated)
                record.units = telemetry.units
                record.gripper_percent = telemetry.gripper_percent
                if not ok:
                    continue
                latency = updated - recv
                internal.append(latency)
                # Twin-updated wall time minus the edge stamp: only meaningful when the clocks agree (same
                # host in `twin bench`); in the field it includes the edge clock's offset.
                end_to_end.append(walls[i] + latency - timestamp_ms / 1000.0)
                record.diagnostics = telemetry.diagnostics
                evaluate.append(n)
            except Exception:
                self._count_error(record.device, "recording a message failed", locked=True)
        self._internal_hist.add_many(internal)
        self._end_to_end_hist.add_many(end_to_end)
        if evaluate and self._alarms_on:
            self.alarm_rows += len(evaluate)
            try:
                self._evaluate_alarms(entries, evaluate, events, monos)
            except Exception:
                self._count_error(None, "evaluating servo alarms failed", locked=True)
        return events

    def _evaluate_alarms(
        self,
        entries: list[_Decoded],
        evaluate: list[int],
        events: list[tuple[AlarmEvent, ...]],
        monos: Sequence[float],
    ) -> None:
        """Servo alarms for the round's applied messages (docs/servo-health.md), under the lock; state changes
        become log lines and go to the sinks with the sample. Inverse dynamics runs only if a still joint's
        model check or a reader needs it (core.alarms._Torques)."""
        chosen = [entries[n] for n in evaluate]
        if self._joint_order_is_the_contracts:
            devices, diagnostics, messages, poses, stamps, received, torques = [], [], [], [], [], [], []
            for i, telemetry, record in chosen:
                twin = record.twin
                pose = twin.target_values
                devices.append(record.device)
                diagnostics.append(telemetry.diagnostics)
                messages.append(telemetry)
                poses.append(pose)
                stamps.append(telemetry.timestamp_ms)
                received.append(monos[i])
                torques.append(twin.holding_torques_at(pose))
            found = self._alarms.evaluate_batch(
                devices,
                diagnostics,
                # Made only for a round the engine takes as arrays (ServoAlarms.small_round).
                columns=lambda: diagnostic_columns(messages),
                angles=poses,
                timestamps_ms=stamps,
                now=received,
                holding_torques_nm=torques,
                # The still arms' torques in one loop over MuJoCo rather than one call each.
                torques_of=holding_torques_of,
            )
        else:
            found = [
                self._alarms.evaluate(
                    record.device,
                    telemetry.diagnostics,
                    record.twin.holding_torques_when_read(),
                    monos[i],
                    angles_rad=record.twin.targets,
                    timestamp_ms=telemetry.timestamp_ms,
                )
                for i, telemetry, record in chosen
            ]
        for n, message_events in zip(evaluate, found, strict=True):
            if message_events:
                events[n] = tuple(message_events)

    def _hand_all(
        self,
        entries: list[_Decoded],
        applied: list[bool],
        events: list[tuple[AlarmEvent, ...]],
        batch: Batch,
    ) -> None:
        """The sinks stage: every applied message to every sink; with history on, every message to its feed
        (history keeps every decoded message, also one the twin did not apply because it came late or twice:
        rows written = rows received; the other sinks mirror the twin)."""
        if self._sinks:
            for (i, telemetry, record), ok, alarm_events in zip(entries, applied, events, strict=True):
                if ok:
                    self._hand_applied(telemetry, batch, i, record.twin.targets, alarm_events)
        history = self._rows
        if history is not None:
            for i, telemetry, _ in entries:
                history.telemetry(_history_row(telemetry, batch, i))

    def _rejected(
        self, topic_device: str | None, rejected: TelemetryRejected, batch: Batch, i: int
    ) -> DeviceLoss | None:
        """Count, log and hand on one rejection; the loss estimator of the topic's device, if it is tracked
        (it arrived: the hole it leaves in the device's timestamps is not transit loss)."""
        if topic_device is not None and self._kept_out(topic_device, rejected):
            self._refuse(topic_device)
            return None
        # Before the refusal is counted: whoever sees the count sees what its readings raised.
        self._watch_held(topic_device, rejected, batch.recv_mono[i])
        reason = str(rejected.reason)
        loss = None
        with self._lock:
            health = self._fleet.get(topic_device) if topic_device else None
            if topic_device is not None and health is not None:
                health.record_received()
                loss = self._loss_of(topic_device)
            self._fleet.record_rejected(topic_device, reason, batch.recv_mono[i])
        if rejected.reason is not RejectReason.UNITS_UNDECIDED:
            self._rejections.rejected(topic_device, reason, str(rejected))
        topic = batch.topics[i]
        self._reject_log.log(
            (topic_device, reason),
            # units=auto turning away a new arm's first messages while it gathers evidence is expected, not a
            # fault (the decision itself is logged at INFO): a 2,000-arm fleet's start made 2,000 warnings.
            logging.DEBUG if rejected.reason is RejectReason.UNITS_UNDECIDED else logging.WARNING,
            "telemetry rejected",
            device=topic_device,
            topic=topic,
            reason=reason,
            detail=str(rejected),
        )
        if self._sinks:
            # Only the payload's first bytes: the sinks' queues must not hold every junk message whole.
            sample = rejected_sample(
                topic_device,
                topic,
                received_wall_s=batch.recv_wall[i],
                reason=reason,
                detail=str(rejected),
                payload=batch.payloads[i],
            )
            for sink in self._sinks:
                self._guard_sink(sink, sink.rejected, sample)
        history = self._rows
        if history is not None:
            payload = batch.payloads[i]
            history.rejected(
                (
                    batch.recv_wall[i],
                    topic,
                    topic_device,
                    reason,
                    str(rejected),
                    bytes(payload[: history.payload_max_bytes]),
                    len(payload),
                )
            )
        return loss

    def _watch_held(self, device: str | None, rejected: TelemetryRejected, received: float) -> None:
        """Servo alarms of an arm held for its refused calibration (a rejection that carries its servo
        readings): its pose waits for a good file, its servos' heat and load do not (a held arm's servo
        passed 65 C unwatched). No pose, so no model check (no holding torques) and no speeds from poses;
        the edge's own velocities still count. As for an applied message, only readings newer than the last
        judged count: a replayed backlog or a QoS 1 redelivery must not raise or clear an alarm on them."""
        diagnostics, timestamp_ms = rejected.servo_diagnostics, rejected.servo_timestamp_ms
        if diagnostics is None or device is None or not self._alarms_on:
            return
        if timestamp_ms <= self._held_stamps.get(device, -1):
            return
        self._held_stamps[device] = timestamp_ms
        try:
            with self._lock:
                self.alarm_rows += 1
                events = self._alarms.evaluate(device, diagnostics, {}, received)
        except Exception:
            self._count_error(device, "evaluating servo alarms failed")
            return
        for event in events:
            self._tell_alarm(event)

    def _admit(self, device: str) -> _Device | None:
        """A new device's record, created on its first valid message while the fleet's device budget
        (telemetry.max_devices, shared by every mirror) has a place, or already holds one (`_hold_place`)."""
        held = device in self._kept_places
        self._kept_places.discard(device)
        self._held_stamps.pop(device, None)  # its twin judges what is newer from now on
        if not held and not self._budget.take(self._slot):
            self._refuse(device)
            return None
        twin = DeviceTwin(self.robot, device, self.mode)
        with self._lock:
            record = self._devices[device] = _Device(
                device, twin, self._fleet.device(device), self._loss_of(device)
            )
        log.info("new device", extra={"device": device, "mode": str(self.mode)})
        self._watch.arrived(device)
        return record

    def _kept_out(self, device: str, rejected: TelemetryRejected) -> bool:
        """Whether a message units=auto turned away while it gathers evidence is of a device the full budget
        keeps out. Its units are forgotten at each refusal, so it gathered them again and again: two of every
        three of its messages were counted as units_undecided, not too_many_devices, and each decision
        logged a line (three a second for an arm at 10 Hz)."""
        return (
            rejected.reason is RejectReason.UNITS_UNDECIDED
            and device not in self._devices
            and device not in self._kept_places
            and self._budget.taken >= self._budget.limit
        )

    def _refuse(self, device: str) -> None:
        """Count and log a valid message of a device the fleet's device budget has no place for."""
        with self._lock:
            # Under its id (counted as untracked all the same): the Fleet page names an arm kept out. An arm
            # listed for its kept alarms with no place left lands here too: it still publishes (forget_arm).
            self._fleet.record_rejected(device, TOO_MANY_DEVICES, self._clock())
        self._rejections.rejected(device, TOO_MANY_DEVICES, "telemetry.max_devices reached")
        # units=auto may have decided this device's units already: an invented id must leave nothing.
        self._decoder.forget(device)
        self._reject_log.log(
            TOO_MANY_DEVICES,
            logging.WARNING,
            "device ignored: telemetry.max_devices devices already sent valid telemetry; raise it if "
            "the fleet is really this large. Arms that left keep their places until forgotten: for a fleet "
            "whose ids come and go, set telemetry.forget_offline_after_s, or forget them on the console",
            device=device,
            max_devices=self._budget.limit,
        )

    def _loss_of(self, device: str) -> DeviceLoss:
        """The device's loss estimator (under the lock). Its nominal period is the configured edge rate; a gap
        longer than the offline time is an outage, not loss."""
        loss = self._loss.get(device)
        if loss is None:
            h = self.config.health
            loss = self._loss[device] = DeviceLoss(
                nominal_period_s=1.0 / h.expected_rate_hz,
                outage_s=h.offline_after_s,
                window_s=max(h.window_s, 10.0),
                clock=self._clock,
            )
        return loss

    def _hand_applied(
        self,
        telemetry: Telemetry,
        batch: Batch,
        i: int,
        joint_angles: dict[str, float],
        events: tuple[AlarmEvent, ...] = (),
    ) -> None:
        sample = AppliedSample(
            device_id=telemetry.device_id,
            received_wall_s=batch.recv_wall[i],
            received_mono_s=batch.recv_mono[i],
            telemetry=telemetry,
            joint_angles=joint_angles,
            payload=batch.payloads[i],
            alarm_events=events,
        )
        for sink in self._sinks:
            self._guard_sink(sink, sink.applied, sample)

    def _guard_sink(self, sink: TwinSink, method: Callable[[_SampleT], None], sample: _SampleT) -> None:
        # A sink that raises (it should not: I/O sinks queue) must not cost the mirror or the other sinks.
        try:
            method(sample)
        except Exception:
            self._count_error(None, f"sink {sink.name} failed", sink=sink.name)

    def _count_error(self, device: str | None, msg: str, *, locked: bool = False, **fields: object) -> None:
        """Count (and log, rate-limited) an error; `locked`: the caller holds the mirror's lock."""
        self.errors += 1
        if device:
            if locked:
                self._record_error(device)
            else:
                with self._lock:
                    self._record_error(device)
        # One traceback per interval; the rest are summarised as `suppressed` on the next line.
        self._error_log.log((device, msg), logging.ERROR, msg, exc_info=True, device=device, **fields)

    def _record_error(self, device: str) -> None:
        health = self._fleet.get(device)
        if health is not None:
            health.record_error()

    # ------------------------------------------------------------------------------------------ readers

    def answer(self, request: Request) -> Reply:
        """What the agent asks of a shard (service.shards), answered here, in-process or in a worker."""
        if isinstance(request, ReportRequest):
            return self.report()
        if isinstance(request, AlarmsRequest):
            return self.alarms(include_normal=request.include_normal)
        if isinstance(request, AckRequest):
            if request.checkpoint:
                return self.acknowledge_checkpointed(request.alarm_id)
            return self.acknowledge_alarm(request.alarm_id)
        if isinstance(request, AckManyRequest):
            if request.checkpoint:
                return self.acknowledge_many_checkpointed(request.alarm_ids)
            return AckedMany(self.acknowledge_alarms(request.alarm_ids))
        if isinstance(request, ForgetRequest):
            return self.forget_arm(request.device, checkpoint=request.checkpoint, reason=request.reason)
        if isinstance(request, EventsRequest):
            # The oldest first: a burst over EVENTS_PER_ASK comes over the rounds that follow, none skipped.
            events = tuple(self._events.after(request.after_id, EVENTS_PER_ASK))
            return EventsReply(events, self._events.alarms_let_go_after(request.after_id))
        if isinstance(request, FleetRowsRequest):
            return tuple(self.fleet_rows())
        if isinstance(request, ArmRequest):
            return self.arm(request.device)
        if isinstance(request, StatusesRequest):
            return tuple((device, str(status)) for device, status in self.statuses().items())
        if isinstance(request, UnheardRequest):
            return self.unheard()
        if isinstance(request, CheckpointRequest):
            return self.checkpoint(alarms_only=request.alarms_only)
        if isinstance(request, RestoreRequest):
            return self.restore(request.checkpoint, request.alarms, request.history)
        if isinstance(request, CalibrationsRequest):
            return self.set_calibrations(request)
        raise TypeError(f"not a request to a mirror: {request!r}")

    def set_calibrations(self, request: CalibrationsRequest) -> int:
        """Each arm's own calibration from now on (from any thread: the decoder swaps its table in whole);
        returns how many arms have one. The files were validated by the agent that read them."""
        calibrations = {device: Calibration.from_dict(data, source) for device, source, data in request.files}
        with self._lock:
            # Before the decoder holds a newly refused arm: its first refusal must find it held here, or it
            # is trimmed as one of the 64 others.
            self._fleet.hold(dict(request.problems))
        # An arm whose file was refused, with no good one from this run to keep, is held (the decoder's doc).
        self._decoder.set_calibrations(
            calibrations,
            held=dict(request.problems),
            store_option=request.store_option,
            restorable=request.restorable,
        )
        with self._lock:
            self._calibration_sources = {device: source for device, source, _ in request.files}
            self._calibration_problems = dict(request.problems)
        return len(calibrations)

    def events(self, query: EventQuery) -> list[Event]:
        """This mirror's events that match `query` (the agent collects them: AgentService.events)."""
        return self._events.query(query)

    def _watch_statuses(self, received: Sequence[float] = ()) -> None:
        """On the worker thread: status transitions become events, read at most every FleetWatch.interval_s
        (statuses change by the passing of time, not by a message, so they are read, not told); so does a
        device publishing well above the expected rate (events.RateWatch), read every RATE_INTERVAL_S.

        `received` are the receive times of the batch just handled (none after an empty turn); the newest,
        read only when a sweep is due, is where the worker stands in its input. A worker behind its input
        (starved of CPU, it takes its backlog in pieces) reads the arms' silence at that time, not on the
        wall clock: the messages of the arms not in this piece are waiting behind it, so none of them is
        silent. An empty turn means nothing waits, and silence is read on the clock."""
        now = self._clock()
        if not self._watch.due(now):
            return
        at = min(now, max(received)) if received else now
        self._swept_behind_s = now - at
        with self._lock:
            # Of the arms heard from only: their arrivals were told by `_admit`.
            statuses = self._fleet.statuses(at, heard_only=True)
        self._watch.statuses(statuses, now)
        self._hand_statuses(statuses, at, now)
        self._watch.alarm_bursts(now)
        if self._watch.rates_due(now):
            with self._lock:
                rates = self._fleet.rates(at)
                # Of the arms heard from, as the rates: an arm's loss estimate is made with its record.
                recent = {device: loss.recent(now) for device, loss in self._loss.items() if device in rates}
            self._watch.rates(rates, now, statuses)
            self._watch.losses(recent, now)
        if self._watch.clocks_due(now):
            # An edge clock far off (events.ClockWatch): a minimum over each arm's window, so not every sweep.
            # The window goes by receive time: read where the worker stands, or a worker a window behind has
            # no offsets, and the arms reported off are dropped without a word (and reported again later).
            with self._lock:
                offsets = self._fleet.clock_offsets(at)
            self._watch.clocks(offsets)

    def _hand_statuses(self, statuses: Mapping[str, DeviceStatus], at: float, now: float) -> None:
        """Every change of an arm's status since the last sweep, to the sinks that show statuses. Each change
        as it is, flapping or not (the events summarise flapping; a viewer shows the arm as it is). A sink
        knows an arm by its samples, so an arm it was not told of was ONLINE to it."""
        if not self._status_sinks:
            return
        saw = self._sinks_saw
        wall = self._wall_clock() - (now - at)
        for device, status in statuses.items():
            previous = saw.get(device)
            if previous is None:
                previous = saw[device] = DeviceStatus.ONLINE
            if status is previous:
                continue
            saw[device] = status
            change = StatusChange(device, previous, status, at_mono_s=at, at_wall_s=wall)
            for sink, method in self._status_sinks:
                self._guard_sink(sink, method, change)

    @property
    def behind_s(self) -> float:
        """How far behind its input the worker stands now (`_behind`)."""
        return self._behind(self._clock())

    def _behind(self, now: float) -> float:
        """How far behind its input the worker stands at `now` (monotonic): where its last status sweep found
        it, or, while it handles a batch, the age of that batch's oldest message if more. Read when asked,
        so a worker held in one long batch (or hung in it) shows its lag growing. The arms' statuses and rates
        stay read at the sweep's point: a worker that stops handling messages lets them go STALE on the clock
        (docs/agent.md, "Health")."""
        behind = self._swept_behind_s
        since = self._handling_since
        if since is not None and now - since > behind:
            behind = now - since
        return behind

    def statuses(self) -> dict[str, DeviceStatus]:
        """Each device's status now (those configured too, heard from or not), without the report; read where
        the worker stood in its input at its last status sweep (`_behind`)."""
        with self._lock:
            return self._fleet.statuses(self._clock() - self._swept_behind_s)

    def unheard(self) -> tuple[UnheardArm, ...]:
        """The devices not tracked whose every message was refused so far, the most recent first
        (core.health.FleetHealth.unheard)."""
        with self._lock:
            return self._unheard_locked()

    def _unheard_locked(self) -> tuple[UnheardArm, ...]:
        """`unheard`, the lock held."""
        now = self._clock()
        return tuple(
            UnheardArm(device, u.rejected, u.reason, now - u.last_mono)
            for device, u in reversed(self._fleet.unheard.items())
        )

    def fleet_rows(self) -> list[FleetRow]:
        """One row per arm for the console's Fleet page, read without building the report (no device
        states, no latency percentiles): at a large fleet that is most of what a console tick costs. The
        lock is taken for FLEET_ROWS_CHUNK arms at a time, so the worker thread, which needs it for every
        batch, waits for a few milliseconds at most rather than for the whole fleet (each row is of one
        moment; an arm forgotten meanwhile has none)."""
        with self._lock:
            worst: dict[str, tuple[str, str, str, str]] = {}
            waiting: Counter[str] = Counter()
            for v in self._alarms.views():  # worst first
                state = str(v.state)
                worst.setdefault(v.device, (str(v.severity), state, str(v.kind), v.joint))
                if state in WAITING_STATES:
                    waiting[v.device] += 1
            devices = self._fleet.listed()
        rows = []
        for start in range(0, len(devices), FLEET_ROWS_CHUNK):
            with self._lock:
                now, wall = self._clock(), self._wall_clock()
                for device in devices[start : start + FLEET_ROWS_CHUNK]:
                    health = self._fleet.devices.get(device)
                    if health is not None:
                        alarm = worst.get(device)
                        rows.append(self._fleet_row(device, health, (now, wall), alarm, waiting[device]))
        return sorted(rows, key=lambda row: row.device)

    def _fleet_row(
        self,
        device: str,
        h: DeviceHealth,
        clocks: tuple[float, float],
        alarm: tuple[str, str, str, str] | None,
        unacknowledged: int,
    ) -> FleetRow:
        """`fleet_rows`' row of one arm (the lock held), at `clocks` (monotonic, wall)."""
        now, wall = clocks
        loss = self._loss.get(device)
        received, lost = loss.recent(now) if loss is not None else (0, 0)
        record = self._devices.get(device)
        diagnostics = record.diagnostics if record is not None and record.diagnostics else {}
        last = h.last_message_mono
        swept = self._swept_behind_s
        return fleet_row(
            device,
            status=str(h.status(now - swept)),
            last_seen=wall - (now - last) if last is not None else None,
            rate_hz=h.rate_hz(now - swept),
            loss_ratio=lost / (received + lost) if received + lost else 0.0,
            temperatures={j: d.temperature_c for j, d in diagnostics.items()},
            rejected=h.rejected_total,
            alarm=alarm,
            uncalibrated=self._card_uncalibrated(
                device,
                record.units
                if record is not None and record.units is not None
                else self.config.telemetry.units,
            ),
            unacknowledged=unacknowledged,
            behind_s=self._behind(now),
            calibration_refused=device in self._calibration_problems,
        )

    def report(self) -> MirrorReport:
        """This mirror's part of the agent's state (docs/http-api.md describes every field)."""
        readout = self._read()
        return MirrorReport(
            devices={
                device: self._device_state(device, reading.snapshot(), readout)
                for device, reading in readout.health.items()
            },
            untracked_rejected=readout.untracked,
            mailbox=MailboxState(
                overwritten_total=self._mailbox.overflowed_total,
                refused_keys=0,
                pending=len(self._mailbox),
            ),
            worker=WorkerState(
                alive=self.running,
                batches=readout.batches,
                processed=readout.processed,
                errors=self.errors,
                stage_cpu_s=readout.stage_cpu_s,
                stage_timed_batches=readout.stage_timed_batches,
                alarm_rows=readout.alarm_rows,
                behind_s=round(self._behind(readout.now), 3),
            ),
            recording=self._recording_state(),
            # The agent has the history's own figures (its writer process); the feed's are a sink's.
            history=None,
            sinks=(
                *(sink.stats() for sink in self._sinks),
                *((self._history.stats(),) if self._history is not None else ()),
            ),
            alarms=readout.alarms,
            internal=readout.internal,
            end_to_end=readout.end_to_end,
        )

    def _read(self, only: str | None = None) -> _Readout:
        """Copy what the worker writes, under the lock, as briefly as possible: what takes time to derive
        from the copies (the latency percentiles, the device states) is left to `report`, after it. With
        `only`, of that one device alone (an arm page's: a fleet's read is far longer)."""
        alarms = self._alarms
        with self._lock:
            now = self._clock()
            if only is None:
                devices: Iterable[_Device] = self._devices.values()
                health = self._fleet.readings(now, self._swept_behind_s)
                worst = alarms.worst_by_device()
                losses: Iterable[tuple[str, DeviceLoss]] = self._loss.items()
            else:
                record, known = self._devices.get(only), self._fleet.devices.get(only)
                if known is not None and not self._fleet.shown(only, known):
                    known = None  # admitted, its first message not yet counted (FleetHealth.shown)
                loss = self._loss.get(only)
                devices = [record] if record is not None else []
                health = {only: known.reading(now, self._swept_behind_s)} if known is not None else {}
                worst = {only: alarms.worst_by_joint(only)}
                losses = [(only, loss)] if loss is not None else []
            return _Readout(
                now=now,
                health=health,
                snapshots={
                    r.device: r.twin.snapshot() for r in devices if r.twin.last_timestamp_ms is not None
                },
                units={r.device: r.units for r in devices if r.units is not None},
                gripper={r.device: r.gripper_percent for r in devices if r.units is not None},
                untracked=dict(self._fleet.untracked_rejected),
                batches=self.batches,
                processed=self.processed,
                stage_cpu_s=dict(self._stage_cpu),
                stage_timed_batches=self._stage_timed_batches,
                alarm_rows=self.alarm_rows,
                internal=self._internal_hist.copy(),
                end_to_end=self._end_to_end_hist.copy(),
                servos={
                    r.device: (r.diagnostics, alarms.joint_health(r.device), worst.get(r.device, {}))
                    for r in devices
                    if r.diagnostics is not None
                },
                alarms=self._alarms_summary(),
                loss={device: loss.snapshot(now) for device, loss in losses},
                forget=self._forget_offer(only, now) if only is not None else None,
            )

    def arm(self, device: str) -> ArmReply:
        """One arm's state (as `report` has it; None when this mirror does not track it) and its alarms that
        are not NORMAL, worst first: an arm page's, without reading the fleet."""
        readout = self._read(device)
        reading = readout.health.get(device)
        return ArmReply(
            state=self._device_state(device, reading.snapshot(), readout) if reading is not None else None,
            alarms=self.alarms(device=device),
            forget=readout.forget,
        )

    @staticmethod
    def _servo_states(readout: _ServoReadout) -> dict[str, ServoState]:
        """Outside the lock: `model_load_percent` may run inverse dynamics on first read (core.alarms)."""
        diagnostics, health, worst = readout
        out = {}
        for joint, diag in diagnostics.items():
            h = health.get(joint)
            severity, state = worst.get(joint, (None, None))
            out[joint] = ServoState(
                velocity_rad_s=diag.velocity_rad_s,
                load_percent=diag.load_percent,
                temperature_c=diag.temperature_c,
                current_a=diag.current_a,
                voltage_v=diag.voltage_v,
                model_load_percent=h.model_load_percent if h else None,
                mismatch_percent=h.mismatch_percent if h else None,
                still=h.still if h else None,
                alarm_severity=str(severity) if severity else None,
                alarm_state=str(state) if state else None,
                errors=None if diag.status is None else sts3215.status_names(diag.status),
            )
        return out

    def _alarms_summary(self) -> AlarmsSummary:
        """Under the lock."""
        counters = self._alarms.counters
        by_state: dict[str, dict[str, int]] = {str(s): {} for s in Severity}
        for (severity, state), count in sorted(self._alarms.counts_by_state().items()):
            by_state[str(severity)][str(state)] = count
        raised: dict[str, int] = {}
        for (kind, _), count in counters.raised.items():
            raised[str(kind)] = raised.get(str(kind), 0) + count
        return AlarmsSummary(
            present={str(k): v for k, v in self._alarms.present_by_severity().items()},
            by_state=by_state,
            raised_total=dict(sorted(raised.items())),
            cleared_total={str(k): v for k, v in sorted(counters.cleared.items())},
            acknowledged_total={str(k): v for k, v in sorted(counters.acknowledged.items())},
        )

    # ------------------------------------------------------------------------------------ alarms (people)

    def alarms(self, *, include_normal: bool = False, device: str | None = None) -> tuple[AlarmInfo, ...]:
        """Servo alarms, worst first (GET /alarms), of every arm or of `device`; NORMAL ones if asked."""
        with self._lock:
            now = self._clock()
            views = self._alarms.views(include_normal=include_normal, device=device)
        wall = self._wall_clock()
        return tuple(alarm_info(v, now, wall) for v in views)

    def acknowledge_alarm(self, alarm_id: str) -> AlarmInfo:
        """ACTIVE -> ACKNOWLEDGED, LATCHED -> NORMAL. Raises twin.core.alarms.AlarmNotFound (unknown id) or
        NothingToAcknowledge (NORMAL or already ACKNOWLEDGED)."""
        with self._lock:
            now = self._clock()
            event = self._alarms.acknowledge(alarm_id, now)
            view = self._alarms.views_of((alarm_id,))[0]
        self._tell_alarm(event)
        return alarm_info(view, now, self._wall_clock())

    def acknowledge_checkpointed(self, alarm_id: str) -> Acknowledged:
        """`acknowledge_alarm`, and the mirror's checkpoint begun right after it between the same two batches:
        a worker's restart point that holds the acknowledgement, so a worker that dies before the agent's next
        checkpoint does not come back with the alarm ACTIVE (or LATCHED) again."""
        return Acknowledged(*self._checkpointed(lambda: self.acknowledge_alarm(alarm_id)))

    def acknowledge_alarms(self, alarm_ids: Sequence[str]) -> tuple[AckResult, ...]:
        """`acknowledge_alarm` of each id in one hold of the mirror's lock, each id's outcome answered (an
        unknown one, or one with nothing to acknowledge, does not stop the others), in the order given."""
        results: list[AckResult] = []
        events: list[AlarmEvent] = []
        with self._lock:
            now = self._clock()
            for alarm_id in alarm_ids:
                outcome, detail = AckOutcome.ACKNOWLEDGED, ""
                try:
                    events.append(self._alarms.acknowledge(alarm_id, now))
                except AlarmNotFound:
                    results.append(
                        AckResult(alarm_id, AckOutcome.ALARM_NOT_FOUND, None, ALARM_NOT_FOUND_DETAIL)
                    )
                    continue
                except NothingToAcknowledge as exc:
                    outcome, detail = AckOutcome.NOTHING_TO_ACKNOWLEDGE, str(exc)
                view = self._alarms.views_of((alarm_id,))[0]
                results.append(AckResult(alarm_id, outcome, str(view.state), detail))
        for event in events:
            self._tell_alarm(event)
        return tuple(results)

    def acknowledge_many_checkpointed(self, alarm_ids: Sequence[str]) -> AckedMany:
        """`acknowledge_alarms`, and one checkpoint begun right after them (acknowledge_checkpointed's)."""
        return AckedMany(*self._checkpointed(lambda: self.acknowledge_alarms(alarm_ids)))

    def _tell_alarm(self, event: AlarmEvent) -> None:
        """An alarm transition as its event (FleetWatch.alarm) and its log line, at the same level."""
        _log_alarm_event(event, told=self._watch.alarm(event))

    def _checkpointed(self, act: Callable[[], _T]) -> tuple[_T, MirrorCheckpoint | None]:
        """`act()` between two batches, and the mirror's checkpoint begun right after it there (a worker's
        restart point that holds what it did: one begun before would not), if taken in ACT_CHECKPOINT_S."""

        def run() -> tuple[_T, Capture]:
            self._finish_capture()
            return act(), self._begin_capture()

        result, capture = self._between_batches(run)
        return result, self._act_checkpoint(capture)

    def _act_checkpoint(self, capture: Capture) -> MirrorCheckpoint | None:
        """The checkpoint an acknowledgement or a forget began, if taken within ACT_CHECKPOINT_S."""
        try:
            return self._captured(capture, time.monotonic() + ACT_CHECKPOINT_S)
        except TimeoutError:
            log.warning(
                "the checkpoint taken with an acknowledgement or a forget took over %.0f s; the act is done, "
                "and the next checkpoint holds it",
                ACT_CHECKPOINT_S,
            )
            return None

    def forget_arm(self, device: str, *, checkpoint: bool = False, reason: str = "") -> ArmForgotten:
        """Remove an OFFLINE arm an operator retired (docs/console.md, "Forget an arm"): its twin, health and
        counters, loss estimator, units decision and every alarm, and give its place in the device budget
        back. Between two batches on the worker thread (the decoder is the worker's alone). Raises
        ArmNotFoundError (not tracked here) or ArmNotForgettableError (not OFFLINE, or configured). With
        `checkpoint`, the mirror's checkpoint begun between the same two batches comes with the answer: a
        worker's restart point without the arm, with no message in between that could still hold it. `reason`:
        why the agent forgot it itself (its event says so), empty for an operator."""
        if not checkpoint:
            return self._between_batches(lambda: self._forget_arm(device, reason))
        forgotten, taken = self._checkpointed(lambda: self._forget_arm(device, reason))
        return dataclasses.replace(forgotten, checkpoint=taken)

    def _forget_arm(self, device: str, reason: str = "") -> ArmForgotten:
        # A checkpoint being taken would carry the arm's row and alarms: finish it first, so the one the agent
        # takes next (it is woken for it) no longer holds them.
        self._finish_capture()
        with self._lock:
            health = self._fleet.get(device)
            if health is None:
                raise ArmNotFoundError(device)
            refusal = self._forget_refusal(device, health, self._clock())
            if refusal is not None:
                raise refusal
            status = DeviceStatus.OFFLINE  # as _forget_refusal found it
            self._fleet.forget(device)
            record = self._devices.pop(device, None)
            self._loss.pop(device, None)
            removed = {str(state): n for state, n in sorted(self._alarms.forget(device).items())}
        self._decoder.forget(device)
        # The queue's drop count of it too: copied into the health of whatever arm of that name comes next.
        self._mailbox.forget(device)
        if record is not None or device in self._kept_places:
            self._kept_places.discard(device)
            self._budget.give_back(self._slot)
        self._watch.forgotten(device, str(status), removed, reason)
        self._sinks_forgot(device)
        log.info("device forgotten", extra={"device": device, "alarms_removed": removed})
        return ArmForgotten(device=device, status=str(status), alarms_removed=removed)

    def _sinks_forgot(self, device: str) -> None:
        """The sinks that show statuses are told of the forget, so they drop what they keep of the arm (the
        Rerun sink its label and record): under a fleet that churns for weeks neither they nor the mirror
        keep anything of the arms gone. An arm of that name that publishes again is new to them, as here."""
        self._sinks_saw.pop(device, None)
        if not self._status_sinks:
            return
        behind = self._swept_behind_s
        at, wall = self._clock() - behind, self._wall_clock() - behind
        # Only an OFFLINE arm is forgotten: `previous` says so even when the forget overtook the sweep that
        # would have told the sinks (their last word of it may still be STALE).
        gone = DeviceStatus.OFFLINE
        change = StatusChange(device, gone, gone, at_mono_s=at, at_wall_s=wall, forgotten=True)
        for sink, method in self._status_sinks:
            self._guard_sink(sink, method, change)

    def _forget_refusal(self, device: str, health: DeviceHealth, now: float) -> ArmNotForgettableError | None:
        """Under the lock: why `device` may not be forgotten at `now` (None: it may). The Arm page shows this
        answer (Mirror.arm): derived in the page, on another clock, it offered what the agent refused."""
        if device in self._fleet.configured:
            why = f"{device} is listed in telemetry.devices: take it out of the config instead"
            return ArmNotForgettableError(ARM_CONFIGURED, why)
        # Where the worker stands: an arm whose messages wait behind it is not silent.
        status = health.status(now - self._swept_behind_s)
        if status is not DeviceStatus.OFFLINE:
            return ArmNotForgettableError(
                ARM_NOT_OFFLINE,
                f"{device} is {status}: only an OFFLINE arm (silent for health.offline_after_s = "
                f"{self.config.health.offline_after_s:g} s) can be forgotten",
            )
        return self._publishing_refusal(device, health, now)

    def _publishing_refusal(
        self, device: str, health: DeviceHealth, now: float
    ) -> ArmNotForgettableError | None:
        """Under the lock: an OFFLINE arm whose refused messages still arrive is not retired. An arm held by
        its refused calibration, listed after a restart for its kept alarms, lost them to a forget while it
        published, and they came back unacknowledged seconds later."""
        last = health.last_refused_mono
        offline_after = self.config.health.offline_after_s
        ago = now - self._swept_behind_s - last if last is not None else None
        if ago is None or ago >= offline_after:
            return None
        if health.last_refused_reason == TOO_MANY_DEVICES:
            fix = "raise telemetry.max_devices, so that it has a place"
        elif device in self._calibration_problems:
            fix = "push a valid calibration for it (its Arm page gives the command)"
        else:
            fix = "mend what its edge sends (the Events page says why each message was refused)"
        return ArmNotForgettableError(
            ARM_NOT_OFFLINE,
            f"{device} still publishes: its last message, {max(ago, 0.0):.1f} s ago, was refused "
            f"({health.last_refused_reason}). "
            f"Only an arm silent for health.offline_after_s = {offline_after:g} s can be forgotten: {fix}, "
            "or stop its edge",
        )

    def _forget_offer(self, device: str, now: float) -> ForgetOffer | None:
        """Under the lock: whether `device` may be forgotten at `now`, and if not the words the forget would
        be refused with (None: not tracked here). The clock its state was read on: one read after it, at a
        boundary, offered Forget beside a STALE arm."""
        health = self._fleet.get(device)
        if health is None:
            return None
        refusal = self._forget_refusal(device, health, now)
        return ForgetOffer(True) if refusal is None else ForgetOffer(False, str(refusal))

    def _device_state(self, device: str, health: HealthSnapshot, readout: _Readout) -> DeviceState:
        snap = readout.snapshots.get(device)
        units = readout.units.get(device, self.config.telemetry.units)
        return DeviceState(
            device_id=device,
            health=health,
            units=units,
            mode=self.mode,
            timestamp_ms=snap.timestamp_ms if snap else None,
            joints_rad=snap.joint_angles if snap else None,
            targets_rad=snap.targets if snap else None,
            torques_nm=snap.joint_torques if snap else None,
            tcp_position_m=snap.tcp_position if snap else None,
            gripper_percent=readout.gripper.get(device),
            servos=self._servo_states(readout.servos[device]) if device in readout.servos else None,
            loss=readout.loss.get(device, LossSnapshot()),
            calibration=calibration_in_use(self._calibration_source(device), units),
            uncalibrated=self._uncalibrated(device, units),
            calibration_problem=self._calibration_problems.get(device, ""),
        )

    def _calibration_source(self, device: str) -> str:
        # Replaced whole by set_calibrations, so reading it needs no lock.
        return self._calibration_sources.get(device) or self.config.telemetry.calibration

    def _uncalibrated(self, device: str, units: Units) -> bool:
        return uncalibrated(self._calibration_source(device), units)

    def _card_uncalibrated(self, device: str, units: Units) -> bool:
        """The Fleet row's `uncalibrated` (console.card_uncalibrated): held is its own file refused, none
        kept."""
        problems, sources = self._calibration_problems, self._calibration_sources  # each replaced whole
        held = device in problems and device not in sources
        return card_uncalibrated(self._uncalibrated(device, units), held, units)

    def _recording_state(self) -> RecordingState | None:
        if self._recording is None:
            return None
        totals = self._recording.totals()
        return RecordingState(
            path=totals.path,
            samples_written=totals.samples_written,
            samples_dropped=totals.samples_dropped,
            flushes=totals.flushes,
            flush_errors=totals.flush_errors,
            rotations=totals.rotations,
            files_deleted=totals.files_deleted,
        )


class LocalShard:
    """The fleet's one share when the mirror runs in the agent's own process (`twin run --workers 1`, the
    demo, the tests): the agent's queue is the mirror's inbox (service.shards, `Shard`)."""

    index = 0
    restarts = 0  # a dead worker thread is `failed`, never started again

    def __init__(
        self,
        config: AgentConfig,
        *,
        budget: DeviceBudget,
        clock: Clock = time.monotonic,
        wall_clock: Clock = time.time,
        sinks: Sequence[TwinSink] = (),
        history: HistoryLink | None = None,
    ) -> None:
        self._inbox: InboundQueue[QueuedMessage] = InboundQueue(
            max_items=MAX_QUEUED_MESSAGES, max_bytes=MAX_QUEUED_BYTES, size_of=_payload_size
        )
        self.checkpoint: MirrorCheckpoint | None = None
        self._gate = QueueInbox(self._inbox, opened=False)
        self.mirror = Mirror(
            config,
            inbox=self._gate,
            budget=budget,
            clock=clock,
            wall_clock=wall_clock,
            sinks=sinks,
            history=history,
        )
        self._closed = False
        self._stall = StallWatch(STALL_AFTER_S)
        self._stalled = False

    def put(self, key: str, topic: str, payload: bytes, recv_mono: float, recv_wall: float) -> None:
        self._inbox.put(key, (topic, payload, recv_mono, recv_wall))

    def launch(self) -> None:
        self.mirror.start()

    def await_ready(self) -> None:
        return  # running once launched

    def open(self) -> None:
        self._gate.open()

    def close(self) -> None:
        self._closed = True
        self._gate.close()

    def join(self, deadline: float) -> StopReport | None:
        if self._stalled:
            # A stuck thread does not finish its batch however long it is given: the stop's budget goes to
            # the sinks and the state file, and systemd starts the agent again sooner.
            deadline = min(deadline, time.monotonic() + STALLED_STOP_S)
        return self.mirror.stop(max(0.1, deadline - time.monotonic()))

    def supervise(self) -> None:
        """Nothing to start again (a dead worker thread is `failed`), but a stuck one must not pass for a
        running mirror: with no turn of its loop for STALL_AFTER_S it is `failed` too, so `twin run` exits and
        systemd starts the agent again, from its state file, as a worker process would be from its checkpoint.
        It cannot be stopped from here, nor started again beside itself (it holds the twins)."""
        if self._closed or self._stalled or not self.mirror.running:
            return
        # On the host's own clock, not the injected one: a test's timeline may leap while the thread turns.
        stalled = self._stall.look(self.mirror.turns, time.monotonic(), self.mirror.wake_s)
        if stalled is None:
            return
        log.error(
            "the mirror's worker thread has not turned for %.0f s, %d messages queued for it: it is stuck; "
            "the agent stops (under systemd, its unit starts it again). It waits in:\n%s",
            stalled,
            len(self._inbox),
            self.mirror.worker_stack(),
            extra={"stalled_s": round(stalled, 1), "queued": len(self._inbox)},
        )
        # Failed only once said: whoever sees the agent stop finds the reason already in its log.
        self._stalled = True

    restarting = False

    def confirm(self, checkpoint: MirrorCheckpoint, *, restarts: int | None = None) -> bool:
        self.checkpoint = checkpoint  # never restarts
        return True

    def restarting_devices(
        self, thresholds: HealthThresholds, now: float, mirror: MirrorStatus = MirrorStatus.RESTARTING
    ) -> dict[str, DeviceState]:
        return {}  # never restarts: a dead worker thread is `failed`

    def restarting_alarms(self, now: float, wall: float, *, include_normal: bool) -> list[AlarmInfo]:
        return []  # never restarts (above)

    def keep_calibrations(self, request: CalibrationsRequest) -> None:
        return  # handed to the mirror itself, which never starts again

    @property
    def failed(self) -> bool:
        return not self._closed and (self._stalled or not self.mirror.running)

    @property
    def answering(self) -> bool:
        return True

    def request(self, request: Request) -> Callable[[], Reply]:
        reply = self.mirror.answer(request)
        return lambda: reply

    def describe(self, report: MirrorReport | None) -> WorkerInfo | None:
        return None  # `agent.workers` lists worker processes only

    def last_exit(self) -> WorkerExit | None:
        return None  # no process of its own

    def dropped(self) -> dict[str, int]:
        return {}  # the mirror counts its own queue's drops

    def forget(self, device: str) -> None:
        return  # the mirror forgot its queue's count of it (Mirror.forget_arm)

    dropped_total = 0


def _payload_size(message: QueuedMessage) -> int:
    return len(message[1])


def _copy_counters(counters: AlarmCounters) -> AlarmCounters:
    return AlarmCounters(
        raised=Counter(counters.raised),
        cleared=Counter(counters.cleared),
        acknowledged=Counter(counters.acknowledged),
    )


def _sliced(batch: Batch, start: int, end: int) -> Batch:
    """Messages `start` to `end` of `batch`."""
    keys, topics, payloads, monos, walls = batch
    return Batch(keys[start:end], topics[start:end], payloads[start:end], monos[start:end], walls[start:end])


def _history_row(telemetry: Telemetry, batch: Batch, i: int) -> TelemetryRow:
    """A decoded message as its history row: its decoded angles (not the applied, clamped ones)."""
    return (
        telemetry.device_id,
        batch.recv_wall[i],
        telemetry.timestamp_ms,
        telemetry.units.value,
        tuple(telemetry.angles_rad.values()),
        batch.payloads[i],
    )


def _rounds(decoded: list[_Decoded]) -> list[list[_Decoded]]:
    """The batch's decoded messages in rounds, each device at most once a round and its messages in order
    (module doc); one round in the usual case of one message per device."""
    if len(decoded) < 2 or len({id(record) for _, _, record in decoded}) == len(decoded):
        return [decoded]
    rounds: list[list[_Decoded]] = []
    seen: dict[int, int] = {}
    for entry in decoded:
        key = id(entry[2])
        k = seen.get(key, 0)
        seen[key] = k + 1
        if k == len(rounds):
            rounds.append([])
        rounds[k].append(entry)
    return rounds


def _log_alarm_event(event: AlarmEvent, *, told: bool = True) -> None:
    """One JSON log line per alarm state change (twin.service.logs formats the fields); at info when the
    event was not `told` at its own level (one of a burst, whose warning counts it: events.MismatchBurst)."""
    # EventLevel's values are logging's: the line goes at its event's level.
    level = int(alarm_level(event)) if told else logging.INFO
    # A raised alarm's line says what to do at the arm, as its e-mail and /alarms do: the log may be all
    # a person on the host reads.
    advice = what_to_do(event.kind, event.joint, event.value) if event.action == "raised" else ""
    # The arm in the text too: a plain-text log (`twin demo`'s) shows no fields, and a fleet has many
    # servos of one name.
    log.log(
        level,
        "servo alarm %s on %s: %s%s",
        event.action,
        event.device,
        event.message,
        f"; what to do: {advice}" if advice else "",
        extra={
            "event": "servo_alarm",
            "alarm_id": event.alarm_id,
            "device": event.device,
            "joint": event.joint,
            "kind": str(event.kind),
            "severity": str(event.severity),
            "action": event.action,
            "previous": str(event.previous),
            "state": str(event.state),
            "value": event.value,
            "threshold": event.threshold,
            **({"advice": advice} if advice else {}),
        },
    )
