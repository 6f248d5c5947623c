"""A sharded agent: one process receives, N worker processes mirror, each a share of the fleet.

One Python process cannot mirror a large fleet: every message is decoded, applied, counted and checked by the
alarm engine, and the interpreter runs that on one core at a time (docs/performance.md). So `twin run
--workers N` splits the work:

    receiving process: connection pool (the IoT Core quota's connections) --CRT threads: on_message-->
      admit the device (telemetry.max_devices), pick its worker (`WorkerPlan.worker_of`)
      --> one bounded queue per worker --sender thread: batches over a pipe-->
    worker process k: an embedded AgentService (decode, twin, health, loss, alarms, sinks) for its devices
    receiving process: HTTP API, CloudWatch metrics; /state asks every worker and merges (`merge_reports`)

Each device belongs to exactly one worker, for as long as the agent runs: a listed fleet is dealt out in
list order (balanced, deterministic), the whole fleet (`*`) by a stable hash of the device id (CRC-32, the
same in every process and on every run). A device's messages travel one queue and one pipe in order, so the
order they arrived in is kept. The receiving process does no per-message work beyond the routing: the
connection pool's no-op ceiling (docs/performance.md) is what it costs.

A worker that dies (a crash in a native library, say) is started again; its devices lose their twins' state
and start over from their next message, and the messages that arrived while it was down are counted as
dropped (`overwritten`) against their devices. Workers ignore SIGINT and SIGTERM: the receiving process
stops them in order (the rest of the queue, then an end marker), so each one flushes its sinks (USD
recording, history) before it exits. A worker whose parent vanished sees its pipe close and exits too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import math
import multiprocessing
import os
import signal
import threading
import time
import zlib
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from twin.core.alarms import AlarmNotFound, NothingToAcknowledge
from twin.core.health import DeviceStatus
from twin.core.latency import LatencyHistogram
from twin.core.loss import fleet_loss
from twin.core.topics import device_from_topic
from twin.output.emf import EmfFileWriter, EmfPublisher, FleetTotals
from twin.service.config import AgentConfig, ConfigError
from twin.service.http_api import AgentHttpServer
from twin.service.logs import RateLimitedLog
from twin.service.state import (
    AgentInfo,
    AgentState,
    AlarmInfo,
    AlarmsSummary,
    FleetLatency,
    HealthReport,
    HistoryState,
    MailboxState,
    RecordingState,
    SinkStats,
    WorkerInfo,
    WorkerState,
)
from twin.service.summary import TOO_MANY_DEVICES, alarm_order, broker_state, fleet_totals, pool_settings
from twin.transport.mailbox import UNTRACKED_KEY, InboundQueue
from twin.transport.pipe import send_batch, send_end
from twin.transport.pool import ConnectionPool

log = logging.getLogger(__name__)

Clock = Callable[[], float]

# Messages a second one worker is planned for when `[twin] workers = 0` chooses the count for a listed fleet:
# about a third of what one worker mirrors on this project's 2-core development machine, so a fleet of up to
# 100 arms at 10 Hz stays in one process (docs/agent.md, "Workers").
WORKER_PLAN_RATE = 1000.0
# Per worker, the receiving process queues at most this many messages for its pipe (about 40 MB of payloads
# across the fleet's queues at most); beyond it the oldest are dropped and counted, as in the worker's own.
MAX_QUEUED_PER_WORKER = 25_000
# One pipe write carries at most this many messages: a backlog goes over in pieces the worker can start on.
MAX_BATCH = 1000
# Above this many messages a second for one worker, its sender pauses SEND_PAUSE_S after each hand-over
# (unless it had a full batch), so messages arriving meanwhile go over together. Without the pause every
# message woke the sender (a Condition notify costs more than routing the message) and crossed the pipe
# alone: at 10,000 msg/s a worker the receiving process spent 26 us a message instead of 18. Below the rate
# the wake-ups cost little and the pause would only add latency.
PAUSE_ABOVE_RATE = 2000.0
SEND_PAUSE_S = 0.002
# How long a merged state is reused: /stream clients, /metrics and the CloudWatch thread read it often, and
# each reading asks every worker.
STATE_REUSE_S = 0.05
# How long a worker may take to answer one request (a state of thousands of arms takes tens of ms).
ASK_TIMEOUT_S = 10.0
# A worker must be up within this (Python, MuJoCo and the sinks it opens, e.g. a Delta table on S3).
START_TIMEOUT_S = 120.0
# A worker that dies within this long of starting is restarted after a growing pause (1, 2, 4 ... s, at most
# MAX_RESTART_PAUSE_S) rather than at once, so a worker that cannot run does not spin.
QUICK_DEATH_S = 30.0
MAX_RESTART_PAUSE_S = 60.0


class WorkerError(RuntimeError):
    """A worker process could not start, or did not answer."""


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, which containers and taskset narrow)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def worker_count(config: AgentConfig, cores: int | None = None) -> int:
    """How many worker processes `config` asks for: `[twin] workers`, or when it is 0 one per usable core,
    but one per WORKER_PLAN_RATE of a listed fleet's expected messages, and one when the Rerun stream is on
    (one stream, one process)."""
    requested = config.twin.workers
    if requested:
        return requested
    if config.rerun.enabled:
        return 1
    cores = usable_cores() if cores is None else cores
    if config.telemetry.all_devices:
        return cores
    expected = len(config.telemetry.devices) * config.health.expected_rate_hz
    return max(1, min(cores, len(config.telemetry.devices), math.ceil(expected / WORKER_PLAN_RATE)))


class WorkerPlan:
    """Which worker mirrors which device: listed devices dealt out in list order, any other by CRC-32."""

    def __init__(self, count: int, listed: Sequence[str] = ()) -> None:
        if count < 1:
            raise ValueError(f"a sharded agent needs at least one worker, got {count}")
        self.count = count
        self._listed = {device: i % count for i, device in enumerate(listed)}

    def worker_of(self, device: str) -> int:
        listed = self._listed.get(device)
        if listed is not None:
            return listed
        return zlib.crc32(device.encode("utf-8", "surrogatepass")) % self.count

    def devices_of(self, index: int) -> tuple[str, ...]:
        """The listed devices worker `index` mirrors."""
        return tuple(device for device, worker in self._listed.items() if worker == index)


def worker_config(config: AgentConfig, plan: WorkerPlan, index: int) -> AgentConfig:
    """What worker `index` runs with: its share of a listed fleet (so each configured device is reported by
    one worker), and no CloudWatch file (the receiving process publishes the fleet's metrics)."""
    telemetry = config.telemetry
    if not telemetry.all_devices:
        telemetry = dataclasses.replace(telemetry, devices=plan.devices_of(index))
    return dataclasses.replace(
        config,
        telemetry=telemetry,
        twin=dataclasses.replace(config.twin, workers=1),
        cloudwatch=dataclasses.replace(config.cloudwatch, emf_file=""),
    )


# ------------------------------------------------------------------------------------------- worker process


@dataclass(frozen=True)
class WorkerReport:
    """A worker's answer to "state": its typed state and its latency histograms (percentiles do not add
    up; histograms do)."""

    state: AgentState
    internal: LatencyHistogram
    end_to_end: LatencyHistogram


class _WorkerLogFilter(logging.Filter):
    def __init__(self, index: int) -> None:
        super().__init__()
        self.index = index

    def filter(self, record: logging.LogRecord) -> bool:
        record.worker = self.index
        return True


def worker_main(index: int, config: AgentConfig, data: Connection, control: Connection) -> None:
    """A worker process: an embedded AgentService fed from `data`, answering `control` (module doc)."""
    # The receiving process decides when workers stop (the rest of the queue first, then the sinks flush);
    # a Ctrl-C in a terminal or systemd's SIGTERM reaches the whole process group.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from twin.service.agent import AgentService  # noqa: PLC0415 - MuJoCo loads in the worker, not its parent
    from twin.service.logs import setup_logging  # noqa: PLC0415
    from twin.service.outputs import close_sinks, configured_sinks  # noqa: PLC0415

    setup_logging(config.log.level)
    for handler in logging.getLogger().handlers:
        handler.addFilter(_WorkerLogFilter(index))
    sinks: list[Any] = []
    try:
        sinks = configured_sinks(config)
        service = AgentService(config, sinks=sinks, inbox=data)
        service.start()
    except ConfigError as exc:
        # A setting the worker cannot work with (the ros2 extra missing, say): the receiving process exits
        # as for any configuration error, with this message.
        close_sinks(sinks)
        control.send(("config", str(exc)))
        return
    except Exception as exc:
        close_sinks(sinks)
        log.exception("worker %d could not start", index)
        control.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    control.send(("ready", os.getpid()))
    threading.Thread(target=_serve_control, args=(service, control), name="twin-control", daemon=True).start()
    # The worker thread reads the pipe until the end marker (or the receiving process is gone), then stops.
    while service.running:
        time.sleep(0.2)
    service.stop(timeout=30.0)


def _serve_control(service: Any, control: Connection) -> None:
    """Answer the receiving process's requests: (id, op, argument) -> (id, ok, result)."""
    while True:
        try:
            request_id, op, arg = control.recv()
        except (EOFError, OSError):
            return
        try:
            if op == "state":
                result: Any = WorkerReport(service.state(), *service.histograms())
            elif op == "alarms":
                result = service.alarms(include_normal=bool(arg))
            elif op == "ack":
                result = service.acknowledge_alarm(arg)
            else:
                raise ValueError(f"unknown request {op!r}")
            reply = (request_id, True, result)
        except (AlarmNotFound, NothingToAcknowledge) as exc:
            reply = (request_id, False, (type(exc).__name__, str(exc)))
        except Exception as exc:
            log.exception("worker request %s failed", op)
            reply = (request_id, False, ("error", f"{type(exc).__name__}: {exc}"))
        try:
            control.send(reply)
        except (OSError, ValueError):
            return


# ----------------------------------------------------------------------------------------- receiving process


class _Worker:
    """The receiving process's handle on one worker: its process, pipes, queue and sender thread."""

    def __init__(self, index: int) -> None:
        self.index = index
        self.queue: InboundQueue[tuple[str, bytes, float, float]] = InboundQueue(MAX_QUEUED_PER_WORKER)
        self.process: Any = None
        self.data: Connection | None = None
        self.control: Connection | None = None
        self.control_lock = threading.Lock()
        self.ready = False
        self.pid = 0
        self.started_at = 0.0
        self.restarts = 0
        self.restart_at: float | None = None
        self.sender: threading.Thread | None = None
        # Messages that could not be handed to the worker (it was down), by device.
        self.dropped: Counter[str] = Counter()

    @property
    def alive(self) -> bool:
        return self.ready and self.process is not None and self.process.is_alive()


class ShardedAgent:
    """The receiving process of `twin run --workers N` (N >= 2): the same surface as AgentService for the CLI
    and the HTTP API (`start`, `stop`, `running`, `state`, `healthz`, `alarms`, `acknowledge_alarm`)."""

    def __init__(
        self,
        config: AgentConfig,
        workers: int,
        *,
        clock: Clock = time.monotonic,
        wall_clock: Clock = time.time,
    ) -> None:
        if workers < 2:
            raise ValueError(f"a sharded agent has at least 2 workers (1 is AgentService), got {workers}")
        if config.rerun.enabled:
            raise ConfigError(
                "[rerun] streams one recording from one process: run with --workers 1 ([twin] workers = 1) "
                "to stream to Rerun, or turn [rerun] off"
            )
        self.config = config
        self._clock = clock
        self._wall_clock = wall_clock
        t = config.telemetry
        self.plan = WorkerPlan(workers, () if t.all_devices else t.devices)
        self._workers = [_Worker(i) for i in range(workers)]
        self._pool_settings = pool_settings(config)
        self._pool = ConnectionPool(config.broker, self._pool_settings, self._on_message, clock=clock)
        self.topic_filters = self._pool.topic_filters
        self._prefix = t.topic_prefix
        # Devices admitted so far (telemetry.max_devices bounds them): device -> its worker.
        self._routes: dict[str, int] = {}
        self._admit_lock = threading.Lock()
        self._refused: Counter[str] = Counter()
        self._refuse_log = RateLimitedLog(log, interval_s=10.0, clock=clock)
        self._ctx = multiprocessing.get_context("spawn")
        self._http: AgentHttpServer | None = None
        self._emf: EmfPublisher | None = None
        self._supervisor: threading.Thread | None = None
        self._stopping = threading.Event()
        self._running = False
        self._started_pool = False
        self._started_mono: float | None = None
        self._started_wall: float | None = None
        self._request_ids = itertools.count(1)
        self._state_lock = threading.Lock()
        self._cached: tuple[float, AgentState] | None = None

    # -------------------------------------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Start the workers (and wait until each is up), the senders, the HTTP server, the subscription.
        Raises WorkerError when a worker cannot start (its reason in the message), OSError when the HTTP
        address is taken."""
        if self._running:
            return
        self._started_mono = self._clock()
        self._started_wall = self._wall_clock()
        try:
            for worker in self._workers:
                self._spawn(worker)
            for worker in self._workers:
                self._await_ready(worker)
            self._http = AgentHttpServer(
                self,
                self.config.http.host,
                self.config.http.port,
                stream_rate_hz=self.config.http.stream_rate_hz,
            )
        except BaseException:
            self._stop_workers(timeout=10.0)
            raise
        for worker in self._workers:
            worker.sender = threading.Thread(
                target=self._send_loop, args=(worker,), name=f"twin-send-{worker.index}", daemon=True
            )
            worker.sender.start()
        self._running = True
        self._supervisor = threading.Thread(target=self._supervise, name="twin-supervisor", daemon=True)
        self._supervisor.start()
        self._http.start()
        self._pool.start()
        self._started_pool = True
        cw = self.config.cloudwatch
        if cw.emf_file:
            self._emf = EmfPublisher(
                EmfFileWriter(cw.emf_file), cw.agent_name, self._fleet_totals, cw.interval_s
            )
            self._emf.start()
        log.info(
            "agent started",
            extra={
                "broker": self.config.broker.url,
                "topics": self.topic_filters,
                "http": self._http.url,
                "workers": len(self._workers),
                "worker_pids": [w.pid for w in self._workers],
            },
        )

    def stop(self, timeout: float = 30.0) -> None:
        """Unsubscribe, hand each worker the rest of its queue and an end marker, wait for them to flush and
        exit, stop HTTP. Idempotent."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        log.info("agent stopping")
        if self._started_pool:
            try:
                self._pool.stop(min(timeout, 5.0))
            except Exception:
                log.exception("stopping the connection pool failed")
        self._stop_workers(timeout)
        if self._emf is not None:
            self._emf.stop(timeout)
        if self._http is not None:
            self._http.stop()
        self._running = False
        log.info("agent stopped")

    def _stop_workers(self, timeout: float) -> None:
        for worker in self._workers:
            worker.queue.close()
        deadline = time.monotonic() + timeout
        for worker in self._workers:
            if worker.sender is not None:
                worker.sender.join(max(0.1, deadline - time.monotonic()))
            elif worker.data is not None:
                with contextlib.suppress(OSError, ValueError):
                    send_end(worker.data)
        for worker in self._workers:
            process = worker.process
            if process is None:
                continue
            process.join(max(0.1, deadline - time.monotonic()))
            if process.is_alive():
                log.error("worker %d did not stop within %.0f s; killing it", worker.index, timeout)
                process.kill()
                process.join(5.0)
            worker.ready = False
            for conn in (worker.data, worker.control):
                if conn is not None:
                    conn.close()

    def __enter__(self) -> ShardedAgent:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._running and not self._stopping.is_set()

    @property
    def http_url(self) -> str:
        if self._http is None:
            raise RuntimeError("the HTTP server starts with start()")
        return self._http.url

    @property
    def workers(self) -> int:
        return len(self._workers)

    def worker_pids(self) -> list[int]:
        return [w.pid for w in self._workers]

    def wait_subscribed(self, timeout: float) -> bool:
        return self._started_pool and self._pool.wait_subscribed(timeout)

    # ------------------------------------------------------------------------------------- worker processes

    def _spawn(self, worker: _Worker) -> None:
        data_read, data_write = self._ctx.Pipe(duplex=False)
        control, control_child = self._ctx.Pipe()
        config = worker_config(self.config, self.plan, worker.index)
        process = self._ctx.Process(
            target=worker_main,
            args=(worker.index, config, data_read, control_child),
            name=f"twin-worker-{worker.index}",
        )
        process.start()
        # The worker holds its own ends now; closing ours lets each side see the other go (EOF).
        data_read.close()
        control_child.close()
        worker.process, worker.data, worker.control = process, data_write, control
        worker.started_at = time.monotonic()

    def _await_ready(self, worker: _Worker) -> None:
        assert worker.control is not None and worker.process is not None
        if not worker.control.poll(START_TIMEOUT_S):
            raise WorkerError(f"worker {worker.index} did not start within {START_TIMEOUT_S:.0f} s")
        try:
            kind, value = worker.control.recv()
        except (EOFError, OSError):
            worker.process.join(5.0)
            raise WorkerError(
                f"worker {worker.index} exited while starting (exit code {worker.process.exitcode}); "
                "its log lines above say why"
            ) from None
        if kind == "config":
            raise ConfigError(str(value))
        if kind != "ready":
            raise WorkerError(f"worker {worker.index} could not start: {value}")
        worker.pid = int(value)
        worker.ready = True

    def _supervise(self) -> None:
        """Start dead workers again (module doc); their devices' twins start over."""
        while not self._stopping.wait(0.5):
            for worker in self._workers:
                if worker.process is None or worker.process.is_alive() or self._stopping.is_set():
                    continue
                now = time.monotonic()
                if worker.restart_at is None:
                    worker.ready = False
                    quick = now - worker.started_at < QUICK_DEATH_S
                    pause = min(MAX_RESTART_PAUSE_S, 2.0 ** min(worker.restarts, 6)) if quick else 0.0
                    worker.restart_at = now + pause
                    log.error(
                        "worker %d exited (code %s); starting it again%s",
                        worker.index,
                        worker.process.exitcode,
                        f" in {pause:.0f} s" if pause else "",
                        extra={"worker": worker.index, "exit_code": worker.process.exitcode},
                    )
                if now < worker.restart_at:
                    continue
                worker.restart_at = None
                worker.restarts += 1
                self._restart(worker)

    def _restart(self, worker: _Worker) -> None:
        with worker.control_lock:
            for conn in (worker.data, worker.control):
                if conn is not None:
                    conn.close()
            try:
                self._spawn(worker)
                self._await_ready(worker)
            except WorkerError as exc:
                log.error("worker %d could not be started again: %s", worker.index, exc)
                return
        log.info("worker %d running again", worker.index, extra={"worker": worker.index, "pid": worker.pid})

    # ------------------------------------------------------------------------------------- receive and send

    def _on_message(self, topic: str, payload: bytes, recv_mono: float) -> None:
        """On a CRT thread: admit the device, queue the message for its worker. Never blocks for long."""
        device = device_from_topic(topic, self._prefix)
        if device is None:
            self._workers[0].queue.put(UNTRACKED_KEY, (topic, payload, recv_mono, self._wall_clock()))
            return
        index = self._routes.get(device)
        if index is None:
            index = self._admit(device)
            if index is None:
                return
        self._workers[index].queue.put(device, (topic, payload, recv_mono, self._wall_clock()))

    def _admit(self, device: str) -> int | None:
        with self._admit_lock:
            index = self._routes.get(device)
            if index is not None:
                return index
            limit = self.config.telemetry.max_devices
            if len(self._routes) >= limit:
                self._refused[TOO_MANY_DEVICES] += 1
                self._refuse_log.log(
                    TOO_MANY_DEVICES,
                    logging.WARNING,
                    "device ignored: telemetry.max_devices devices already seen; raise it if the fleet is "
                    "really this large",
                    device=device,
                    max_devices=limit,
                )
                return None
            index = self._routes[device] = self.plan.worker_of(device)
            return index

    def _send_loop(self, worker: _Worker) -> None:
        """Hand the worker its queue in batches; what cannot be handed over (it is down) is counted."""
        queue = worker.queue
        window_start, window_count, pause = time.monotonic(), 0, False
        while True:
            items = queue.take_all(0.2)
            if not items:
                if queue.closed:
                    break
                continue
            if pause and len(items) < MAX_BATCH:
                time.sleep(SEND_PAUSE_S)
                items += queue.take_all(0)
            window_count += len(items)
            now = time.monotonic()
            if now - window_start >= 1.0:
                pause = window_count / (now - window_start) > PAUSE_ABOVE_RATE
                window_start, window_count = now, 0
            for start in range(0, len(items), MAX_BATCH):
                chunk = items[start : start + MAX_BATCH]
                conn = worker.data
                if not worker.ready or conn is None:
                    worker.dropped.update(key for key, _ in chunk)
                    continue
                try:
                    send_batch(conn, chunk)
                except (OSError, ValueError):
                    worker.ready = False
                    worker.dropped.update(key for key, _ in chunk)
        if worker.data is not None and worker.ready:
            with contextlib.suppress(OSError, ValueError):
                send_end(worker.data)

    # ------------------------------------------------------------------------------------------- requests

    def _ask_all(self, op: str, arg: Any = None) -> list[tuple[_Worker, Any]]:
        """Send the request to every running worker, then collect the answers (they work in parallel)."""
        asked = []
        for worker in self._workers:
            if not worker.alive:
                continue
            worker.control_lock.acquire()
            request_id = next(self._request_ids)
            try:
                assert worker.control is not None
                worker.control.send((request_id, op, arg))
            except (OSError, ValueError):
                worker.control_lock.release()
                continue
            asked.append((worker, request_id))
        answers = []
        for worker, request_id in asked:
            try:
                answers.append((worker, self._answer(worker, request_id)))
            except WorkerError as exc:
                log.warning("%s", exc)
            finally:
                worker.control_lock.release()
        return answers

    def _ask(self, worker: _Worker, op: str, arg: Any = None) -> Any:
        if not worker.alive:
            raise WorkerError(f"worker {worker.index} is not running (it is being started again)")
        with worker.control_lock:
            request_id = next(self._request_ids)
            try:
                assert worker.control is not None
                worker.control.send((request_id, op, arg))
            except (OSError, ValueError) as exc:
                raise WorkerError(f"worker {worker.index} is not reachable: {exc}") from exc
            return self._answer(worker, request_id)

    @staticmethod
    def _answer(worker: _Worker, request_id: int) -> Any:
        """The answer to `request_id` (under the worker's control lock); late answers to requests that timed
        out are skipped."""
        conn = worker.control
        assert conn is not None
        deadline = time.monotonic() + ASK_TIMEOUT_S
        while True:
            remaining = deadline - time.monotonic()
            try:
                if remaining <= 0 or not conn.poll(remaining):
                    raise WorkerError(f"worker {worker.index} did not answer within {ASK_TIMEOUT_S:.0f} s")
                answer_id, ok, result = conn.recv()
            except (EOFError, OSError) as exc:
                raise WorkerError(f"worker {worker.index} went away: {exc}") from exc
            if answer_id != request_id:
                continue
            if ok:
                return result
            kind, message = result
            if kind == "AlarmNotFound":
                raise AlarmNotFound(message)
            if kind == "NothingToAcknowledge":
                raise NothingToAcknowledge(message)
            raise WorkerError(f"worker {worker.index}: {message}")

    # --------------------------------------------------------------------------------------------- readers

    def state(self) -> AgentState:
        """The fleet's state: every worker's, merged (docs/agent.md; `agent.workers` has each worker)."""
        with self._state_lock:
            now = self._clock()
            if self._cached is not None and now - self._cached[0] < STATE_REUSE_S:
                return self._cached[1]
            answers = self._ask_all("state")
            state = merge_reports(
                self._info(now),
                [report for _, report in answers],
                self._worker_infos({worker.index: report for worker, report in answers}),
                refused=dict(self._refused),
                dropped=self._dropped(),
            )
            self._cached = (now, state)
            return state

    def _info(self, now: float) -> AgentInfo:
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
        )

    def _worker_infos(self, reports: dict[int, WorkerReport]) -> tuple[WorkerInfo, ...]:
        out = []
        for worker in self._workers:
            report = reports.get(worker.index)
            agent = report.state.agent if report is not None else None
            out.append(
                WorkerInfo(
                    index=worker.index,
                    pid=worker.pid,
                    # Running and answering: a worker being started again has no report to merge yet.
                    alive=worker.alive and report is not None,
                    restarts=worker.restarts,
                    devices=len(report.state.devices) if report is not None else 0,
                    queued=len(worker.queue),
                    dropped=worker.dropped.total(),
                    processed=agent.worker.processed if agent is not None else 0,
                    errors=agent.worker.errors if agent is not None else 0,
                    recording=agent.recording.path if agent is not None and agent.recording else "",
                )
            )
        return tuple(out)

    def _dropped(self) -> Counter[str]:
        """Messages of each device dropped in this process: a worker's queue overflowed, or it was down."""
        total: Counter[str] = Counter()
        for worker in self._workers:
            total.update(worker.queue.overflowed)
            total.update(worker.dropped)
        return total

    def healthz(self) -> HealthReport:
        """Healthy = running, the broker connection up, every worker running and no configured device
        OFFLINE."""
        state = self.state()
        connected = self._started_pool and self._pool.connected
        reasons = []
        if not self.running:
            reasons.append("service not running")
        if not connected:
            reasons.append("broker connection down")
        reasons.extend(f"worker {w.index} is not running" for w in state.agent.workers if not w.alive)
        configured = set() if self.config.telemetry.all_devices else set(self.config.telemetry.devices)
        statuses = {device: d.status for device, d in state.devices.items()}
        reasons.extend(
            f"device {d} is OFFLINE" for d in sorted(configured) if statuses.get(d) is DeviceStatus.OFFLINE
        )
        return HealthReport(
            status="ok" if not reasons else "unavailable",
            running=self.running,
            broker_connected=connected,
            devices=statuses,
            reasons=tuple(reasons),
        )

    def alarms(self, *, include_normal: bool = False) -> tuple[AlarmInfo, ...]:
        """Every worker's alarms, worst first (the order AgentService.alarms uses)."""
        merged = [info for _, infos in self._ask_all("alarms", include_normal) for info in infos]
        return tuple(sorted(merged, key=alarm_order))

    def acknowledge_alarm(self, alarm_id: str) -> AlarmInfo:
        """Acknowledged by the worker that owns the alarm's device; raises AlarmNotFound or
        NothingToAcknowledge as AgentService does."""
        device = alarm_id.split("/", 1)[0]
        index = self._routes.get(device)
        if index is None:
            raise AlarmNotFound(alarm_id)
        self._cached = None
        return self._ask(self._workers[index], "ack", alarm_id)

    def _fleet_totals(self) -> FleetTotals:
        return fleet_totals(self.state(), self.config.health.expected_rate_hz)


# ------------------------------------------------------------------------------------------------ merging


def merge_reports(
    info: AgentInfo,
    reports: Sequence[WorkerReport],
    workers: tuple[WorkerInfo, ...],
    *,
    refused: dict[str, int],
    dropped: Counter[str],
) -> AgentState:
    """One fleet state from the workers' states. `info` is the receiving process's own part (process,
    broker); `refused` its rejections by reason (devices over telemetry.max_devices); `dropped` the messages
    of each device it could not hand to a worker, counted with the worker's own queue drops (`overwritten`).
    """
    devices = {}
    untracked: Counter[str] = Counter(refused)
    internal, end_to_end = LatencyHistogram(), LatencyHistogram()
    for report in reports:
        state = report.state
        for device, d in state.devices.items():
            extra = dropped.get(device, 0)
            counters = d.counters
            devices[device] = (
                dataclasses.replace(
                    d, counters=dataclasses.replace(counters, overwritten=counters.overwritten + extra)
                )
                if extra
                else d
            )
        untracked.update(state.untracked_rejected)
        internal.merge(report.internal)
        end_to_end.merge(report.end_to_end)
    agents = [report.state.agent for report in reports]
    return AgentState(
        agent=dataclasses.replace(
            info,
            running=info.running and all(w.alive for w in workers),
            mailbox=MailboxState(
                overwritten_total=sum(a.mailbox.overwritten_total for a in agents) + dropped.total(),
                refused_keys=0,
                pending=sum(a.mailbox.pending for a in agents) + sum(w.queued for w in workers),
            ),
            latency=FleetLatency(internal_s=internal.summary(), end_to_end_s=end_to_end.summary()),
            worker=WorkerState(
                alive=all(w.alive for w in workers),
                batches=sum(a.worker.batches for a in agents),
                processed=sum(a.worker.processed for a in agents),
                errors=sum(a.worker.errors for a in agents),
            ),
            recording=_merge_recording([a.recording for a in agents if a.recording is not None]),
            history=_merge_history([a.history for a in agents if a.history is not None]),
            sinks=_merge_sinks([a.sinks for a in agents]),
            alarms=_merge_alarms([a.alarms for a in agents]),
            loss=fleet_loss(d.loss for d in devices.values()),
            workers=workers,
        ),
        devices=dict(sorted(devices.items())),
        untracked_rejected=dict(sorted(untracked.items())),
    )


def _sum_fields(items: Sequence[Any], cls: type, **fixed: Any) -> Any:
    """A dataclass whose counts are the sums of `items`' (other fields from `fixed`)."""
    values: dict[str, Any] = dict(fixed)
    for f in dataclasses.fields(cls):
        first = getattr(items[0], f.name)
        # By value, not annotation: under `from __future__ import annotations` those are strings.
        if f.name not in fixed and isinstance(first, int) and not isinstance(first, bool):
            values[f.name] = sum(getattr(item, f.name) for item in items)
    return cls(**values)


def _merge_recording(parts: list[RecordingState]) -> RecordingState | None:
    if not parts:
        return None
    # Each worker records its own devices into its own session file; `agent.workers` lists every path.
    return _sum_fields(parts, RecordingState, path=parts[0].path)


def _merge_history(parts: list[HistoryState]) -> HistoryState | None:
    if not parts:
        return None
    return _sum_fields(
        parts,
        HistoryState,
        uri=parts[0].uri,
        storage_ok=all(p.storage_ok for p in parts),
        last_error=next((p.last_error for p in parts if p.last_error), ""),
    )


def _merge_sinks(parts: list[tuple[SinkStats, ...]]) -> tuple[SinkStats, ...]:
    by_name: dict[str, list[SinkStats]] = {}
    for stats in parts:
        for sink in stats:
            by_name.setdefault(sink.name, []).append(sink)
    return tuple(
        _sum_fields(
            group,
            SinkStats,
            name=name,
            last_error=next((s.last_error for s in group if s.last_error), ""),
        )
        for name, group in by_name.items()
    )


def _merge_counts(parts: Sequence[dict[str, int]]) -> dict[str, int]:
    total: Counter[str] = Counter()
    for part in parts:
        total.update(part)
    return dict(sorted(total.items()))


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
    "ShardedAgent",
    "WorkerError",
    "WorkerPlan",
    "WorkerReport",
    "merge_reports",
    "worker_config",
    "worker_count",
]
