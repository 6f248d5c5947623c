"""The agent service: MQTT telemetry in, the fleet mirrored by its shards, HTTP and CloudWatch metrics out.

Data path and threads (docs/architecture.md draws it):

    connection pool (one or more MQTT connections, each under the broker's per-connection budget)
      --CRT threads: feed()--> device from the topic, its shard (service.shards, `WorkerPlan`)
        --> the shard's queue --> its mirror (service.mirror): decode -> loss -> admit -> twin -> health
            -> servo alarms -> sinks
    HTTP threads (service.http_api) and the CloudWatch thread read `state()`: every shard's report, merged.

One class for one process and for many: the agent is the front (connection pool, HTTP, metrics, lifecycle),
and its shards mirror. `workers=1` (the default, `twin run --workers 1`, the demo and the tests) runs the one
mirror in this process; `workers=N` runs N worker processes, each a mirror of a share of the fleet fed
through a pipe (service.shards). Either way a message takes the same path through the mirror, a device
counts against `telemetry.max_devices` once it has sent a valid message (service.admission), and `/state`
is the shards' reports merged by the same code.

The CRT callback (`feed`) only finds the device in the topic and appends the message to its shard's queue:
decoding there would stall the client's event loop. `feed` is public: a test, a replay or a bridge hands the
agent a message exactly as the broker connection does.

Time: the injected `clock` (monotonic seconds: receive stamps, uptime) and `wall_clock` (epoch seconds:
receive wall time, `started_at`) reach an in-process mirror too, so tests can drive the whole agent on a
timeline of their own; worker processes use the system clocks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import logging
import multiprocessing
import os
import threading
import time
from bisect import bisect_right
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from operator import attrgetter
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from twin.core.alarms import WAITING_STATES, AlarmRecord, worst_first
from twin.core.health import DeviceStatus
from twin.core.topics import TELEMETRY_SUFFIX, device_from_topic
from twin.core.units import Units
from twin.output.alerts import Alert, AlertPublisher, sns_publisher
from twin.output.emf import EmfFileWriter, EmfPublisher, FleetTotals, UnsentCount, unsent_path
from twin.output.history_feed import HistoryProcess, HistoryStartError, WriterFigures
from twin.output.sinks import TwinSink
from twin.service.admission import TOO_MANY_DEVICES, DeviceBudget
from twin.service.calibrations import (
    CalibrationBook,
    CalibrationWatcher,
    open_store,
    push_hint,
    refused_effect,
    store_location,
    store_option,
)
from twin.service.config import AgentConfig, ConfigError, pool_settings
from twin.service.console import (
    ArmView,
    FleetRow,
    ForgetOffer,
    HeldArm,
    Listening,
    SessionCatalog,
    device_rows,
    held_arms,
    rerun_viewer_url,
)
from twin.service.event_journal import EventJournal
from twin.service.events import Event, EventKind, EventLevel, EventQuery, EventStore, FleetWatch
from twin.service.logs import setup_logging, thread_stack
from twin.service.persist import NotSavedError, PreviousRun, StateFile
from twin.service.shards import (
    ASK_TIMEOUT_S,
    CHECKPOINT_EVERY_S,
    SINK_UNWRITTEN_SUFFIX,
    AckManyRequest,
    AckOutcome,
    AckRequest,
    AckResult,
    AlarmsRequest,
    ArmForgotten,
    ArmNotForgettableError,
    ArmNotFoundError,
    ArmRequest,
    AskTimedOutError,
    CalibrationsRequest,
    CheckpointRequest,
    EventsRequest,
    FleetRowsRequest,
    ForgetRequest,
    ForgetTimedOutError,
    MirrorCheckpoint,
    MirrorReport,
    Reply,
    ReportRequest,
    Request,
    RestoreRequest,
    Shard,
    StatusesRequest,
    StopReport,
    UnheardArm,
    UnheardRequest,
    WorkerError,
    WorkerExit,
    WorkerPlan,
    WorkerShard,
    acked_many_of,
    acknowledged_of,
    alarms_of,
    applied_of,
    arm_reply_of,
    checkpoint_of,
    events_of,
    fleet_rows_of,
    forgotten_of,
    merge_reports,
    report_of,
    restored_of,
    statuses_of,
    unheard_of,
    with_dropped,
    worker_config,
)
from twin.service.stall import StallWatch
from twin.service.state import (
    AgentInfo,
    AgentState,
    AlarmInfo,
    BrokerState,
    ConnectionState,
    DeviceState,
    HealthReport,
    HistoryState,
    MirrorStatus,
    RecordingState,
    WorkerInfo,
)
from twin.service.workerstart import start_fork_server, worker_context
from twin.transport.mailbox import UNTRACKED_KEY
from twin.transport.plan import PoolSettings
from twin.transport.pool import ConnectionPool

if TYPE_CHECKING:
    from twin.robot.model import RobotModel
    from twin.service.http_api import AgentHttpServer
    from twin.service.mirror import Mirror

log = logging.getLogger(__name__)

Clock = Callable[[], float]
_T = TypeVar("_T")

# With worker processes, a merged state is reused for this long: /stream clients, /metrics and the CloudWatch
# thread read it often, and each reading asks every worker. An in-process mirror is read afresh every time.
STATE_REUSE_S = 0.05
# How often the agent looks for a worker process to start again.
SUPERVISE_EVERY_S = 0.5
# The supervisor counts each step it gets past (a shard looked after, a request answered, the state kept); one
# that has not got past any for this long is stuck (a lock a stuck thread holds, a disk that hangs): nothing
# would start a dead worker again, keep state or collect events, while the main thread still told systemd's
# watchdog all was well. The agent then fails, so `twin run` exits and systemd starts it again. Its longest
# step is a worker started again: up to START_TIMEOUT_S (120 s) for the new process, then an ask or two for
# its restore (ASK_TIMEOUT_S each) and the messages sent again, so well within this.
SUPERVISOR_STUCK_S = 300.0
# At a stop, the alert publisher has at least this long for what is pending, even when the workers' flush took
# the whole shutdown budget (the unit's stop timeout leaves room for it: docs/host.md).
ALERTS_STOP_MIN_S = 5.0
# ... and the history writer at least this long for its last commit.
HISTORY_STOP_MIN_S = 5.0
# What a failed start gives what it launched to stop (the workers, then the history writer), each.
FAILED_START_STOP_S = 10.0
# feed() remembers where each topic goes (its shard and mailbox key) for this many topics at most; beyond
# that (junk on invented topics) it starts over, so memory stays bounded.
MAX_ROUTES = 16_384
# The forgets that timed out the supervisor still completes once their mirror gets to them (forget_arm): a
# person's or the sweep's, a few at a time; past this the oldest is left to the next checkpoint alone.
MAX_PENDING_FORGETS = 256
# The arms held by a refused calibration the Fleet page names one by one; the rest as a count.
MAX_HELD_NOTICES = 5
# An arm not tracked whose messages are all refused is named on the Fleet page (`_unheard_notices`) once this
# many were, the last no longer ago than UNHEARD_RECENT_S: a new arm's first messages, refused while units =
# auto decides, do not count, nor does one message of garbage under an invented id; an edge mended or switched
# off leaves the page after a minute.
UNHEARD_MIN_REJECTED = 10
UNHEARD_RECENT_S = 60.0
# How often the agent looks for arms OFFLINE longer than telemetry.forget_offline_after_s.
FORGET_SWEEP_S = 5.0


def long_offline(
    rows: Sequence[FleetRow],
    wall: float,
    after_s: float,
    started_wall: float,
    configured: frozenset[str],
    *,
    unseen_after_s: float = 0.0,
) -> list[tuple[str, float]]:
    """The arms `_forget_long_offline` forgets, with how long each has been silent: OFFLINE and silent
    `after_s` or more (one not heard in this run, kept for its alarms: since the agent's start), not listed
    in the config, and its worker running (a restarting one's rows are its checkpoint's). One with an alarm
    ACTIVE or LATCHED (not seen by a person yet) only once silent `unseen_after_s` (0: never), so a fleet
    whose arms leave with an alarm up does not fill every max_devices place with them for good."""
    out = []
    for row in rows:
        if row.status != "OFFLINE" or row.device in configured or row.mirror != "running":
            continue
        horizon = unseen_after_s if row.unacknowledged else after_s
        silent = wall - (row.last_seen if row.last_seen is not None else started_wall)
        if horizon and silent >= horizon:
            out.append((row.device, silent))
    return out


def _named_then_counted(lines: list[str], what: str) -> list[str]:
    """A Fleet page notice per arm for the first MAX_HELD_NOTICES arms, then one line counting the rest
    (`what` they are), whom the Events page names: a fleet of them must not bury the page."""
    if len(lines) <= MAX_HELD_NOTICES:
        return lines
    more = len(lines) - MAX_HELD_NOTICES
    return [*lines[:MAX_HELD_NOTICES], f"and {more} more arm(s) {what} (the Events page names them)"]


def _spoken(seconds: float) -> str:
    """A span as a person reads it: 45 s, 12 min, 5 h, 8 days."""
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= 2 * size:
            return f"{seconds / size:.0f} {unit}"
    return f"{seconds:.0f} s"


def _check_workers(config: AgentConfig, workers: int, sinks: Sequence[TwinSink]) -> None:
    """What only one process can do: extra sinks and the Rerun stream need the in-process mirror."""
    if workers > 1 and sinks:
        raise ValueError("extra sinks run in the agent's own process: pass them with workers=1")
    if workers > 1 and config.rerun.enabled:
        raise ConfigError(
            "[rerun] streams one recording from one process: run with --workers 1 ([twin] workers = 1) "
            "to stream to Rerun, or turn [rerun] off"
        )


class AgentService:
    """Config -> connection pool -> shards (mirrors) -> HTTP and metrics. See the module doc.

    Lifecycle: `start()` (returns once every mirror runs; the broker connection itself is asynchronous; raises
    OSError when the HTTP address is taken, ConfigError when a worker finds a setting it cannot work with,
    WorkerError when a worker cannot start), `stop()` (idempotent: unsubscribes, lets every mirror handle what
    is queued and close its sinks (final USD save, history's last commit), stops HTTP). `state()`,
    `healthz()`, `alarms()`, `acknowledge_alarm()` and `feed()` may be called from any thread. `sinks` are
    extra outputs of an in-process mirror (it closes them in `stop()`); worker processes build theirs from the
    config (service.outputs).
    """

    def __init__(
        self,
        config: AgentConfig,
        *,
        workers: int = 1,
        sinks: Sequence[TwinSink] = (),
        clock: Clock = time.monotonic,
        wall_clock: Clock = time.time,
        sessions: SessionCatalog | None = None,
    ) -> None:
        # Everything that can be wrong with the configuration is found here (an in-process mirror loads the
        # model and the calibration now), before any thread or socket.
        _check_workers(config, workers, sinks)
        # Then the agent's parts and state, a declaration a line.
        self.config = config
        self._clock = clock
        self._wall_clock = wall_clock
        t = config.telemetry
        self._prefix = t.topic_prefix
        self.plan = WorkerPlan(max(1, workers), () if t.all_devices else t.devices)
        self._mirror: Mirror | None = None
        # Telemetry history is written by a process of its own, fed by every mirror (output.history_feed).
        self._context = multiprocessing.get_context("spawn")
        self._history = self._history_process(config)
        self._shards = self._build_shards(config, sinks)
        self._pool_settings = pool_settings(config)
        self._pool = ConnectionPool(config.broker, self._pool_settings, self.feed, clock=clock)
        self.topic_filters = self._pool.topic_filters
        self._reuse_s = STATE_REUSE_S if self._mirror is None else 0.0
        self._init_run_state()
        # The console: sessions from history (the reader lives in ops/; `twin run` hands it in), and the
        # twin's events: the agent's own (broker, workers) and every mirror's, collected by the supervisor.
        self._sessions = sessions
        self._events = EventStore(config.twin.events_capacity, wall_clock=wall_clock)
        self._watch = FleetWatch(self._events)
        self._events_seen: dict[int, int] = {}
        self._events_held: list[Event] = []  # collected from a mirror, for the next round (_collect_events)
        self._events_lock = threading.Lock()  # a supervisor round and the stop's last collection
        self._workers_seen: dict[int, tuple[bool, int]] = {}
        self._history_seen = (0, 0)  # the history writer's exits and restarts the events have told
        self._state_file = StateFile(config.twin.state_file) if config.twin.state_file else None
        # The events over a restart (service.event_journal): read back and subscribed at start().
        self._journal = _event_journal(config)
        # Set to make the supervisor take checkpoints now (an acknowledgement must reach the state file).
        self._wake = threading.Event()
        # Held while the supervisor takes, confirms and saves checkpoints, and while a forget does: a
        # checkpoint taken before a forget must not replace the one taken after it (forget_arm).
        self._keep_lock = threading.Lock()
        self.stop_reports: dict[int, StopReport | None] = {}
        # Servo alarm transitions to the alarm topic (docs/servo-health.md, "Alarm e-mails"): the events
        # every mirror's alarms make, once collected here, go to the publisher.
        self._alerts = alert_publisher(config) if config.alerts.enabled else None
        if self._alerts is not None:
            self._events.subscribe(self._offer_alert)
        # Each arm's own calibration (docs/agent.md, "Calibration"): watched here, once for every shard, and
        # handed to each; the last hand-over is kept for a worker that is started again.
        self._calibration_request = CalibrationsRequest()
        self._calibrations = self._calibration_watcher(config)
        self._calibration_store = store_location(self._calibrations.store if self._calibrations else None)
        self._routes: dict[str, tuple[Shard, str]] = {}

    def _history_process(self, config: AgentConfig) -> HistoryProcess | None:
        """The history writer process's handle, with the agent's logging for it; None with history off."""
        settings = history_settings(config)
        if settings is None:
            return None
        return HistoryProcess(settings, self._context, log=(setup_logging, config.log.level))

    def _init_run_state(self) -> None:
        """What start() and stop() set: the HTTP server, the metrics publisher, the supervisor, whether and
        since when the agent runs, the merged state it reuses for a moment, and the forgets still pending."""
        self._http: AgentHttpServer | None = None
        self._emf: EmfPublisher | None = None
        self._supervisor: threading.Thread | None = None
        self._supervisor_turns = 0  # the steps it got past (_turned)
        self._supervisor_watch = StallWatch(SUPERVISOR_STUCK_S)
        self._supervisor_stuck = False
        self._supervisor_ended = False  # its thread ended while the agent ran (_supervise)
        self._supervisor_watch_lock = threading.Lock()
        self._running = False
        self._stopping = threading.Event()
        self._stop_lock = threading.Lock()
        self._started_pool = False
        self._started_mono: float | None = None
        self._started_wall: float | None = None
        self._state_lock = threading.Lock()
        self._cached: tuple[float, AgentState] | None = None
        # The arms whose forget got no answer in time, by the index of their shard and its restart count when
        # asked (under the keep lock): the mirror may still forget one, and the agent's own part is then done
        # by `_settle_forgets`.
        self._forgets_pending: dict[str, tuple[int, int]] = {}

    def _calibration_watcher(self, config: AgentConfig) -> CalibrationWatcher | None:
        """The watcher of each arm's calibration file, when the config names where they are."""
        t = config.telemetry
        if not t.calibrations:
            return None
        store = open_store(t.calibrations, region=config.broker.region or config.history.region)
        return CalibrationWatcher(
            store,
            interval_s=t.calibration_poll_s,
            on_change=self._hand_calibrations,
            fallback=t.calibration,
            units=t.units,
        )

    def _build_shards(self, config: AgentConfig, sinks: Sequence[TwinSink]) -> list[Shard]:
        count = self.plan.count
        context = self._context
        budget = DeviceBudget(config.telemetry.max_devices, count, context)
        link = self._history.link if self._history is not None else None
        if count == 1:
            # MuJoCo (and USD when recording) load here, with the mirror, not when the module is imported.
            from twin.service.mirror import LocalShard  # noqa: PLC0415

            local = LocalShard(
                config,
                budget=budget,
                clock=self._clock,
                wall_clock=self._wall_clock,
                sinks=sinks,
                history=link,
            )
            self._mirror = local.mirror
            return [local]
        # Workers are forked from a server that has imported the mirror (NumPy, MuJoCo) once: N workers
        # started, or one started again after a crash, do not each pay the imports (service.workerstart).
        workers = worker_context()
        return [
            WorkerShard(i, worker_config(config, self.plan, i), budget, workers, link) for i in range(count)
        ]

    # -------------------------------------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Start the mirrors (and wait until each runs), the HTTP server, the subscription and the metrics, in
        that order, so nothing a message triggers can meet a half-built agent. See the class doc for what it
        raises."""
        if self._running:
            return
        self._started_mono = self._clock()
        self._started_wall = self._wall_clock()
        # First, so this run's events follow the ones read back and its own start.
        previous = self._state_file.previous_run() if self._state_file is not None else None
        last = self._restore_events()
        # A run before left its state file but no events (an upgrade walk: nothing said they were gone).
        self._emit_started(_previous_stopped(last, previous), unkept=last is None and previous is not None)
        self._http = self._launch_mirrors()
        self._running = True
        self._supervisor = threading.Thread(target=self._supervise, name="twin-supervisor", daemon=True)
        self._supervisor.start()
        if self._calibrations is not None:
            self._calibrations.start()
        if self._alerts is not None:
            self._alerts.start()
        self._http.start()
        cw = self.config.cloudwatch
        if cw.emf_file:
            # The failed publishes no document told yet, kept beside the file: a crash while the disk is full
            # must not lose them (docs/servo-health.md, "metrics unwritten").
            self._emf = EmfPublisher(
                EmfFileWriter(cw.emf_file),
                cw.agent_name,
                self._fleet_totals,
                interval_s=cw.interval_s,
                unsent=UnsentCount(unsent_path(cw.emf_file)),
            )
            self._emf.start()
        workers = self._worker_infos({}, {})
        log.info(
            "agent started",
            extra={
                "broker": self.config.broker.url,
                "topics": self.topic_filters,
                "http": self._http.url,
                "mode": self.config.twin.mode,
                "units": self.config.telemetry.units,
                # Mirrors, not processes: one mirror runs in the agent's own process (no pid of its own), and
                # "workers": 0 for `--workers 1` read as no mirror at all (a walk).
                "workers": len(self._shards),
                "worker_pids": [w.pid for w in workers],
            },
        )

    def _launch_mirrors(self) -> AgentHttpServer:
        """The workers' fork server and the broker connection and subscription first, so they run while the
        rest starts; then history's writer and every mirror (each waited for), the alarms of the state file
        and each arm's calibration, and only then does any message reach a mirror (Shard.open). Returns the
        HTTP server, bound but not serving yet. What was launched is stopped again when a step fails."""
        opened = False
        try:
            if self.plan.count > 1:
                # Already running when `twin run` started it; otherwise it starts importing now, beside what
                # follows.
                start_fork_server(self.config.twin.model)
            # Connecting and subscribing (TLS and SigV4 to IoT Core) overlap the processes' start, most of a
            # cold start (docs/performance.md, "Footprint"): what arrives meanwhile waits in the shards'
            # queues, bounded as always, and is handed over once each mirror has what it needs below.
            self._pool.start()
            self._started_pool = True
            # The HTTP stack (Starlette, uvicorn; about 0.15 s) loads while the connection is made on awscrt's
            # threads, not before it starts.
            from twin.service.http_api import AgentHttpServer  # noqa: PLC0415

            if self._history is not None:
                # Before the mirrors, so their feeds find it listening.
                self._launch_history(self._history)
            for shard in self._shards:
                shard.launch()
            for shard in self._shards:
                shard.await_ready()
            self._restore_state_file()
            if self._calibrations is not None:
                # Before any message reaches a mirror, so the first ones already decode with each arm's own.
                self._calibrations.poll()
            for shard in self._shards:
                shard.open()
            opened = True
            return AgentHttpServer(
                self,
                self.config.http.host,
                self.config.http.port,
                stream_rate_hz=self.config.http.stream_rate_hz,
                settings=self.config.http,
                sessions=self._sessions,
                rerun_url=rerun_viewer_url(self.sinks),
            )
        except BaseException:
            self._abandon_start(opened=opened)
            raise

    def _abandon_start(self, *, opened: bool) -> None:
        """A start that failed: stop what it launched and report that stop, from what each shard said as it
        ended, once. The agent counts as stopped: the stop() a caller makes next (`twin run` does) returns
        at once. Were it to stop the shards again, it would find their pipes closed, take every worker for
        one killed at the budget, and save an empty state file over the alarms it kept."""
        with self._stop_lock:
            self._stopping.set()
        if self._started_pool:
            with contextlib.suppress(Exception):
                self._pool.stop(5.0)
            self._started_pool = False
        if self._history is not None:
            self._history.stopping()
        self._stop_shards(time.monotonic() + FAILED_START_STOP_S)
        self._collect_last_events()
        if self._alerts is not None:
            # Never started (start() starts it once the mirrors run), but its stop flushes once: an alarm
            # the mirrors raised on what they handled (an in-process mirror drains its queue) is sent.
            self._alerts.stop(ALERTS_STOP_MIN_S)
        if opened:
            # Messages reached the mirrors, which had the state file's alarms: what they hold now is kept.
            # Before that the file is left as it is: nothing has changed what it holds.
            self._keep_state(final=True)
        if self._history is not None:
            self._history.stop(timeout=FAILED_START_STOP_S)
        unwritten, killed = self._unwritten()
        self._report_stop(FAILED_START_STOP_S, unwritten, killed, "the agent stopped: its start failed")

    def stop(self, timeout: float | None = None) -> None:
        """Unsubscribe, let every mirror handle what is queued for it, flush its sinks and end, stop the
        metrics and HTTP, all within `timeout` seconds (default: `[twin] shutdown_budget_s`); a worker still
        running then is killed. Logs what could not be written, and keeps the alarms in the state file.
        Idempotent; nothing to do after a start() that failed (it stopped what it launched itself)."""
        with self._stop_lock:
            if self._stopping.is_set():
                return
            self._stopping.set()
        budget = self.config.twin.shutdown_budget_s if timeout is None else timeout
        deadline = time.monotonic() + budget
        self._wake.set()
        log.info("agent stopping", extra={"shutdown_budget_s": budget})
        if self._started_pool:
            try:
                self._pool.stop(min(budget / 4.0, 5.0))
            except Exception:
                log.exception("stopping the connection pool failed")
        if self._calibrations is not None:
            self._calibrations.stop(min(5.0, max(0.1, deadline - time.monotonic())))
        if self._supervisor is not None:
            # It may be starting a worker again (up to START_TIMEOUT_S): the budget does not wait for that.
            self._supervisor.join(min(5.0, max(0.1, deadline - time.monotonic())))
        last_totals = None
        if self._emf is not None:
            # Its thread stops first, so the last document below follows the last one it wrote.
            self._emf.stop(5.0)
            last_totals = self._last_totals()
        if self._history is not None:
            # No writer started again from here: one that is down (its restart pause) is not waited for.
            self._history.stopping()
        self._stop_shards(deadline)
        self._collect_last_events()
        self._keep_state(final=True)
        if self._history is not None:
            # Last of the budget: every mirror's feed has handed over its rows; the writer commits them (a
            # store that fails is retried until the budget ends), then exits.
            self._history.stop(max(HISTORY_STOP_MIN_S, deadline - time.monotonic()))
        unwritten, killed = self._unwritten()
        if last_totals is not None:
            self._publish_last(last_totals, unwritten)
        if self._alerts is not None:
            # After the last events were collected: what is pending still goes out, with at least a few
            # seconds of its own when the workers took the whole budget (systemd's stop timeout leaves them).
            self._alerts.stop(min(15.0, max(ALERTS_STOP_MIN_S, deadline - time.monotonic())))
        if self._http is not None:
            self._http.stop()
        self._running = False
        self._report_stop(budget, unwritten, killed, "the agent stopped")

    def _stop_shards(self, deadline: float) -> None:
        # Closed together, so the workers hand over and flush in parallel, then waited for one by one.
        for shard in self._shards:
            shard.close()
        for shard in self._shards:
            self.stop_reports[shard.index] = shard.join(deadline)

    def _unwritten(self) -> tuple[Counter[str], list[int]]:
        """After the shards and the history writer stopped: what they could not write, by kind
        (`history_rows`, `history_rows_unread`, `<sink>_items`), and the workers killed at the budget."""
        unwritten: Counter[str] = Counter()
        killed = []
        for index, report in sorted(self.stop_reports.items()):
            if report is None:
                killed.append(index)
            else:
                unwritten.update(report.unwritten)
        history = self._history
        if history is not None:
            # The writer process's own: what it could not commit before it ended.
            unwritten["history_rows"] += history.unwritten_rows()
            # What the feeds wrote to a writer's socket and no writer read (one died, or the last stopped
            # reading at its budget): nothing else sees these. The feeds count it in shared memory, so the
            # figure holds across workers started again or killed at the budget.
            unwritten["history_rows_unread"] += history.count_unread()
        return +unwritten, killed  # unary plus: the kinds with nothing unwritten go

    def _last_totals(self) -> FleetTotals | None:
        """Before the workers stop: the CloudWatch totals the last EMF document starts from (after the stop
        they could only be pieced together from checkpoints). Asked of every worker, as a /metrics scrape
        is: one that does not answer costs its ask timeout of the budget, and would be killed anyway."""
        try:
            return self._fleet_totals()
        except Exception:
            log.exception("the CloudWatch totals could not be read at the stop")
            return None

    def _publish_last(self, totals: FleetTotals, unwritten: Counter[str]) -> None:
        """The last EMF document: the totals read before the workers stopped, with history's as it ended,
        plus what the stop could not write, so a loss at shutdown reaches HistoryRowsDropped and SinkDrops
        (and their alarms) too."""
        assert self._emf is not None
        history = self._history
        if history is not None and totals.history_rows_dropped is not None:
            # After its stop: the writer's last answer (its drops while stopping) and the rows lost, the
            # unread ones included (count_unread).
            dropped = max(totals.history_rows_dropped, history.figures().rows_not_written)
            dropped += unwritten["history_rows"]
            totals = dataclasses.replace(totals, history_rows_dropped=dropped)
        samples = sum(n for kind, n in unwritten.items() if kind.endswith(SINK_UNWRITTEN_SUFFIX))
        totals = dataclasses.replace(totals, sink_drops=totals.sink_drops + samples)
        try:
            self._emf.publish_once(totals)
        except Exception as exc:
            self._emf.failed(exc)
            log.exception("the last CloudWatch metrics could not be written")

    def _report_stop(self, budget: float, unwritten: Counter[str], killed: list[int], message: str) -> None:
        """The stop's own event (`message`), then the journal written out, then one log line: the agent
        stopped, and what it could not write (ERROR when anything)."""
        self._close_events(message, unwritten, killed)
        fields = {"unwritten": dict(unwritten), "workers_killed": killed, "shutdown_budget_s": budget}
        if unwritten or killed:
            log.error(
                "agent stopped; not everything was written: %s%s",
                _unwritten_text(unwritten) or "nothing counted",
                f"; worker(s) {killed} killed at the {budget:g} s budget, what they held is lost"
                if killed
                else "",
                extra=fields,
            )
        else:
            log.info("agent stopped", extra=fields)

    def _supervise(self) -> None:
        try:
            self._supervise_loop()
        except Exception:
            # Nothing would start a dead worker again, keep state or collect events: the agent fails
            # (`running`), so `twin run` exits and systemd starts it again; the traceback says why.
            log.exception(
                "the agent's supervisor failed; the agent stops (under systemd, its unit starts it again)"
            )
        finally:
            # Only a stop ends it otherwise; set after the log line, so whoever sees the agent fail finds it.
            self._supervisor_ended = not self._stopping.is_set()

    def _supervise_loop(self) -> None:
        next_checkpoint = time.monotonic() + CHECKPOINT_EVERY_S
        next_forget = time.monotonic() + FORGET_SWEEP_S
        while not self._stopping.is_set():
            self._wake.wait(SUPERVISE_EVERY_S)
            if self._stopping.is_set():
                return
            self._turned()
            urgent = self._wake.is_set()
            self._wake.clear()
            for shard in self._shards:
                if self._stopping.is_set():
                    return
                shard.supervise()
                self._turned()
            if self._history is not None:
                self._history.supervise()
                self._watch_history_writer(self._history)
            self._collect_events()
            if self._journal is not None:
                self._journal.flush()
            now = time.monotonic()
            if urgent or now >= next_checkpoint:
                next_checkpoint = now + CHECKPOINT_EVERY_S
                self._keep_state()
            if self.config.telemetry.forget_offline_after_s and now >= next_forget:
                next_forget = now + FORGET_SWEEP_S
                try:
                    self._forget_long_offline()
                except Exception:
                    # The supervisor restarts workers and keeps state: a sweep's fault must not end it.
                    log.exception("looking for arms silent past telemetry.forget_offline_after_s failed")

    def _turned(self) -> None:
        """The supervisor got past one more step (SUPERVISOR_STUCK_S). Only its own steps count: an
        acknowledgement's state file write on an HTTP thread, going by, must not hide a supervisor stuck."""
        if threading.current_thread() is self._supervisor:
            self._supervisor_turns += 1

    def _forget_long_offline(self) -> None:
        """Forget each arm silent for telemetry.forget_offline_after_s with no alarm waiting for a person, as
        an operator's forget does (kept at once, one event): a fleet whose ids come and go otherwise filled
        every max_devices place with arms retired long ago, refusing new ones until a person forgot them. One
        with alarms no person has seen only after telemetry.forget_unseen_after_s, its event naming them."""
        telemetry = self.config.telemetry
        started = self._started_wall if self._started_wall is not None else self._wall_clock()
        configured = frozenset(() if telemetry.all_devices else telemetry.devices)
        rows = self.fleet_rows()
        unseen = {row.device for row in rows if row.unacknowledged}
        gone = long_offline(
            rows,
            self._wall_clock(),
            telemetry.forget_offline_after_s,
            started,
            configured,
            unseen_after_s=telemetry.forget_unseen_after_s,
        )
        waiting = self._unseen_alarms(unseen.intersection(device for device, _ in gone))
        for device, silent in gone:
            if self._stopping.is_set():
                return
            reason = f"by the agent: silent for {_spoken(silent)} (telemetry.forget_offline_after_s)"
            if device in unseen:
                named = "; ".join(waiting.get(device, ())) or "not listed"
                reason = (
                    f"by the agent: silent for {_spoken(silent)} with alarms no person has seen "
                    f"(telemetry.forget_unseen_after_s), dropped unseen: {named}"
                )
            try:
                self.forget_arm(device, reason=reason)
            except (ArmNotFoundError, ArmNotForgettableError, WorkerError) as exc:
                # Heard again, forgotten by a person meanwhile, or its worker restarting: the next sweep.
                log.debug("arm %s not forgotten: %s", device, exc)

    def _unseen_alarms(self, devices: set[str]) -> dict[str, list[str]]:
        """The alarms of `devices` no person has seen (ACTIVE, LATCHED), as the forget's event names them."""
        if not devices:
            return {}
        named: dict[str, list[str]] = {}
        for alarm in self.alarms(devices=devices):
            if alarm.device in devices and alarm.state in WAITING_STATES:
                named.setdefault(alarm.device, []).append(f"{alarm.alarm_id} {alarm.state}: {alarm.message}")
        return named

    # ------------------------------------------------------------------------------------------ state kept

    def _keep_state(self, *, final: bool = False) -> None:
        """Each worker's checkpoint (its restart's starting point) and the alarms the state file keeps.
        `final`: the shards have stopped; their stop reports hold their alarms."""
        workers = self._mirror is None
        if not workers and self._state_file is None and not self._forgets_pending:
            return
        with self._keep_lock:
            self._keep_state_now(workers, final=final)

    def _keep_state_now(self, workers: bool, *, final: bool) -> None:
        """`_keep_state`, under the lock a forget takes too."""

        def alarms_of(shard: Shard) -> tuple[AlarmRecord, ...] | None:
            if final:
                report = self.stop_reports.get(shard.index)
                return None if report is None else report.alarms
            checkpoint = self._checkpoint(shard, alarms_only=not workers)
            if checkpoint is None:
                return None
            self._settle_forgets(shard, checkpoint)
            return checkpoint.alarms

        records = self._alarm_records(alarms_of)
        if self._state_file is not None:
            # `stopped` only on the stop's write: a file that still says it ran tells the next start this
            # run ended without stopping (persist's module doc).
            self._state_file.save(records, time.monotonic(), time.time(), stopped=final)

    def _alarm_records(
        self, alarms_of: Callable[[Shard], tuple[AlarmRecord, ...] | None]
    ) -> list[AlarmRecord]:
        """Every shard's alarms as `alarms_of` gets them, else as its last checkpoint said (restarting, or
        gone)."""
        records: list[AlarmRecord] = []
        for shard in self._shards:
            alarms = alarms_of(shard)
            self._turned()
            if alarms is None:
                checkpoint = shard.checkpoint
                alarms = () if checkpoint is None else checkpoint.alarms
            records.extend(alarms)
        return records

    def _checkpoint(
        self, shard: Shard, *, alarms_only: bool, confirm: bool = True
    ) -> MirrorCheckpoint | None:
        """The shard's checkpoint, None when it cannot give one. `confirm`: the agent may drop the messages
        it counts (shard.confirm); not for one taken only for the state file between two of the
        supervisor's."""
        if not shard.answering:
            return None
        try:
            checkpoint = checkpoint_of(shard.request(CheckpointRequest(alarms_only))())
        except (WorkerError, TimeoutError) as exc:
            log.warning("no checkpoint of shard %d: %s", shard.index, exc)
            return None
        if confirm:
            shard.confirm(checkpoint)
        return checkpoint

    def _restore_state_file(self) -> None:
        """Give each mirror the alarms the state file kept for its devices (before any message)."""
        if self._state_file is None:
            return
        records = self._state_file.load(time.monotonic(), time.time())
        by_shard: dict[int, list[AlarmRecord]] = {}
        for record in records:
            by_shard.setdefault(self.plan.worker_of(record.device), []).append(record)
        for shard in self._shards:
            mine = tuple(by_shard.get(shard.index, ()))
            if not mine:
                continue
            restored = restored_of(shard.request(RestoreRequest(alarms=mine))())
            # Also what the worker starts from if it dies before its first checkpoint.
            kept = tuple(sorted({record.device for record in mine}))
            shard.confirm(MirrorCheckpoint(alarms=mine, at=time.monotonic(), kept=kept))
            log.info(
                "alarms restored from the state file",
                extra={"shard": shard.index, "alarms": restored.alarms, "path": str(self._state_file.path)},
            )

    @staticmethod
    def _launch_history(history: HistoryProcess) -> None:
        try:
            history.launch()
        except HistoryStartError as exc:
            if exc.setting:
                raise ConfigError(str(exc)) from exc
            raise

    def __enter__(self) -> AgentService:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        """Started, not stopping, no mirror gone for good (a dead worker process is started again) and the
        supervisor not stuck."""
        running = self._running and not self._stopping.is_set()
        return running and not any(s.failed for s in self._shards) and not self._supervisor_stalled()

    def _supervisor_stalled(self) -> bool:
        """Whether the supervisor ended, or got past no step for SUPERVISOR_STUCK_S (said once, with where it
        waits). Judged by whoever asks `running` (the main thread of `twin run`, every second), never by
        itself."""
        if self._supervisor_ended:
            return True
        with self._supervisor_watch_lock:
            if self._supervisor_stuck or self._supervisor is None:
                return self._supervisor_stuck
            stalled = self._supervisor_watch.look(self._supervisor_turns, time.monotonic(), SUPERVISE_EVERY_S)
            if stalled is None:
                return False
            log.error(
                "the agent's supervisor has got past no step for %.0f s: it is stuck, so no worker would be "
                "started again, no state kept and no event collected; the agent stops (under systemd, its "
                "unit starts it again). It waits in:\n%s",
                stalled,
                thread_stack(self._supervisor),
                extra={"stalled_s": round(stalled, 1)},
            )
            # Failed only once said: whoever sees the agent stop finds the reason already in its log.
            self._supervisor_stuck = True
            return True

    @property
    def http_url(self) -> str:
        if self._http is None:
            raise RuntimeError("the HTTP server starts with start()")
        return self._http.url

    def wait_subscribed(self, timeout: float) -> bool:
        return self._started_pool and self._pool.wait_subscribed(timeout)

    @property
    def robot(self) -> RobotModel:
        """The in-process mirror's robot model (worker processes load their own)."""
        return self._in_process().robot

    @property
    def recording_path(self) -> Path | None:
        """The in-process mirror's newest USD session file on disk, None once none is (each worker process
        records its own: `agent.workers`)."""
        return self._mirror.recording_path if self._mirror is not None else None

    @property
    def sinks(self) -> tuple[TwinSink, ...]:
        """The in-process mirror's sinks (the recording first, when there is one); empty before start() and
        with worker processes."""
        return self._mirror.sinks if self._mirror is not None else ()

    def _in_process(self) -> Mirror:
        if self._mirror is None:
            raise RuntimeError("the mirrors run in worker processes (workers > 1)")
        return self._mirror

    # ------------------------------------------------------------------------------------------- messages

    def feed(self, topic: str, payload: bytes, received_mono: float | None = None) -> None:
        """Hand the agent one message as its broker connections do for each they receive: thread-safe, never
        blocks for long. The message is queued for the shard of the device its topic names (a topic that names
        none goes to the first, where it is counted as rejected) and then mirrored, rejected or refused like
        any other. `received_mono` is when it arrived on the agent's clock (default: now)."""
        recv_mono = self._clock() if received_mono is None else received_mono
        # Every message of the fleet comes through here on a CRT thread: a topic's route is worked out once.
        route = self._routes.get(topic)
        if route is None:
            route = self._route(topic)
        route[0].put(route[1], topic, payload, recv_mono, self._wall_clock())

    def _route(self, topic: str) -> tuple[Shard, str]:
        device = device_from_topic(topic, self._prefix)
        route = (
            (self._shards[0], UNTRACKED_KEY)
            if device is None
            else (self._shards[self.plan.worker_of(device)], device)
        )
        routes = self._routes
        if len(routes) >= MAX_ROUTES:
            routes.clear()
        routes[topic] = route
        return route

    def _forget_route(self, device: str) -> None:
        """Drop the route of a forgotten arm's topic: a fleet whose ids come and go otherwise kept every
        one gone until MAX_ROUTES. A message racing this only puts it back, as it would any route."""
        self._routes.pop(f"{self._prefix}/{device}/{TELEMETRY_SUFFIX}", None)

    # ------------------------------------------------------------------------------------------- requests

    def _ask_all(
        self, request: Request, read: Callable[[Reply], _T], shards: Sequence[Shard] | None = None
    ) -> list[tuple[Shard, _T]]:
        """`request` to every shard (or those of `shards`) that can answer now, then their answers (worker
        processes work on it in parallel); a worker that does not answer is logged and left out."""
        waiting = []
        for shard in self._shards if shards is None else shards:
            if not shard.answering:
                continue
            try:
                waiting.append((shard, shard.request(request)))
            except WorkerError:
                continue  # it died since; the supervisor starts it again
        answers = []
        for shard, wait in waiting:
            try:
                answers.append((shard, read(wait())))
            except WorkerError as exc:
                log.warning("%s", exc)
        return answers

    def _ask_fleet(
        self, request: Request, read: Callable[[Reply], _T], shards: Sequence[Shard] | None = None
    ) -> _FleetAnswers[_T]:
        """`_ask_all` (of `shards`, default all), and the shards that gave no answer to it. Readers show
        those shards' arms and alarms from their latest checkpoints, decided on this one read whatever
        `restarting` says afterwards: a worker passed over while being started again may be running by the
        time `restarting` is read (its arms left /state for that read: seen under load), and one that did
        not answer is not serving them either. An arm and its alarms never leave a reader while its worker
        restarts."""
        asked = self._shards if shards is None else shards
        answers = self._ask_all(request, read, asked)
        answered = {shard.index for shard, _ in answers}
        silent = tuple(shard for shard in asked if shard.index not in answered)
        return _FleetAnswers(answers, silent)

    def _checkpoint_devices(self, silent: Sequence[Shard]) -> dict[str, DeviceState]:
        """The arms of shards that gave no answer, as their latest checkpoints left them (`_ask_fleet`)."""
        # Worker processes share the host's monotonic clock, which their checkpoints are on.
        now = time.monotonic()
        # A page open through a stop read "restarting" on every card, and nothing restarts.
        mirror = MirrorStatus.STOPPING if self._stopping.is_set() else MirrorStatus.RESTARTING
        devices: dict[str, DeviceState] = {}
        for shard in silent:
            devices.update(shard.restarting_devices(self.config.health, now, mirror))
        return devices

    def _checkpoint_alarms(self, silent: Sequence[Shard], *, include_normal: bool) -> list[AlarmInfo]:
        """The alarms of shards that gave no answer, as their latest checkpoints left them (`_ask_fleet`)."""
        # The host's clocks, as the workers read them (their checkpoints' times are on its monotonic one).
        now, wall = time.monotonic(), time.time()
        alarms: list[AlarmInfo] = []
        for shard in silent:
            alarms.extend(shard.restarting_alarms(now, wall, include_normal=include_normal))
        return alarms

    # --------------------------------------------------------------------------------------------- readers

    def state(self) -> AgentState:
        """The agent's typed state for /state, /metrics and /stream: every shard's report merged
        (docs/http-api.md describes every field; `agent.workers` lists the worker processes)."""
        with self._state_lock:
            cached = self._cached
            if cached is not None and time.monotonic() - cached[0] < self._reuse_s:
                return cached[1]
            now = self._clock()
            asked = self._ask_fleet(ReportRequest(), report_of)
            reports = {shard.index: report for shard, report in asked.answers}
            checkpoints = [shard.checkpoint for shard in asked.silent if shard.checkpoint is not None]
            # After the stop a worker process is gone; its recording's figures are its stop report's.
            stopped = {
                shard.index: report.recording
                for shard in asked.silent
                if (report := self.stop_reports.get(shard.index)) is not None and report.recording is not None
            }
            state = merge_reports(
                self._info(now),
                list(reports.values()),
                self._worker_infos(reports, stopped),
                dropped=self._dropped(),
                dropped_total=sum(shard.dropped_total for shard in self._shards),
                restarting=self._checkpoint_devices(asked.silent),
                restarting_untracked=[c.untracked_rejected for c in checkpoints],
                restarting_alarms=[c.alarms_summary for c in checkpoints if c.alarms_summary is not None],
                stopped_recordings=list(stopped.values()),
            )
            if self._history is not None:
                state = dataclasses.replace(
                    state, agent=dataclasses.replace(state.agent, history=self._history_state(self._history))
                )
            own = [
                *(self._journal.sinks() if self._journal is not None else ()),
                *((self._state_file.stats(),) if self._state_file is not None else ()),
                *((self._alerts.sink_stats(),) if self._alerts is not None else ()),
                *((self._emf.sink_stats(),) if self._emf is not None else ()),
            ]
            if own:
                sinks = (*state.agent.sinks, *own)
                state = dataclasses.replace(state, agent=dataclasses.replace(state.agent, sinks=sinks))
            self._cached = (time.monotonic(), state)
            return state

    def _history_state(self, history: HistoryProcess) -> HistoryState:
        """The history writer process's figures, as /state shows them (docs/history.md)."""
        figures = history.figures()
        stats = figures.stats or WriterFigures()
        return HistoryState(
            uri=self.config.history.uri,
            storage_ok=stats.storage_ok,
            rows_committed=stats.rows_committed,
            commits=stats.commits,
            commit_failures=stats.commit_failures,
            rows_dropped=stats.rows_dropped,
            rows_buffered=stats.rows_buffered,
            rejected_rows_committed=stats.rejected_rows_committed,
            maintenance_runs=stats.maintenance_runs,
            maintenance_failures=stats.maintenance_failures,
            rows_expired=stats.rows_expired,
            log_entries_set_aside=stats.log_entries_set_aside,
            last_error=stats.last_error,
            writer_pid=figures.pid,
            writer_restarts=figures.restarts,
            rows_received=figures.rows_received,
            rows_lost=figures.rows_lost,
            lag_s=stats.lag_s,
        )

    def _info(self, now: float) -> AgentInfo:
        """The agent's own part of the state: the process, the broker and the metrics publisher's clock."""
        started = self._started_mono
        return AgentInfo(
            running=self.running,
            pid=os.getpid(),
            started_at=self._started_wall,
            uptime_s=(now - started) if started is not None else 0.0,
            time=self._wall_clock(),
            mode=self.config.twin.mode,
            units=self.config.telemetry.units,
            devices=tuple(self.config.telemetry.devices),
            topic_filters=tuple(self.topic_filters),
            broker=broker_state(self.config.broker.url, self._pool_settings, self._pool, self._started_pool),
            calibration_store=self._calibration_store,
            emf_clock_steps=self._emf.clock_steps if self._emf is not None else None,
        )

    def _worker_infos(
        self, reports: dict[int, MirrorReport], stopped: Mapping[int, RecordingState]
    ) -> tuple[WorkerInfo, ...]:
        """Each worker process's row; a stopped one names the session file its stop report left."""
        infos = []
        for shard in self._shards:
            info = shard.describe(reports.get(shard.index))
            if info is not None and shard.index in stopped:
                info = dataclasses.replace(info, recording=stopped[shard.index].path)
            if info is not None:
                infos.append(info)
        return tuple(infos)

    def _dropped(self) -> Counter[str]:
        """Messages of each device the agent could not hand to its mirror (the most recent devices)."""
        total: Counter[str] = Counter()
        for shard in self._shards:
            total.update(shard.dropped())
        return total

    def notices(self, shown: Collection[str] = ()) -> list[str]:
        """What the console's fleet page shows above the arms: the broker's (`broker_notices`), then each arm
        held by a refused calibration file, and each other arm whose messages are all refused: no card
        shows them. An arm in `shown` has a card: it is not held (one publishing degrees under units=auto
        decodes, as degrees use no calibration)."""
        return [*self.broker_notices(), *self._held_notices(shown), *self._unheard_notices()]

    def _unheard_notices(self) -> list[str]:
        # A walk's arm whose edge sent what the agent refuses had no card, and the empty Fleet page said no
        # arm was heard and pointed at the topic and IAM: the reasons were only on the Events page.
        held = {device for device, _ in self._calibration_request.problems}
        # By id, so that the lines keep their places from one tick of the page to the next.
        arms = sorted(
            (
                arm
                for arm in self._unheard_arms()
                if arm.device not in held
                and arm.rejected >= UNHEARD_MIN_REJECTED
                and arm.last_s <= UNHEARD_RECENT_S
            ),
            key=attrgetter("device"),
        )
        lines = [
            f"{a.device} publishes, but the agent refused all {a.rejected} of its messages (the last: "
            f"{a.reason}), so it has no card: the Events page says why"
            for a in arms
        ]
        return _named_then_counted(lines, "whose messages are all refused")

    def _unheard_arms(self) -> list[UnheardArm]:
        """Every mirror's arms not tracked whose every message was refused. Worker processes': from their
        latest checkpoints (taken every CHECKPOINT_EVERY_S anyway), so a console tick, twice a second, asks
        no worker over its pipe for them; a restarting worker's as its last checkpoint left them."""
        if self._mirror is not None:  # the mirror in this process: asking it is a call, not a pipe's trip
            return [arm for _, part in self._ask_all(UnheardRequest(), unheard_of) for arm in part]
        now = time.monotonic()  # worker processes share the host's monotonic clock, their checkpoints' too
        arms: list[UnheardArm] = []
        for shard in self._shards:
            checkpoint = shard.checkpoint
            if checkpoint is not None:
                since = max(0.0, now - checkpoint.at)
                arms.extend(dataclasses.replace(a, last_s=a.last_s + since) for a in checkpoint.unheard)
        return arms

    def _held_problems(self) -> dict[str, str]:
        """The arms with no calibration to keep (their file was bad at the start), held, by device: why. None
        with units = degrees, which use no calibration (the decoder holds no such arm)."""
        t = self.config.telemetry
        if t.units is Units.DEGREES:
            return {}
        request = self._calibration_request  # read once: a new book may replace it meanwhile
        kept = {device for device, _, _ in request.files}
        # An arm a listed fleet leaves out is never heard: the Fleet page said its messages were refused.
        return {
            device: problem
            for device, problem in request.problems
            if device not in kept and (t.all_devices or device in t.devices)
        }

    def _held_notices(self, shown: Collection[str]) -> list[str]:
        # An arm with no calibration to keep (its file was bad at the start) is held: with the whole fleet
        # subscribed it is never admitted, so only the log and the Events page named it.
        problems = {d: why for d, why in self._held_problems().items() if d not in shown}
        # "its messages are refused" was said of an arm nothing was received from: asked only with one held.
        heard = {a.device for a in self._unheard_arms()} if problems else set()
        lines = [
            f"{device}'s calibration in the store is refused ({problem}), so "
            f"{self._held_words(device, heard)}: push a valid one "
            f"({push_hint(device, self._calibration_store).command})"
            for device, problem in problems.items()
        ]
        return _named_then_counted(lines, "held the same way")

    def _held_words(self, device: str, heard: Collection[str]) -> str:
        if device in heard:
            return (
                "its messages are refused and its twin does not move (its servos' alarms are still checked)"
            )
        if device in self.config.telemetry.devices:
            # Listed, so tracked: its refusals are on its card, not among the arms not tracked, and asking
            # every worker for its rows is a pipe's trip each. The console passes its cards (`shown`), so it
            # gets this only while the arm's worker does not answer and no checkpoint of that worker holds
            # the arm (it died or hangs before its first one): no card then, and "its card says" was untrue.
            # Worded to be true whether it publishes or not.
            return (
                "its messages are refused whenever they come and its twin does not move (its servos' alarms "
                "are still checked); its card, back once its worker answers, says whether any came"
            )
        return (
            "it is held: nothing has been received from it since the agent started, and once it "
            "publishes its messages are refused and its twin stays still (check that it is on and "
            "publishes under this id)"
        )

    def held_arms(self, shown: Collection[str] = ()) -> list[HeldArm]:
        """Every arm `_held_notices` names (it names five), with its alarms, for the Fleet page's links and
        counts: no row has them. Only with an arm held does a console tick ask its mirror their alarms."""
        problems = {d: why for d, why in self._held_problems().items() if d not in shown}
        if not problems:
            return []
        alarms = [a for a in self.alarms(devices=problems) if a.device in problems]
        # A held arm is never admitted, so its refused messages are counted among the arms not tracked (kept
        # beside the 64 most recent other ids: core.health.HELD_REASON).
        refused = {a.device: a.rejected for a in self._unheard_arms() if a.device in problems}
        return held_arms(problems, alarms, refused)

    def broker_notices(self) -> list[str]:
        """/healthz's reasons from the broker: each topic filter it refuses (the arms it covers are never
        heard, so no card can say it), and its quota discarding messages the connection pool cannot take
        on. An arm held by its calibration is not among them: arms come and go without /healthz."""
        if not self._started_pool:
            return []
        refused = [
            f"the broker refused the subscription to {f} ({reason}): no telemetry of it arrives; the agent's "
            "IAM identity must allow iot:Subscribe on it (docs/agent.md, IAM permissions)"
            for f, reason in sorted(self._pool.refused().items())
        ]
        # The quota's losses are counted per arm, but no card says why every arm loses (a walk's /healthz
        # was 200 while the broker discarded a third of the fleet's messages).
        return [*refused, self._pool.quota_notice] if self._pool.quota_notice else refused

    def listening(self) -> Listening:
        """The topic filters the agent subscribes to, and whether every connection of its pool is up (the
        console's fleet page says so while no arm has been heard from)."""
        return Listening(
            tuple(self.topic_filters),
            self._started_pool and self._pool.connected,
            stopping=self._stopping.is_set(),
        )

    def healthz(self) -> HealthReport:
        """Healthy = the agent runs, the broker connection is up and refuses none of its subscriptions, every
        worker process runs and no configured device is OFFLINE.

        With devices = ["*"] no device is configured, so the last rule does not apply: a fleet agent stays
        healthy while individual arms come and go (their status is in /state and /metrics).
        """
        # Each mirror's statuses only, not the state: health checks come often, and a report of 1,000 arms
        # costs its worker the fleet's holding torques and tool points (docs/http-api.md, "GET /healthz").
        asked = self._ask_fleet(StatusesRequest(), statuses_of)
        statuses = {device: DeviceStatus(status) for _, pairs in asked.answers for device, status in pairs}
        restarting = self._checkpoint_devices(asked.silent)
        statuses.update({device: d.health.status for device, d in restarting.items()})
        connected = self._started_pool and self._pool.connected
        running = self.running
        reasons = []
        if not running:
            reasons.append("service not running")
        if not connected:
            reasons.append("broker connection down")
        else:
            reasons.extend(self.broker_notices())
        # A worker process that did not answer is not running (dead, or being started again), as in /state.
        reasons.extend(
            f"worker {shard.index} is not running"
            for shard in asked.silent
            if shard.describe(None) is not None
        )
        configured = () if self.config.telemetry.all_devices else self.config.telemetry.devices
        reasons.extend(
            f"device {d} is OFFLINE" for d in sorted(configured) if statuses.get(d) is DeviceStatus.OFFLINE
        )
        return HealthReport(
            status="ok" if not reasons else "unavailable",
            running=running,
            broker_connected=connected,
            devices=statuses,
            reasons=tuple(reasons),
        )

    def alarms(
        self, *, include_normal: bool = False, devices: Collection[str] | None = None
    ) -> tuple[AlarmInfo, ...]:
        """Servo alarms of every mirror, worst first (GET /alarms); NORMAL ones only when asked. A worker
        being started again lists its alarms from its latest checkpoint. With `devices`: only the mirrors
        of those arms are asked (the others' alarms may come with theirs)."""
        shards = None
        if devices is not None:
            shards = [self._shards[i] for i in sorted({self.plan.worker_of(d) for d in devices})]
        asked = self._ask_fleet(AlarmsRequest(include_normal), alarms_of, shards)
        merged = [a for _, alarms in asked.answers for a in alarms]
        merged.extend(self._checkpoint_alarms(asked.silent, include_normal=include_normal))
        return tuple(sorted(merged, key=alarm_order))

    def acknowledge_alarm(self, alarm_id: str) -> AlarmInfo:
        """ACTIVE -> ACKNOWLEDGED, LATCHED -> NORMAL, by the mirror of the alarm's device. Raises
        twin.core.alarms.AlarmNotFound (unknown id) or NothingToAcknowledge (NORMAL or already ACKNOWLEDGED),
        WorkerError when that device's worker is being started again."""
        device = alarm_id.split("/", 1)[0]
        shard = self._shards[self.plan.worker_of(device)]
        return self._keep_act(
            shard,
            "acknowledgement",
            lambda checkpoint: acknowledged_of(shard.request(AckRequest(alarm_id, checkpoint=checkpoint))()),
        )

    def acknowledge_alarms(self, alarm_ids: Sequence[str]) -> tuple[AckResult, ...]:
        """`acknowledge_alarm` of many ids (POST /alarms/ack), each id's outcome in the order given: one
        request to each worker that mirrors any of them, and the state file written once for them all (one
        write per alarm made a few hundred take minutes). An id whose worker is being started again is
        answered WORKER_UNAVAILABLE, the others are made. Raises NotSavedError (its `result` the outcomes)
        when the state file could not be written."""
        by_shard: dict[int, list[str]] = {}
        for alarm_id in alarm_ids:
            by_shard.setdefault(self.plan.worker_of(alarm_id.split("/", 1)[0]), []).append(alarm_id)

        def make() -> tuple[AckResult, ...]:
            # Every worker asked before any answer is waited for: they take their checkpoints in parallel.
            waits = [self._acknowledge_on(self._shards[index], ids) for index, ids in by_shard.items()]
            results = {r.alarm_id: r for wait in waits for r in wait()}
            return tuple(results[alarm_id] for alarm_id in alarm_ids)

        return self._kept("acknowledgement", make, many=True)

    def _acknowledge_on(self, shard: Shard, alarm_ids: list[str]) -> Callable[[], tuple[AckResult, ...]]:
        """One shard's share of `acknowledge_alarms`, asked now; the returned call waits for its answer and
        confirms its checkpoint (`_confirm_act`). A worker that cannot be asked, or died as it answered:
        every id unavailable."""

        def unavailable(why: str) -> tuple[AckResult, ...]:
            detail = f"{why}; acknowledge again once it runs (GET /state, agent.workers)"
            return tuple(AckResult(a, AckOutcome.WORKER_UNAVAILABLE, None, detail) for a in alarm_ids)

        restarts = shard.restarts
        try:  # a worker being started again refuses the request (WorkerShard.request)
            wait = shard.request(AckManyRequest(tuple(alarm_ids), checkpoint=self._mirror is None))
        except WorkerError as exc:
            why = str(exc)
            return lambda: unavailable(why)

        def answer() -> tuple[AckResult, ...]:
            try:
                acked = acked_many_of(wait())
                self._confirm_act(shard, "acknowledgement", restarts, acked.checkpoint)
            except WorkerError as exc:
                return unavailable(str(exc))
            return acked.results

        return answer

    def forget_arm(self, device: str, *, reason: str = "") -> ArmForgotten:
        """Remove an OFFLINE arm from the fleet, by the mirror of its device (Mirror.forget_arm). Raises
        ArmNotFoundError, ArmNotForgettableError (not OFFLINE, or configured), ForgetTimedOutError when its
        mirror does not answer in time, or WorkerError when that device's worker is being started again."""
        shard = self._shards[self.plan.worker_of(device)]
        if not shard.answering:
            raise WorkerError(f"worker {shard.index} is being started again")

        def forget(checkpoint: bool) -> tuple[ArmForgotten, MirrorCheckpoint | None]:
            request = ForgetRequest(device, checkpoint=checkpoint, reason=reason)
            restarts = shard.restarts
            try:
                forgotten = forgotten_of(shard.request(request)())
            except (AskTimedOutError, TimeoutError) as exc:  # TimeoutError: the mirror in this process's wait
                log.warning("the forget of %s got no answer in time: %s", device, exc)
                # Still waiting in the mirror: the supervisor does the agent's part once it is made.
                self._forgets_pending.pop(device, None)
                if len(self._forgets_pending) >= MAX_PENDING_FORGETS:
                    del self._forgets_pending[next(iter(self._forgets_pending))]
                self._forgets_pending[device] = (shard.index, restarts)
                raise ForgetTimedOutError(forget_timed_out(device, shard)) from exc
            # Forgotten now, and its part done here: an earlier forget of it that timed out is settled, and
            # must not be settled again on an arm of that name heard after. Not on a 404, which may be that
            # earlier forget made.
            self._forgets_pending.pop(device, None)
            return dataclasses.replace(forgotten, checkpoint=None), forgotten.checkpoint

        return self._keep_act(shard, "forget", forget, kept=lambda: self._forgotten(shard, device))

    def _forgotten(self, shard: Shard, device: str) -> None:
        """Once a forget is kept: the agent's own counts of the arm (its queue's drops) go, as the mirror's
        went, and its route."""
        shard.forget(device)
        self._forget_route(device)
        if self._state_file is not None:  # and the alarms of kinds only a newer agent knows
            self._state_file.forget(device)

    def _settle_forgets(self, shard: Shard, checkpoint: MirrorCheckpoint) -> None:
        """The timed-out forgets of `shard`'s arms, now that its mirror answered for `checkpoint`, asked after
        them (a mirror answers in order): one it made gets the agent's part (`_forgotten`), which otherwise
        never came: the arm's drop count went to a new arm of its name, its route stayed, and the state file
        kept its alarms of unknown kinds. `checkpoint`, confirmed, is already a worker's restart point without
        it, and the state file is written next. An arm still there gets none: its forget was refused, or its
        worker started again from a checkpoint that holds it, or (not told apart) it was forgotten and
        published again before this checkpoint. A worker started again since the forget was asked settles
        none: the arm may be missing from its restart point without having been forgotten. Under the keep
        lock."""
        mine = [(d, r) for d, (index, r) in self._forgets_pending.items() if index == shard.index]
        for device, restarts in mine:
            if restarts != shard.restarts:
                del self._forgets_pending[device]
                log.info("the forget of %s that timed out is not settled: its worker started again", device)
                continue
            if self._mirror is None:
                there = device in checkpoint.devices
            else:  # its checkpoint here is alarms only
                try:
                    there = arm_reply_of(shard.request(ArmRequest(device))()).state is not None
                except Exception:
                    # Under the supervisor, which a fault here would end: the next checkpoint asks again.
                    log.exception("asking after %s, whose forget timed out, failed", device)
                    continue
            del self._forgets_pending[device]
            if there:
                log.info("the forget of %s that timed out was not made: the arm is still there", device)
                continue
            self._forgotten(shard, device)
            self._cached = None
            log.info("the forget of %s that timed out was made; the agent's counts of it are dropped", device)

    def _keep_act(
        self,
        shard: Shard,
        act: str,
        ask: Callable[[bool], tuple[_T, MirrorCheckpoint | None]],
        kept: Callable[[], None] = lambda: None,
    ) -> _T:
        """A person's act (an acknowledgement, a forget) by `shard`'s mirror, kept before it is answered.
        `ask(checkpoint)` makes it, with worker processes asking for the checkpoint begun right after it,
        which `_confirm_act` makes the worker's restart point."""

        def make() -> _T:
            restarts = shard.restarts
            result, checkpoint = ask(self._mirror is None)
            self._confirm_act(shard, act, restarts, checkpoint)
            kept()
            return result

        return self._kept(act, make)

    def _confirm_act(
        self, shard: Shard, act: str, restarts: int, checkpoint: MirrorCheckpoint | None
    ) -> None:
        """The checkpoint a worker began right after a person's act becomes its restart point: the one held
        before would give a worker that dies before the supervisor's next checkpoint the alarm back ACTIVE,
        or the forgotten arm back. WorkerError when it died since `restarts` was read, before asking."""
        if checkpoint is not None and not shard.confirm(checkpoint, restarts=restarts):
            raise WorkerError(_DIED_AFTER.format(index=shard.index, act=act))

    def _kept(self, act: str, make: Callable[[], _T], *, many: bool = False) -> _T:
        """`make()` under the keep lock, then the state file written once before the answer. The lock keeps
        the supervisor from confirming or saving a checkpoint it took before the act over the ones `make`
        confirms. Raises NotSavedError (its `result` what `make` gave, its detail naming the `act`, or
        `many` of them) when the file could not be written."""
        with self._keep_lock:
            result = make()
            self._cached = None
            saved = self._save_alarms_now()
        self._wake.set()
        if not saved and self._state_file is not None:
            # Made, and kept in memory; a restart before the next write that succeeds would undo it.
            made, them = (f"the {act}s are", "them") if many else (f"the {act} is", "it")
            raise NotSavedError(
                f"{made} made, but the state file {self._state_file.path} could not be written "
                f"({self._state_file.last_error}): a restart before it can be would undo {them}. Free space "
                "in (or fix the permissions of) its directory; the agent writes it again every second",
                result,
            )
        return result

    def _save_alarms_now(self) -> bool:
        """Every mirror's alarms into the state file before an acknowledgement or a forget is answered: a
        person's act must survive a kill that comes before the supervisor's next check (which, with workers,
        takes a whole checkpoint: up to a second or two at a large fleet). Alarms only, so quick, and not
        confirmed: an alarms-only checkpoint is no restart's starting point for the messages it would drop.
        False when the file could not be written."""
        if self._state_file is None or self._stopping.is_set():
            return True  # a stop makes its own last write, which says the run stopped

        def alarms_of(shard: Shard) -> tuple[AlarmRecord, ...] | None:
            checkpoint = self._checkpoint(shard, alarms_only=True, confirm=False)
            return None if checkpoint is None else checkpoint.alarms

        records = self._alarm_records(alarms_of)
        self._state_file.save(records, time.monotonic(), time.time())
        return not self._state_file.failing

    def _fleet_totals(self) -> FleetTotals:
        """Running totals and gauges for the CloudWatch metrics (EmfPublisher thread)."""
        return fleet_totals(self.state(), self.config.health.expected_rate_hz)

    # ------------------------------------------------------------------------------------------ console

    def fleet_rows(self) -> list[FleetRow]:
        """The console's Fleet page: every mirror's row per arm (Mirror.fleet_rows), without their states. A
        worker being started again gives its arms' rows from its latest checkpoint, marked restarting."""
        asked = self._ask_fleet(FleetRowsRequest(), fleet_rows_of)
        rows = [row for _, part in asked.answers for row in part]
        if asked.silent:
            alarms = sorted(self._checkpoint_alarms(asked.silent, include_normal=False), key=alarm_order)
            devices = self._checkpoint_devices(asked.silent)
            rows.extend(device_rows(devices, alarms, time.time(), held=self._held_problems()))
        return sorted(rows, key=lambda row: row.device)

    def arm_view(self, device: str) -> ArmView:
        """The console's arm page: one arm, asked of its own mirror only (Mirror.arm), with the messages the
        agent dropped for it, as the whole state would show it. A worker being started again, or one that
        does not answer in time: as its latest checkpoint left the arm (as the whole state shows it then),
        without asking any worker again."""
        shard = self._shards[self.plan.worker_of(device)]
        reply = None
        # Not answering, the worker cannot forget it: the page says so, in the words forget_arm refuses with
        # (a request that failed, in that failure's words: its worker is not being started again, maybe).
        forget: ForgetOffer | None = ForgetOffer(False, f"worker {shard.index} is being started again")
        if shard.answering:
            try:
                reply = arm_reply_of(shard.request(ArmRequest(device))())
            except WorkerError as exc:
                log.debug("arm %s asked of its mirror: %s; shown from its checkpoint", device, exc)
                forget = ForgetOffer(False, str(exc))
        if reply is not None:
            state, alarms, forget = reply.state, list(reply.alarms), reply.forget
        else:
            state = self._checkpoint_devices([shard]).get(device)
            silent = self._checkpoint_alarms([shard], include_normal=False)
            alarms = sorted((a for a in silent if a.device == device), key=alarm_order)
        dropped = shard.dropped().get(device, 0) if state is not None else 0
        if state is not None and dropped:
            state = with_dropped(state, dropped)
        # Held with a card too (a listed fleet admits it; kept alarms list it): its page read "the nominal
        # SO-101's zero and range" for an arm whose messages are all refused.
        # Not one whose units use no calibration: under units = auto an arm publishing degrees decodes (the
        # decoder's rule), and its page said "its twin does not move" of a twin that moved.
        degrees = state is not None and state.units is Units.DEGREES
        refused = "" if degrees else self._held_problems().get(device, "")
        # With no card its refused messages are counted among the arms not tracked: the page says whether
        # any came, and when the last did (its state's health says so for one with a card).
        heard = [a for a in self._unheard_arms() if a.device == device] if refused and state is None else []
        return ArmView(
            self._wall_clock(),
            state,
            alarms,
            self._calibration_store,
            self._started_wall,
            calibration_refused=refused,
            refused=(heard[0].rejected, heard[0].last_s) if heard else None,
            expected_rate_hz=self.config.health.expected_rate_hz,
            per_connection_limit=self._pool_settings.limit is not None,
            forget=forget if state is not None else None,
        )

    def events(self, query: EventQuery) -> list[Event]:
        """The twin's events that match `query` (docs/console.md): the agent's own and every mirror's,
        collected every supervisor round, so at most about SUPERVISE_EVERY_S late."""
        return self._events.query(query)

    def alarms_complete_from(self) -> float | None:
        """From when the alarm events of the agent's store are all there were (console.AlarmHorizon): the
        mirrors' are collected into it, so it tells what it let go of (one a mirror's store let go of
        before a round collected it is only logged: _new_events)."""
        return self._events.alarms_complete_from()

    def _collect_events(self) -> None:
        """On the supervisor thread: broker reconnects, worker exits and restarts, and each mirror's new
        events, into the agent's store, numbered anew in the order they happened (a merge by time of the
        mirrors' lists, each kept in its order), so one mirror's do not all follow another's."""
        with self._events_lock:
            if self._stopping.is_set():
                return  # the stop collects what is left (_collect_last_events), once the shards ended
            self._collect_round()

    def _collect_round(self) -> None:
        """`_collect_events`, its lock held."""
        if self._started_pool:
            self._watch.broker(self._pool.connections())
        collected: list[Sequence[Event]] = []
        line: float | None = None
        for shard in self._shards:
            self._watch_worker(shard)
            if not shard.answering:
                continue
            after = self._events_seen.get(shard.index, 0)
            asked = self._wall_clock()
            try:
                answer = events_of(shard.request(EventsRequest(after))())
            except WorkerError as exc:
                log.debug("events of shard %d not collected: %s", shard.index, exc)
                continue
            finally:
                self._turned()
            if answer.alarms_lost_until is not None:
                self._events.alarms_lost_until(answer.alarms_lost_until)
            fresh = answer.events
            line = asked if line is None else line
            if fresh:
                self._events_seen[shard.index] = fresh[-1].id
                collected.append(_new_events(shard.index, fresh, after))
        # A mirror asked after the first may answer with events newer than what the first one makes next:
        # those wait for the next round (one round at most), so they do not go before older ones.
        held, self._events_held = self._events_held, []
        ready: list[Sequence[Event]] = [held]
        for events in collected:
            cut = len(events) if line is None else bisect_right(events, line, key=attrgetter("time"))
            ready.append(events[:cut])
            self._events_held.extend(events[cut:])
        self._ingest_in_order(ready)

    def _ingest_in_order(self, ready: Sequence[Sequence[Event]]) -> None:
        """Lists of events, each in its mirror's order, into the store merged by the time they happened."""
        if any(ready):
            self._events.ingest(heapq.merge(*ready, key=attrgetter("time")))

    def _collect_last_events(self) -> None:
        """After the shards stopped: the events no round collected (held over, made in the last half second
        or as the mirrors handled what was queued), from their stop reports, so an alarm raised then is
        listed and alerted too. A supervisor round still under way (the stop waits for it a few seconds at
        most) finishes first: they share what was collected."""
        with self._events_lock:
            self._collect_from_reports()

    def _collect_from_reports(self) -> None:
        ready: list[Sequence[Event]] = [self._events_held]
        self._events_held = []
        for index, report in sorted(self.stop_reports.items()):
            if report is None or not report.events:
                continue
            ready.append(_new_events(index, report.events, self._events_seen_of(self._shards[index])))
        self._ingest_in_order(ready)

    def _events_seen_of(self, shard: Shard) -> int:
        """The id of the last event of the shard's process that a round collected: 0 for a process started
        again since the last round (the supervisor's restart can end just as a stop begins, and the round
        that would have seen it is not made), which numbers its events from 1."""
        info = shard.describe(None)
        if info is not None and info.restarts != self._workers_seen.get(shard.index, (True, 0))[1]:
            return 0
        return self._events_seen.get(shard.index, 0)

    def _watch_worker(self, shard: Shard) -> None:
        info = shard.describe(None)
        if info is None:
            return  # an in-process mirror: no process to lose
        answering = shard.answering
        was_answering, restarts = self._workers_seen.get(shard.index, (True, 0))
        self._workers_seen[shard.index] = (answering, info.restarts)
        # The supervisor starts a worker that ran a while again at once, in the round that finds it dead and
        # before that round's watch: one started again since the last watch died unseen, and is told too.
        if was_answering and (not answering or info.restarts > restarts):
            # Not info.pid: a restart made before this watch has put the new process's pid there.
            ended = shard.last_exit() or WorkerExit(info.pid, None)
            self._events.emit(
                EventKind.WORKER,
                EventLevel.ERROR,
                f"worker {shard.index} (pid {ended.pid}) {ended.how()}; it is started again from "
                "its last checkpoint, its arms kept",
                data={"worker": shard.index, "pid": ended.pid, "exit_code": ended.exit_code}
                | ({"hung_s": round(ended.hung_s)} if ended.hung_s else {}),
            )
        if info.restarts > restarts and answering:
            self._events_seen[shard.index] = 0  # a new process numbers its events from 1
            # It had them before its first message (WorkerShard.supervise); again, in case they changed
            # while it was being started.
            self._hand_calibrations_to(shard, self._calibration_request)
            self._events.emit(
                EventKind.WORKER,
                EventLevel.INFO,
                f"worker {shard.index} running again (restart {info.restarts})",
                data={"worker": shard.index, "pid": info.pid, "restarts": info.restarts},
            )

    def _watch_history_writer(self, history: HistoryProcess) -> None:
        """The history writer's deaths and restarts as events, as a worker's: the rows it lost are a hole in
        a session's history that only the log named, not the Events page an operator reads."""
        told_exits, told_restarts = self._history_seen
        self._history_seen = (history.exits, history.restarts)
        if history.exits > told_exits:
            code, lost = history.last_exit
            self._events.emit(
                EventKind.WORKER,
                EventLevel.ERROR,
                f"the history writer exited (code {code}); the {lost} rows it held, not yet written, are "
                "lost; it is started again",
                data={"worker": "history", "exit_code": code, "history_rows_lost": lost},
            )
        if history.restarts > told_restarts and history.alive:
            self._events.emit(
                EventKind.WORKER,
                EventLevel.INFO,
                f"the history writer runs again (restart {history.restarts})",
                data={"worker": "history", "pid": history.pid, "restarts": history.restarts},
            )
        elif history.restarts > told_restarts:
            self._history_seen = (history.exits, told_restarts)  # not running yet: told once it is

    # ------------------------------------------------------------------------------- the agent's own events

    def _restore_events(self) -> Event | None:
        """The journal's events back in the store (before any of this run's), then every new one to the
        journal. Returns the journal's last event; None when there is no journal, or nothing in it."""
        journal = self._journal
        if journal is None:
            return None
        # The newest `capacity` of each of the store's parts, not of all: after a flood of status events those
        # would be statuses only, and the store keeps the alarms before it (EventStore.restore).
        restored = journal.load(self._events.capacity)
        self._events.restore(restored)
        self._events.subscribe(journal.add)
        return restored[-1] if restored else None

    def _emit_started(self, previous_stopped: bool | None, *, unkept: bool) -> None:
        data = {"action": "started", "pid": os.getpid()}
        level, message = EventLevel.INFO, "the agent started"
        if previous_stopped is False:
            level = EventLevel.WARNING
            message += (
                "; its run before did not record a stop (killed, crashed, its host went down, or the journal "
                "could not be written): that run's last events and counters are missing"
            )
            data["previous"] = "did not stop"
        elif previous_stopped:
            message += "; its run before stopped"
            data["previous"] = "stopped"
        # else no journal, or nothing in it: nothing is known of how a run before ended
        if unkept:
            message += (
                "; the events of the runs before it were not kept ([twin] events_file keeps them over a "
                "restart)"
            )
        self._events.emit(EventKind.AGENT, level, message, data=data)

    def _close_events(self, message: str, unwritten: Counter[str], killed: list[int]) -> None:
        """The stop's own event, last, then the journal written out: the next start reads it as the sign
        that this run stopped."""
        lost = _unwritten_text(unwritten)
        if killed:
            lost = ", ".join(filter(None, (lost, f"worker(s) {killed} killed at the budget")))
        self._events.emit(
            EventKind.AGENT,
            EventLevel.ERROR if lost else EventLevel.INFO,
            f"{message}; not written: {lost}" if lost else message,
            data={"action": "stopped", "pid": os.getpid(), "not_written": lost},
        )
        if self._journal is not None:
            self._journal.close()

    # ------------------------------------------------------------------------------------------ alerts

    def _offer_alert(self, event: Event) -> None:
        """An event of the agent's store (on the thread that added it): an alarm transition of a severity the
        config sends goes to the alert publisher's queue."""
        # A burst's summary (events.MismatchBurst) names no alarm: its alarms are sent each as ever.
        if event.kind != EventKind.ALARM or self._alerts is None or not event.data.get("alarm_id"):
            return
        alert = alert_of(event)
        if alert.severity == "critical" or self.config.alerts.warnings:
            self._alerts.offer(alert)

    # ------------------------------------------------------------------------------------- calibrations

    def _hand_calibrations(self, book: CalibrationBook) -> None:
        """A new set of the arms' own calibrations (CalibrationWatcher, on its thread or start's): to every
        mirror, and into the events."""
        request = CalibrationsRequest(
            files=tuple(
                (device, entry.source, entry.calibration.to_dict()) for device, entry in book.entries.items()
            ),
            problems=tuple(book.problems.items()),
            store_option=store_option(self._calibration_store),
            restorable=tuple(sorted(book.restorable)),
        )
        self._calibration_request = request
        for shard in self._shards:
            shard.keep_calibrations(request)
            self._hand_calibrations_to(shard, request)
        self._cached = None
        # The start's poll comes before the agent runs, and before any arm can have been heard.
        first = not self._running
        for change in book.changes:
            if change.action == "refused":
                # The page is where an operator reads it: what the arm does now, and what puts it right.
                # Kept only while the agent runs: its next start holds the arm, which the page did not say.
                now = refused_effect(kept=change.device in book.entries, units=self.config.telemetry.units)
                push = push_hint(change.device, self._calibration_store).command
                why = f"{change.detail}; push a good file: {push}"
                level, message = EventLevel.WARNING, f"calibration of {change.device} refused, {now}: {why}"
            elif change.action == "removed":
                level, message = EventLevel.INFO, f"calibration of {change.device} removed from the store"
            else:
                hint = "" if first else self._unheard_hint(change.device)
                level, message = (
                    EventLevel.WARNING if hint else EventLevel.INFO,
                    f"calibration of {change.device} picked up from {change.detail}{hint and '; ' + hint}",
                )
            self._events.emit(
                EventKind.CALIBRATION, level, message, device=change.device, data={"action": change.action}
            )

    def _unheard_hint(self, device: str) -> str:
        """For a calibration pushed while the agent runs, under an id the agent does not mirror or has not
        heard: nothing else tells a mistyped id from a new arm. Logged too, where the one who pushed looks."""
        t = self.config.telemetry
        if not t.all_devices and device not in t.devices:
            hint = (
                f"{device} is not in this agent's telemetry.devices ({', '.join(t.devices)}), so this "
                f"calibration is never used: check the id{_case_hint(device, t.devices)}, or add the arm to "
                "telemetry.devices"
            )
        else:
            # Asked of the arm's own mirror (or its checkpoint), not every worker's rows of the whole fleet.
            if self.arm_view(device).state is not None:
                return ""
            # An arm whose messages were all refused (one held by its bad file, above all) was heard: it has
            # no card, but "no message yet" would send its owner to check an id that is right.
            if any(arm.device == device for arm in self._unheard_arms()):
                return ""
            # A miss only: then the fleet's ids, for one that differs by case alone (ARM-03 for arm-03).
            heard = [row.device for row in self.fleet_rows()]
            hint = (
                f"no message from {device} yet: if this arm is already sending, check the id against the "
                f"Fleet page{_case_hint(device, heard)}"
            )
        log.warning("calibration of %s: %s", device, hint, extra={"event": "calibration", "device": device})
        return hint

    def _hand_calibrations_to(self, shard: Shard, request: CalibrationsRequest) -> None:
        if not shard.answering:
            return  # a worker being started again gets them once it answers (_watch_worker)
        try:
            applied_of(shard.request(request)())
        except WorkerError as exc:
            log.warning("calibrations not handed to shard %d: %s", shard.index, exc)


def _case_hint(device: str, ids: Iterable[str]) -> str:
    """ " (ids are case-sensitive: did you mean arm-03?)" when `ids` has one that differs by case alone."""
    same = sorted(i for i in ids if i != device and i.casefold() == device.casefold())
    return f" (ids are case-sensitive: did you mean {same[0]}?)" if same else ""


def _event_journal(config: AgentConfig) -> EventJournal | None:
    """The agent's event journal (None without `[twin] events_file`), its files sized by the store's
    capacity: each pair holds all the store keeps of its kinds (service.event_journal)."""
    tw = config.twin
    return EventJournal(tw.events_file, capacity=tw.events_capacity) if tw.events_file else None


def _previous_stopped(journal_last: Event | None, previous: PreviousRun | None) -> bool | None:
    """Whether the run before this one stopped, for this start's event; None when nothing tells. The state
    file says so when it has `stopped`: every run with one writes it, and the journal only runs with an
    events file, so the journal's last `stopped` may be a run older than the last (a walk saw "its run
    before stopped" under a log line saying that run was killed). Without it, the journal's last event,
    unless the state file was written after it: a run that kept no journal came between."""
    if previous is not None and previous.stopped is not None:
        return previous.stopped
    if journal_last is None:
        return None
    if (
        previous is not None
        and previous.written_at is not None
        and previous.written_at > journal_last.time + 1.0
    ):
        return None
    return journal_last.kind == EventKind.AGENT and journal_last.data.get("action") == "stopped"


def _unwritten_text(unwritten: Counter[str]) -> str:
    """What a stop could not write, as its log line and its event both say it: "12 history_rows, ..."."""
    return ", ".join(f"{n} {what}" for what, n in sorted(unwritten.items()))


def alert_publisher(config: AgentConfig) -> AlertPublisher:
    """The publisher of servo alarm transitions to the config's SNS topic."""
    a = config.alerts
    url = f"http://{config.http.host}:{config.http.port}"
    # Read on a phone or a laptop, not on the twin host: the console reaches the laptop through
    # `twin instance console`, and an agent run on the laptop serves it at `url` itself.
    how = (
        f"Open the agent's console, {url}/arm/<arm>, and press Acknowledge: for the twin host, run "
        "`twin instance console` on your machine (it forwards that port), or use the host's DCV desktop "
        f"(`twin instance url`). Or, where the agent runs (on the host, a Session Manager shell): curl -X "
        f"POST {url}/alarms/<alarm id>/ack. Until acknowledged, an alarm whose condition went away stays "
        "LATCHED (docs/servo-health.md)."
    )
    return AlertPublisher(
        sns_publisher(a.topic_arn.strip(), a.region or config.broker.region),
        agent_name=config.cloudwatch.agent_name,
        how_to_acknowledge=how,
        flush_s=a.flush_s,
        max_per_hour=a.max_per_hour,
        burst=a.burst,
    )


def alert_of(event: Event) -> Alert:
    """An alarm event of the store (service.events, FleetWatch.alarm) as the notification names it."""
    d = event.data
    return Alert(
        alarm_id=d.get("alarm_id", ""),
        device=event.device,
        joint=d.get("joint", ""),
        kind=d.get("kind", ""),
        severity=d.get("severity", ""),
        action=d.get("action", ""),
        state=d.get("state", ""),
        value=_number(d.get("value", "")),
        threshold=_number(d.get("threshold", "")),
        unit=d.get("unit", ""),
        message=d.get("text", "") or event.message,
        at=event.time,
    )


def _number(text: str) -> float | None:
    try:
        return float(text) if text else None
    except ValueError:
        return None


@dataclasses.dataclass(frozen=True, slots=True)
class _FleetAnswers(Generic[_T]):
    """One request's answers by shard, and the shards that gave none (AgentService._ask_fleet)."""

    answers: list[tuple[Shard, _T]]
    silent: tuple[Shard, ...]


# An acknowledgement or a forget its worker answered just before it died: the restart takes up from the
# checkpoint before, which does not hold it (the HTTP API answers 503: make it again once the worker runs).
_DIED_AFTER = "worker {index} died as it answered, and is being started again without this {act}"


def forget_timed_out(device: str, shard: Shard) -> str:
    """The one answer to a forget whose answer did not come in time, whichever wait ran out (the agent's for a
    worker process, the worker's or an in-process mirror's for its mirror thread): the request still waits
    for the mirror thread, so the arm may yet be forgotten, and neither "was not forgotten" nor "try again
    once it runs" (of a worker that runs) was true."""
    if isinstance(shard, WorkerShard):
        who, timeout_s = f"worker {shard.index}, which mirrors {device},", ASK_TIMEOUT_S
    else:
        from twin.service.mirror import JOB_TIMEOUT_S  # noqa: PLC0415 - loaded already: the mirror runs here

        who, timeout_s = "the agent's mirror", JOB_TIMEOUT_S
    return (
        f"{who} did not answer the forget within {timeout_s:.0f} s: it is busy or stuck, and may still "
        f"forget the arm when it gets to it. Look at {device} again in a minute (its Arm page, or GET "
        f"/api/arm/{device}) and forget it again if it is still there"
    )


def alarm_order(info: AlarmInfo) -> tuple[int, int, str]:
    """Worst first, as ServoAlarms.views orders them (core.alarms.worst_first)."""
    return worst_first(info.severity, info.state, info.alarm_id)


def _new_events(index: int, events: Sequence[Event], seen: int) -> Sequence[Event]:
    """A mirror's `events` (its numbering, oldest first) after the `seen` one, saying how many between were
    never collected: its store keeps `[twin] events_capacity`, and a stop report the newest EVENTS_PER_ASK."""
    fresh = [e for e in events if e.id > seen]
    # Every id up to the newest collected that is not among them: the store lets go of its bulk events
    # before its alarms (events.BULK_KINDS), so a gap can lie between two collected events, not only before.
    missed = fresh[-1].id - seen - len(fresh) if fresh else 0
    if missed > 0:
        log.warning("%d events of mirror %d were not collected", missed, index)
    return fresh


def fleet_totals(state: AgentState, expected_rate_hz: float) -> FleetTotals:
    """The CloudWatch metrics' running totals and gauges, from one state document (docs/servo-health.md)."""
    statuses = [d.health.status for d in state.devices.values()]
    live = [d for d in state.devices.values() if d.health.status is not DeviceStatus.OFFLINE]
    # Per arm, the share of the expected rate that did not arrive, averaged over arms that are not OFFLINE
    # (an OFFLINE arm is counted as such, not as 100 % loss), and whose rate is known: read from a restarting
    # worker's checkpoint it is not, and its arms counted as 100 % loss at 0 Hz.
    rates = [d.health.rate_hz for d in live if d.health.rate_hz is not None]
    # None, left out of the metrics, when no arm's loss is measured: every arm OFFLINE (or none at all), where
    # the dashboard's 0 % beside a fleet all offline read as an all-clear, or arms deliver but no rate is
    # known (a one-worker fleet whose worker restarts), where 0 was a false all-clear too.
    loss = 100.0 * sum(max(0.0, 1.0 - r / expected_rate_hz) for r in rates) / len(rates) if rates else None
    p99s = [
        d.health.internal_latency_s.p99 for d in state.devices.values() if d.health.internal_latency_s.p99
    ]
    # Over each arm's recent window (core.loss): one arm's loss, which the average above dilutes. None with
    # no arm live, as above.
    worst = max((d.loss.recent_loss_ratio for d in live), default=None)
    history = state.agent.history
    return FleetTotals(
        decoded=sum(d.health.counters.decoded for d in state.devices.values()),
        rejected=sum(d.health.counters.rejected_total for d in state.devices.values())
        + sum(state.untracked_rejected.values()),
        devices_online=statuses.count(DeviceStatus.ONLINE),
        devices_stale=statuses.count(DeviceStatus.STALE),
        devices_offline=statuses.count(DeviceStatus.OFFLINE),
        loss_percent=loss,
        worst_arm_loss_percent=100.0 * worst if worst is not None else None,
        internal_latency_p99_ms=max(p99s) * 1000.0 if p99s else None,
        active_alarms=state.agent.alarms.present,
        messages_dropped=state.agent.mailbox.overwritten_total,
        sink_drops=sum(s.dropped for s in state.agent.sinks),
        # The history writer is a worker process too.
        worker_restarts=sum(w.restarts for w in state.agent.workers)
        + (history.writer_restarts if history is not None else 0),
        subscriptions_refused=state.agent.broker.subscriptions_refused,
        broker_disconnected=sum(c.state == "connecting" for c in state.agent.broker.connections),
        device_limit_refusals=state.untracked_rejected.get(TOO_MANY_DEVICES, 0),
        # The alarm e-mails' publisher is an output of the agent's own (/state agent.sinks, "alerts").
        alert_publish_failures=sum(s.errors for s in state.agent.sinks if s.name == "alerts"),
        history_rows_dropped=history.rows_not_written if history is not None else None,
        history_commit_failures=history.commit_failures if history is not None else None,
        history_lag_s=history.lag_s if history is not None else None,
        history_commits_failing=int(history is not None and history.storage_ok is False),
    )


def broker_state(url: str, settings: PoolSettings, pool: ConnectionPool, started: bool) -> BrokerState:
    """The broker side of /state: the pool's connections, summed and one by one."""
    limit = settings.limit
    if not started:
        return BrokerState(url=url, per_connection_limit=limit)
    infos = pool.connections()
    stats = [c.stats for c in pool.subscribers()]
    latest = max((st for st in stats if st.last_error), key=lambda st: st.last_error_at or 0.0, default=None)
    return BrokerState(
        url=url,
        client_id=infos[0].client_id if infos else None,
        connected=pool.connected,
        connection_successes=sum(st.connection_successes for st in stats),
        connection_failures=sum(st.connection_failures for st in stats),
        disconnections=sum(st.disconnects for st in stats),
        subscribes=sum(st.subscribes_acked for st in stats),
        messages=pool.messages,
        last_error=latest.last_error if latest is not None else "",
        last_error_at=latest.last_error_at if latest is not None else None,
        per_connection_limit=limit,
        rate_hz=pool.rate_hz,
        subscriptions_refused=sum(len(c.refused) for c in infos),
        quota_notice=pool.quota_notice,
        connections=tuple(
            ConnectionState(
                index=c.index,
                client_id=c.client_id,
                state=c.state,
                filters=len(c.filters),
                rate_hz=c.rate_hz,
                messages=c.messages,
                connection_successes=c.connection_successes,
                disconnections=c.disconnections,
                last_error=c.last_error,
                last_error_at=c.last_error_at,
                connected_at=c.connected_at,
                refused=c.refused,
            )
            for c in infos
        ),
    )


def history_settings(config: AgentConfig) -> dict[str, Any] | None:
    """HistorySettings' fields from the config's [history] (None when it is off), and the writer process's
    nice value; the writer process makes the settings (and checks them: a bad one stops the agent as a
    configuration error)."""
    h = config.history
    if not h.enabled:
        return None
    return {
        "uri": h.uri.strip(),
        "commit_every_s": h.commit_every_s,
        "commit_every_rows": h.commit_every_rows,
        "max_buffer_rows": h.max_buffer_rows,
        "queue_max": h.queue_max,
        "maintain_every_s": h.maintain_every_s,
        "vacuum_retention_hours": h.vacuum_retention_hours,
        "keep_days": h.keep_days,
        "storage_options": {"AWS_REGION": h.region} if h.region else {},
        "writer_nice": h.writer_nice,  # the writer process's own, not HistorySettings'
    }
