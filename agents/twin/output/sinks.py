"""Sinks: where each mirrored sample goes besides the twin itself (USD recording, history, Rerun, ROS 2).

The agent's worker applies a message to the device's twin and then hands one `AppliedSample` to every sink
(and one `RejectedSample` for each rejected message, and one `StatusChange` when an arm goes STALE, OFFLINE or
back ONLINE: silence changes those, not a message, so a sink could not tell them from its samples). The worker
is the mirror's hot path, so a sink's `applied`/`rejected`/`status` must return in microseconds and never
block on I/O. Sinks that do I/O (a file, S3, a network peer) wrap their blocking work in `QueuedSink`: a
bounded queue and a thread of their own, which drops the oldest queued item when the sink falls behind and
counts it (save an arm's newest status change, kept aside in a slot of one per arm tracked, and a forget,
kept in a queue of its own as large, which drops only its own oldest when full), so a slow disk, a
stalled viewer or an absent ROS peer never slows mirroring and never grows memory without bound.

A sample carries joint angles, not body poses: forward kinematics is computed where it is needed, in the
sink's own thread (`RobotModel.body_poses`), because MuJoCo scratch data is per thread and most sinks need
no poses at all.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from twin.core import heap
from twin.core.alarms import AlarmEvent
from twin.core.health import DeviceStatus

if TYPE_CHECKING:
    # Annotations only: the config imports the ROS 2 sink's settings, which import this module, and
    # `twin --help` must not need the decoder's msgspec (tests/infra/test_userdata.py).
    from twin.core.telemetry import Telemetry

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class AppliedSample:
    """One message the twin applied: the decoded telemetry and the angles the twin now shows.

    The history sink alone also receives the valid messages the twin did not apply (late or duplicate); for
    those `joint_angles` are the decoded angles."""

    device_id: str
    received_wall_s: float
    received_mono_s: float
    telemetry: Telemetry
    # What the twin applied: the decoded angles clamped to the model's joint ranges (radians, by joint name).
    joint_angles: Mapping[str, float]
    # The message exactly as received. History keeps the raw readings the decoder does not carry (the
    # velocity and load registers before sign decoding); empty when the producer did not pass it.
    payload: bytes = b""
    # Servo alarm state changes this message caused (raised, cleared), in the order the engine made them.
    alarm_events: tuple[AlarmEvent, ...] = ()

    @property
    def timestamp_ms(self) -> int:
        return self.telemetry.timestamp_ms


# A rejected message travels to the sinks with at most this many bytes of its payload (history keeps as much,
# docs/history.md); its full size goes with it. A rejection may be a 128 KiB message (or a larger one refused
# for its size): every sink queue holding the whole of it would make a flood of junk cost megabytes per sink.
REJECTED_PAYLOAD_KEPT = 4096
# What a queued sample weighs besides its payload (the decoded telemetry, its dicts and the sample itself),
# for the queues' byte bounds: measured with tracemalloc on edge-mock samples, rounded up.
SAMPLE_OVERHEAD_BYTES = 2048


@dataclass(frozen=True, slots=True)
class RejectedSample:
    """One message the decoder refused, with the reason it was counted under: what its counters and history
    need, so `payload` is the message's first bytes (`rejected_sample` keeps REJECTED_PAYLOAD_KEPT of them)
    and `payload_bytes` its full size."""

    device_id: str | None
    topic: str
    received_wall_s: float
    reason: str
    detail: str
    payload: bytes
    payload_bytes: int = -1

    @property
    def size(self) -> int:
        """The message's full size (`payload_bytes`, or the payload's when not given)."""
        return self.payload_bytes if self.payload_bytes >= 0 else len(self.payload)


def rejected_sample(
    device_id: str | None, topic: str, *, received_wall_s: float, reason: str, detail: str, payload: bytes
) -> RejectedSample:
    """A RejectedSample that keeps only the payload's first REJECTED_PAYLOAD_KEPT bytes (and its size)."""
    return RejectedSample(
        device_id=device_id,
        topic=topic,
        received_wall_s=received_wall_s,
        reason=reason,
        detail=detail[:1024],
        payload=bytes(payload[:REJECTED_PAYLOAD_KEPT]),
        payload_bytes=len(payload),
    )


@dataclass(frozen=True, slots=True)
class StatusChange:
    """An arm's status changed (docs/agent.md, "Health"), as the mirror's status sweep read it: `at_mono_s`
    is where the mirror stood in its input then, on the clock of the samples' `received_mono_s` (to place it
    among the arm's samples), and `at_wall_s` the same moment on the wall clock. `forgotten`: the agent
    forgot the OFFLINE arm (`previous` is OFFLINE, as the mirror read it, even if the sweep had not yet told
    the sink so): a sink drops what it keeps of it, and an arm of that name that publishes again is new to
    it, ONLINE from its first sample."""

    device_id: str
    previous: DeviceStatus
    status: DeviceStatus
    at_mono_s: float
    at_wall_s: float
    forgotten: bool = False


def sample_bytes(item: AppliedSample | RejectedSample | StatusChange) -> int:
    """What a queued sample weighs, roughly: its payload plus a fixed overhead (SAMPLE_OVERHEAD_BYTES)."""
    payload = 0 if isinstance(item, StatusChange) else len(item.payload)
    return payload + SAMPLE_OVERHEAD_BYTES


@dataclass(frozen=True, slots=True)
class SinkStats:
    """Counters a sink reports in /state and /metrics."""

    name: str
    delivered: int = 0
    dropped: int = 0
    errors: int = 0
    pending: int = 0
    last_error: str = ""
    # Samples the sink chose not to write (a rate cap), unlike `dropped` ones it could not keep up with.
    skipped: int = 0


class TwinSink(Protocol):
    """What the agent's worker calls. Every method except `close` must return without blocking."""

    name: str

    def applied(self, sample: AppliedSample) -> None: ...

    def rejected(self, sample: RejectedSample) -> None: ...

    def status(self, change: StatusChange) -> None:
        """An arm's status changed; a sink that shows no statuses does nothing. (The mirror looks this up
        per sink: a sink written before it is handed none.)"""

    def stats(self) -> SinkStats: ...

    def close(self, timeout: float = 5.0) -> None: ...


class SinkWorker(Protocol):
    """The blocking half of a queued sink; runs on the sink's own thread only. One that shows arms' statuses
    also has `handle_status(change: StatusChange)`; `QueuedSink` hands the others none."""

    def handle_applied(self, sample: AppliedSample) -> None: ...

    def handle_rejected(self, sample: RejectedSample) -> None: ...

    def idle(self) -> None:
        """Called when the queue has been empty for `idle_s` (time-based flushes go here)."""
        ...

    def close(self) -> None:
        """Flush and release; called once, on the sink's thread, after the queue is drained."""
        ...


# A queued sink holds at most this many bytes of samples (payloads and their overhead) besides its count.
DEFAULT_MAX_PENDING_BYTES = 64 * 2**20
# The most arms one agent tracks at once (the limit of telemetry.max_devices): a queued sink keeps aside the
# newest status change of at least this many (a few hundred bytes each), so none of them is lost.
RESCUE_MIN_ARMS = 10_000


# DeviceRateCap forgets a device silent this long at least (longer when its bucket takes longer to refill).
FORGET_DEVICE_AFTER_S = 10.0


class DeviceRateCap:
    """A token bucket per device on the agent's receive clock: at most `rate_hz` samples a second, with up to
    `burst` at once. The receive clock, not the edge's: a sink's cost follows the messages arriving,
    whatever the edge's stamps say. One entry per admitted device, so the table is as bounded as the fleet.

    With `fleet_rate_hz`, a fleet of n devices gets at most that in all: each device `fleet_rate_hz / n`
    when that is less than `rate_hz`, its burst scaled with it, so a sink whose cost is per sample keeps
    up with a large fleet at a lower rate per arm instead of dropping whole seconds of it. n counts the
    devices heard from lately: a device silent for `forget_after_s` is forgotten, so arms that left do not
    shrink the share of those still sending for the rest of the run."""

    __slots__ = ("_buckets", "_burst", "_fleet_rate", "_forget_after_s", "_next_sweep", "_rate")

    def __init__(self, rate_hz: float, burst: float, fleet_rate_hz: float = math.inf) -> None:
        self._rate = rate_hz
        self._burst = max(1.0, burst)
        self._fleet_rate = fleet_rate_hz
        self._buckets: dict[str, tuple[float, float]] = {}  # device -> (tokens, receive time)
        # A bucket left alone for burst / rate seconds is full again (a share scales both alike), so
        # forgetting it after that long changes nothing for its device when it comes back.
        refill_s = self._burst / rate_hz if 0 < rate_hz < math.inf else 0.0
        self._forget_after_s = max(FORGET_DEVICE_AFTER_S, refill_s)
        self._next_sweep = -math.inf

    @property
    def devices(self) -> int:
        """Devices with a bucket: those heard from within about `forget_after_s`."""
        return len(self._buckets)

    def take(self, device: str, received_mono_s: float) -> bool:
        """Whether `device` may have a sample received at `received_mono_s` (a token is spent if so)."""
        if received_mono_s >= self._next_sweep:
            self._forget_silent(received_mono_s)
        bucket = self._buckets.get(device)
        rate, burst = self._rate, self._burst
        devices = len(self._buckets) + (bucket is None)
        if self._fleet_rate < rate * devices:
            rate = self._fleet_rate / devices
            burst = max(1.0, burst * rate / self._rate)
        tokens, last = bucket if bucket is not None else (burst, received_mono_s)
        tokens = min(burst, tokens + max(0.0, received_mono_s - last) * rate)
        if tokens < 1.0:
            self._buckets[device] = (tokens, received_mono_s)
            return False
        self._buckets[device] = (tokens - 1.0, received_mono_s)
        return True

    def _forget_silent(self, now: float) -> None:
        """Drop the buckets of devices silent for `forget_after_s`; runs twice in that time at most."""
        horizon = now - self._forget_after_s
        silent = [device for device, (_, last) in self._buckets.items() if last < horizon]
        for device in silent:
            del self._buckets[device]
        self._next_sweep = now + self._forget_after_s / 2


class QueuedSink:
    """Runs a `SinkWorker` on its own thread behind a queue bounded by samples (`max_pending`) and by their
    bytes (`max_pending_bytes`, sample_bytes), which drops the oldest when full. Status changes queue with the
    samples, in order, but an arm's newest is kept: dropped from the queue, it waits in a slot of its own (one
    per arm, for every arm tracked at once) and goes to the worker before the rest. A dropped forget waits
    too, in a queue of its own as large, that no later change of its id replaces; each is bounded on its own,
    so no forget goes for want of room for changes, and no change for forgets.

    Errors raised by the worker are caught, counted and logged (at most once per `error_log_s`), never
    propagated: a broken sink must not stop the mirror or the other sinks.
    """

    def __init__(
        self,
        name: str,
        worker: SinkWorker,
        *,
        max_pending: int = 10_000,
        max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES,
        idle_s: float = 0.5,
        hand_off_s: float = 0.0,
    ) -> None:
        if max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending}")
        if max_pending_bytes < 1:
            raise ValueError(f"max_pending_bytes must be >= 1, got {max_pending_bytes}")
        if hand_off_s < 0:
            raise ValueError(f"hand_off_s must be >= 0, got {hand_off_s}")
        self.name = name
        self._worker = worker
        self._queue: collections.deque[AppliedSample | RejectedSample | StatusChange] = collections.deque()
        # Looked up once: a worker that shows no statuses (the USD recording, ROS 2) is handed none, so they
        # take no room in its queue.
        self._handle_status: Callable[[StatusChange], None] | None = getattr(worker, "handle_status", None)
        # A quiet arm sends no sample to correct a status change the queue dropped: it would be shown wrong
        # until its next change. So each arm's newest change not yet taken by the thread is known (`_latest`),
        # and when dropped it waits in `_rescued` instead, until taken or replaced by a newer one. A dropped
        # forget waits in `_forgets`, oldest first, never replaced (lost, an arm of its id back would keep
        # the old one's OFFLINE label), and goes before its id's newer change in `_rescued`. All hold one
        # change per arm at most and empty at each batch taken: every change in them came after the last.
        # Each is bounded (`_rescue`), and `_latest` holds only changes queued or in them.
        self._latest: dict[str, StatusChange] = {}
        self._rescued: dict[str, StatusChange] = {}
        self._forgets: dict[str, StatusChange] = {}
        self._max = max_pending
        self._max_bytes = max_pending_bytes
        # The slot holds as many changes as the queue would (by count and by bytes), and at least one for
        # every arm an agent may track at once, however small the queue: an arm's newest status never goes
        # for want of room (`_rescue`). The forgets' queue holds as many besides.
        queued = min(max_pending, max_pending_bytes // SAMPLE_OVERHEAD_BYTES)
        self._max_rescued = max(RESCUE_MIN_ARMS, queued)
        self._bytes = 0
        self._cond = threading.Condition(threading.Lock())
        self._idle_s = idle_s
        # After each batch the thread pauses this long before it takes the next, so under load samples arrive
        # in batches: waking the thread for every sample hands the GIL back and forth with the mirror's own
        # threads, which cost more than the sink's work (docs/web.md, "Where the CPU goes"). The agent's
        # worker only wakes a thread that waits on an empty queue.
        self._hand_off_s = hand_off_s
        self._waiting = False
        self._in_flight = 0
        # A batch this large is a backlog (the sink fell behind): once it has drained, the memory its samples
        # and the worker's buffers took is free, and is given back to the system (twin.core.heap).
        self._backlog_items = max(256, max_pending // 10)
        self._in_backlog = False
        self._closing = False
        self._delivered = 0
        self._dropped = 0
        self._errors = 0
        self._last_error = ""
        self._thread = threading.Thread(target=self._run, name=f"sink-{name}", daemon=True)
        self._thread.start()

    def applied(self, sample: AppliedSample) -> None:
        self._put(sample)

    def rejected(self, sample: RejectedSample) -> None:
        self._put(sample)

    def status(self, change: StatusChange) -> None:
        if self._handle_status is None:
            return
        with self._cond:
            if not self._closing:
                device = change.device_id
                # Replaced by this newer change before the thread took it (never a forget: `_forgets`).
                if self._rescued.pop(device, None) is not None:
                    self._dropped += 1
                self._latest[device] = change
            self._append(change)

    def _put(self, item: AppliedSample | RejectedSample) -> None:
        with self._cond:
            self._append(item)

    def _append(self, item: AppliedSample | RejectedSample | StatusChange) -> None:
        """Queue `item` (the lock held), dropping the oldest beyond the bounds."""
        if self._closing:
            self._dropped += 1
            return
        queue = self._queue
        queue.append(item)
        self._bytes += sample_bytes(item)
        # Newest wins: a live view wants the present, and history counts what it lost.
        while len(queue) > 1 and (len(queue) > self._max or self._bytes > self._max_bytes):
            old = queue.popleft()
            self._bytes -= sample_bytes(old)
            if isinstance(old, StatusChange) and (old.forgotten or self._latest.get(old.device_id) is old):
                self._rescue(old)
            else:
                self._dropped += 1
        if self._waiting and len(queue) == 1:
            self._cond.notify()

    def _rescue(self, change: StatusChange) -> None:
        """Keep `change`, a forget or the newest of its arm, in the slot or the forgets' queue (the lock
        held). An id's forget kept already stands for a later one: the sink saw nothing of the arm between
        them (it was older than this one, and dropped first). Each is bounded on its own: a stuck thread with
        arms forgotten and replaced would fill them with every new device id. The arms tracked, one change
        each, fit in the slot, so none of them loses its newest; and forgets never go to make room for them
        (a lost forget leaves the old arm's OFFLINE label over its id's return, which sends no change). Only
        more forgets waiting than the queue holds drop the oldest of them, counted."""
        forgets, rescued = self._forgets, self._rescued
        if not change.forgotten:
            kept = rescued
        elif change.device_id in forgets:
            self._drop_change(change)
            return
        else:
            kept = forgets
        kept[change.device_id] = change
        if len(kept) > self._max_rescued:
            self._drop_change(kept.pop(next(iter(kept))))

    def _drop_change(self, change: StatusChange) -> None:
        """Count `change` dropped, and let its id's `_latest` go with it if it was that (the lock held)."""
        if self._latest.get(change.device_id) is change:
            del self._latest[change.device_id]
        self._dropped += 1

    def stats(self) -> SinkStats:
        with self._cond:
            return SinkStats(
                name=self.name,
                delivered=self._delivered,
                dropped=self._dropped,
                errors=self._errors,
                pending=len(self._queue) + len(self._forgets) + len(self._rescued) + self._in_flight,
                last_error=self._last_error,
            )

    def close(self, timeout: float = 5.0) -> None:
        """Deliver what is queued, then close the worker; waits up to `timeout` s. Idempotent."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.error("sink %s did not finish within %.1f s; its queued items are lost", self.name, timeout)

    def _run(self) -> None:
        worker = self._worker
        while True:
            with self._cond:
                if not self._queue and not self._closing:
                    self._waiting = True
                    self._cond.wait(self._idle_s)
                    self._waiting = False
                # The slot's changes came before everything still queued (each was the oldest item then).
                # All its forgets go before the changes of its other ids: harmless, as each arm is drawn at
                # its own times.
                items = [*self._forgets.values(), *self._rescued.values(), *self._queue]
                self._queue.clear()
                self._forgets.clear()
                self._rescued.clear()
                self._latest.clear()
                self._bytes = 0
                self._in_flight = len(items)
                closing = self._closing
            if not items:
                if closing:
                    self._guard(worker.close)
                    return
                self._guard(worker.idle)
                self._backlog_check(0)
                continue
            delivered = 0
            for item in items:
                if isinstance(item, AppliedSample):
                    delivered += self._guard(worker.handle_applied, item)
                elif isinstance(item, StatusChange):
                    if self._handle_status is not None:
                        self._guard(self._handle_status, item)
                else:
                    self._guard(worker.handle_rejected, item)
            with self._cond:
                self._delivered += delivered
                self._in_flight = 0
            self._backlog_check(len(items))
            if self._hand_off_s and not closing:
                time.sleep(self._hand_off_s)

    def _backlog_check(self, batch: int) -> None:
        """After a batch of `batch` items: a large one starts a backlog, a small one after it ends it, and
        then the memory the backlog took goes back to the system."""
        if batch >= self._backlog_items:
            self._in_backlog = True
        elif self._in_backlog and batch < self._backlog_items // 4:
            self._in_backlog = False
            heap.trim()

    def _guard(self, fn: Callable[..., object], *args: object) -> bool:
        try:
            fn(*args)
        except Exception as exc:
            with self._cond:
                first = self._errors == 0 or str(exc) != self._last_error
                self._errors += 1
                self._last_error = f"{type(exc).__name__}: {exc}"
            if first:
                log.exception("sink %s failed", self.name, extra={"sink": self.name})
            return False
        return True
