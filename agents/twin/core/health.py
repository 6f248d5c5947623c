"""Per-device health of the telemetry stream: status, age, rate, counters and latencies.

Pure bookkeeping with an injected monotonic clock, so every rule is tested without sleeping. Ages and
rates use the agent's monotonic receive time only: the edge clock is not NTP-disciplined and may drift or
jump, so it never decides whether a device is alive. The edge timestamp is used for one thing here, the
end-to-end latency, which is published as `edge_clock_latency` next to an estimate of the clock offset so
a skewed edge clock is visible instead of masquerading as network delay.

Not thread-safe by itself: the agent updates it from its one worker thread and reads it under the service
lock.
"""

from __future__ import annotations

import math
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import StrEnum

Clock = Callable[[], float]

# Latency percentiles are computed over at most this many recent samples: enough for a stable p99 at 10 Hz
# over the window, and bounded during a flood.
MAX_LATENCY_SAMPLES = 4096
# The rate counter groups receive times into buckets this long instead of keeping one entry per message.
RATE_BUCKET_S = 0.1


class DeviceStatus(StrEnum):
    ONLINE = "ONLINE"
    STALE = "STALE"
    OFFLINE = "OFFLINE"


@dataclass(frozen=True)
class HealthThresholds:
    """STALE after `stale_periods` missed expected periods; OFFLINE after `offline_after_s` of silence."""

    expected_rate_hz: float = 10.0
    stale_periods: float = 3.0
    offline_after_s: float = 10.0
    window_s: float = 5.0

    @property
    def stale_after_s(self) -> float:
        return self.stale_periods / self.expected_rate_hz

    def classify(self, silent_for_s: float) -> DeviceStatus:
        if silent_for_s >= self.offline_after_s:
            return DeviceStatus.OFFLINE
        if silent_for_s > self.stale_after_s:
            return DeviceStatus.STALE
        return DeviceStatus.ONLINE


@dataclass(frozen=True, slots=True)
class WindowLatency:
    """Percentiles (seconds) over the health window; None while the window holds no sample."""

    p50: float | None = None
    p99: float | None = None
    samples: int = 0


@dataclass(frozen=True)
class DeviceCounters:
    """Message counters of one device since the agent started (docs/agent.md, "counters")."""

    received: int = 0
    decoded: int = 0
    applied: int = 0
    ignored_stale: int = 0
    # Valid messages not applied because a newer valid one of the same arm was already waiting (the worker
    # was catching up); they still count as received and decoded, and history keeps them.
    coalesced: int = 0
    overwritten: int = 0
    errors: int = 0
    clock_resets: int = 0
    rejected_total: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    # Applied angles that lay outside the model's joint range and were clamped into it.
    clamped: int = 0


@dataclass(frozen=True)
class HealthSnapshot:
    """One device's health at one instant: what /state and /metrics publish for it."""

    status: DeviceStatus = DeviceStatus.OFFLINE
    age_s: float | None = None
    # None while not known: read from a checkpoint (a worker started again), whose meter starts empty, it
    # read 0 beside a valid message 1 s old. So is the default, as refused_rate_hz's.
    rate_hz: float | None = None
    last_timestamp_ms: int | None = None
    counters: DeviceCounters = field(default_factory=DeviceCounters)
    # Receive wall time minus the edge timestamp. The edge clock is not NTP-disciplined, so this is transit
    # delay PLUS clock offset; the offset estimate (the window minimum) shows how much is skew, and p99 minus
    # that minimum is a transit jitter that no constant skew can fake.
    edge_clock_latency_s: WindowLatency = field(default_factory=WindowLatency)
    edge_clock_offset_s: float | None = None
    edge_transit_jitter_p99_s: float | None = None
    internal_latency_s: WindowLatency = field(default_factory=WindowLatency)
    # Its refused messages (rejected for its topic): a held arm's are all refused, yet they show it is on.
    # Its page read "last seen never, 0.0 Hz" while it published ten a second. The rate is None while not
    # known (`refused_rate`), not 0: read from a checkpoint it was 0 beside "a refused one 2 s ago". So is
    # the default: a snapshot built without it knows nothing of its refused messages.
    refused_age_s: float | None = None
    refused_rate_hz: float | None = None


# A HealthCheckpoint as plain values (`DeviceHealth.checkpoint_row`, `HealthCheckpoint.from_row`), which
# pickle without a call into Python per object: received, decoded, applied, ignored_stale, coalesced,
# overwritten, errors, clock_resets, clamped, the rejections by reason, the three times, then the last refused
# message's arrival and reason.
HealthRow = tuple[
    int,
    int,
    int,
    int,
    int,
    int,
    int,
    int,
    int,
    dict[str, int],
    float | None,
    float | None,
    int | None,
    float | None,
    str,
]


@dataclass(frozen=True, slots=True)
class HealthCheckpoint:
    """What a device's health must carry across a restart of its mirror: the counters and the times that
    decide its status (the agent's monotonic clock, which every process of one host shares). The windows
    behind the rate and the latencies start again empty."""

    counters: DeviceCounters
    last_message_mono: float | None = None
    last_applied_mono: float | None = None
    last_timestamp_ms: int | None = None
    # A worker started again refused no forget of an arm whose refused messages still arrived, until the
    # next one: it did not know of the last (DeviceHealth.last_refused_mono).
    last_refused_mono: float | None = None
    last_refused_reason: str = ""

    @classmethod
    def from_row(cls, row: HealthRow) -> HealthCheckpoint:
        """The checkpoint `DeviceHealth.checkpoint_row` gave as plain values."""
        received, decoded, applied, ignored, coalesced, overwritten, errors, resets, clamped = row[:9]
        rejected = row[9]
        return cls(
            counters=DeviceCounters(
                received=received,
                decoded=decoded,
                applied=applied,
                ignored_stale=ignored,
                coalesced=coalesced,
                overwritten=overwritten,
                errors=errors,
                clock_resets=resets,
                rejected_total=sum(rejected.values()),
                rejected=dict(sorted(rejected.items())),
                clamped=clamped,
            ),
            last_message_mono=row[10],
            last_applied_mono=row[11],
            last_timestamp_ms=row[12],
            last_refused_mono=row[13],
            last_refused_reason=row[14],
        )

    def snapshot(self, thresholds: HealthThresholds, now: float, since: float) -> HealthSnapshot:
        """The health as far as the checkpoint knows it at `now` (no rate, no latencies); `since`: when
        tracking began, for a device never heard from."""
        last = self.last_message_mono if self.last_message_mono is not None else since
        return HealthSnapshot(
            status=thresholds.classify(max(0.0, now - last)),
            age_s=None if self.last_message_mono is None else max(0.0, now - self.last_message_mono),
            rate_hz=refused_rate(self.last_message_mono, None, now, thresholds.window_s),
            last_timestamp_ms=self.last_timestamp_ms,
            counters=self.counters,
            refused_age_s=None if self.last_refused_mono is None else max(0.0, now - self.last_refused_mono),
            refused_rate_hz=refused_rate(self.last_refused_mono, None, now, thresholds.window_s),
        )


def refused_rate(
    last_mono: float | None, meter: RateMeter | None, at: float, window_s: float
) -> float | None:
    """A device's refused messages per second at `at`: 0 with none within `window_s`, None (not known) while
    `meter` has not counted them for a whole window (none: a checkpoint's, or a worker started again). A
    checkpoint's valid rate is read so too, with no meter."""
    if last_mono is None or at - last_mono > window_s:
        return 0.0
    if meter is None or meter.since is None or at - meter.since < window_s:
        return None
    return meter.rate(at)


def percentile(sorted_values: list[float], q: float) -> float | None:
    """Nearest-rank percentile (q in 0..1) of an ascending list; None when empty."""
    if not sorted_values:
        return None
    rank = max(1, math.ceil(q * len(sorted_values)))
    return sorted_values[min(rank, len(sorted_values)) - 1]


class SampleWindow:
    """Values observed in the last `window_s` seconds (bounded), for percentiles and minima."""

    def __init__(self, window_s: float, max_samples: int = MAX_LATENCY_SAMPLES) -> None:
        self._window = window_s
        self._samples: deque[tuple[float, float]] = deque(maxlen=max_samples)

    def add(self, now: float, value: float) -> None:
        samples = self._samples
        samples.append((now, value))
        # Trimmed here as well as when read: nobody may read /state for hours, and a window that only ever
        # reached its maxlen held 4,096 samples of every device instead of the window's worth.
        horizon = now - self._window
        while samples[0][0] <= horizon:
            samples.popleft()

    def values(self, now: float) -> list[float]:
        horizon = now - self._window
        while self._samples and self._samples[0][0] <= horizon:
            self._samples.popleft()
        return [v for _, v in self._samples]

    def samples(self, now: float) -> tuple[tuple[float, float], ...]:
        """The window's (time, value) samples, copied (a copy of the deque costs a tenth of `values`)."""
        horizon = now - self._window
        while self._samples and self._samples[0][0] <= horizon:
            self._samples.popleft()
        return tuple(self._samples)

    def minimum(self, now: float) -> float | None:
        """The window's smallest value (None when empty)."""
        values = self.values(now)
        return min(values) if values else None

    def summary(self, now: float) -> tuple[WindowLatency, float | None]:
        """Percentiles over the window, and its minimum (None when empty)."""
        return window_summary(self.values(now))


def window_summary(values: list[float]) -> tuple[WindowLatency, float | None]:
    """Percentiles of a window's values (sorted here, in place), and their minimum (None when empty)."""
    values.sort()
    latency = WindowLatency(p50=percentile(values, 0.50), p99=percentile(values, 0.99), samples=len(values))
    return latency, (values[0] if values else None)


@dataclass(frozen=True, slots=True)
class HealthReading:
    """A device's health as copied while its worker waits (`DeviceHealth.reading`): the latency windows'
    samples as they are, summarised by `snapshot` afterwards. Summarising every window under the worker's
    lock was most of the time a report held it at a large fleet (docs/performance.md)."""

    status: DeviceStatus
    age_s: float | None
    rate_hz: float
    last_timestamp_ms: int | None
    counters: DeviceCounters
    edge_latencies: tuple[tuple[float, float], ...]  # (receive time, latency) samples
    internal_latencies: tuple[tuple[float, float], ...]
    refused_age_s: float | None = None
    refused_rate_hz: float | None = None

    def snapshot(self) -> HealthSnapshot:
        """The health this reading holds, as /state publishes it."""
        edge, offset = window_summary([v for _, v in self.edge_latencies])
        internal, _ = window_summary([v for _, v in self.internal_latencies])
        return HealthSnapshot(
            status=self.status,
            age_s=self.age_s,
            rate_hz=self.rate_hz,
            last_timestamp_ms=self.last_timestamp_ms,
            counters=self.counters,
            edge_clock_latency_s=edge,
            edge_clock_offset_s=offset,
            edge_transit_jitter_p99_s=None if offset is None or edge.p99 is None else edge.p99 - offset,
            internal_latency_s=internal,
            refused_age_s=self.refused_age_s,
            refused_rate_hz=self.refused_rate_hz,
        )


class RateMeter:
    """Events per second over a sliding window, from counts in short buckets (O(1) per event, bounded)."""

    def __init__(self, window_s: float, bucket_s: float = RATE_BUCKET_S) -> None:
        self._window = window_s
        self._bucket = bucket_s
        self._buckets: deque[list[float]] = deque()  # [bucket start, count]
        # The buckets' sum, kept as they open and go: a fleet's rates are read every few seconds
        # (service.events.RateWatch), and summing 50 buckets an arm held the worker's lock for milliseconds.
        self._count = 0.0
        self._first: float | None = None

    @property
    def since(self) -> float | None:
        """When its first event came (None: none yet)."""
        return self._first

    def add(self, now: float, n: int = 1) -> None:
        if self._first is None:
            self._first = now
        self._count += n
        start = now - (now % self._bucket)
        buckets = self._buckets
        if buckets and buckets[-1][0] == start:
            buckets[-1][1] += n
            return
        buckets.append([start, float(n)])
        # Trimmed as buckets open, not only when read: unread for hours, a device kept ten buckets a second.
        self._trim(now)

    def _trim(self, now: float) -> None:
        horizon = now - self._window
        buckets = self._buckets
        while buckets and buckets[0][0] + self._bucket <= horizon:
            self._count -= buckets.popleft()[1]
        if not buckets:
            self._count = 0.0  # no float residue left over from the sums

    def rate(self, now: float) -> float:
        self._trim(now)
        if self._first is None:
            return 0.0
        count = self._count
        buckets = self._buckets
        if buckets:
            # The oldest bucket reaches back past the window: only its share inside it counts. Counted whole,
            # a steady arm read half a bucket high on average (10.0-10.2 Hz at 10 Hz), and LossPercent low.
            start, oldest = buckets[0]
            outside = (now - self._window - start) / self._bucket
            if outside > 0.0:
                count -= oldest * outside
        # A device seen for less than the window is rated over the time it has been seen, but over at least
        # one second so the first message does not read as a burst.
        span = max(min(self._window, now - self._first), 1.0)
        return count / span


class DeviceHealth:
    """The health record of one device."""

    def __init__(self, device_id: str, thresholds: HealthThresholds, clock: Clock, *, since: float) -> None:
        self.device_id = device_id
        self.thresholds = thresholds
        self._clock = clock
        self._since = since  # when tracking began: a device never heard from is silent since then
        self.last_message_mono: float | None = None
        self.last_applied_mono: float | None = None
        # The last refused message's arrival: an arm whose every message is refused is OFFLINE (its
        # status is of valid messages) yet still publishes, so it is not retired (Mirror.forget_arm).
        self.last_refused_mono: float | None = None
        self.last_refused_reason = ""
        self._refused_rate: RateMeter | None = None  # made at the first refusal: most arms have none
        self.last_timestamp_ms: int | None = None
        self.received = 0
        self.decoded = 0
        self.applied = 0
        self.ignored_stale = 0
        self.coalesced = 0
        self.overwritten = 0
        self.errors = 0
        self.clock_resets = 0
        self.clamped = 0
        self.rejected: Counter[str] = Counter()
        self._rate = RateMeter(thresholds.window_s)
        self._edge_latency = SampleWindow(thresholds.window_s)
        self._internal_latency = SampleWindow(thresholds.window_s)

    def clock_offset(self, now: float) -> float | None:
        """Receive wall time minus the edge's timestamp, the window's least (HealthSnapshot's
        edge_clock_offset_s): transit plus the edge clock's offset, so mostly the offset when it is large."""
        return self._edge_latency.minimum(now)

    def record_received(self) -> None:
        """A message for this device left the mailbox (before decoding)."""
        self.received += 1

    def record_rejected(self, reason: str, recv_mono: float | None = None) -> None:
        self.rejected[str(reason)] += 1
        if recv_mono is None:
            return
        if self._refused_rate is None:
            self._refused_rate = RateMeter(self.thresholds.window_s)
        self._refused_rate.add(recv_mono)
        if self.last_refused_mono is None or recv_mono >= self.last_refused_mono:
            self.last_refused_mono, self.last_refused_reason = recv_mono, str(reason)

    def record_error(self) -> None:
        self.errors += 1

    def record_decoded(self, recv_mono: float, recv_wall: float, timestamp_ms: int) -> None:
        """A valid telemetry message: the device is alive, whatever its timestamp says."""
        self.decoded += 1
        if self.last_message_mono is None or recv_mono > self.last_message_mono:
            self.last_message_mono = recv_mono
        self._rate.add(recv_mono)
        self._edge_latency.add(recv_mono, recv_wall - timestamp_ms / 1000.0)

    def record_applied(self, recv_mono: float, updated_mono: float, timestamp_ms: int) -> None:
        self.applied += 1
        self.last_applied_mono = updated_mono
        self.last_timestamp_ms = timestamp_ms
        self._internal_latency.add(recv_mono, max(0.0, updated_mono - recv_mono))

    def record_message(
        self, recv_mono: float, recv_wall: float, timestamp_ms: int, applied: bool, updated_mono: float
    ) -> None:
        """One valid message, received and decoded, then applied (at `updated_mono`) or ignored as stale:
        record_received, record_decoded and record_applied or record_ignored_stale in one call, since the
        mirror makes it for every message of the fleet."""
        self.received += 1
        self.decoded += 1
        last = self.last_message_mono
        if last is None or recv_mono > last:
            self.last_message_mono = recv_mono
        self._rate.add(recv_mono)
        self._edge_latency.add(recv_mono, recv_wall - timestamp_ms / 1000.0)
        if applied:
            self.applied += 1
            self.last_applied_mono = updated_mono
            self.last_timestamp_ms = timestamp_ms
            self._internal_latency.add(recv_mono, max(0.0, updated_mono - recv_mono))
        else:
            self.ignored_stale += 1

    def record_ignored_stale(self) -> None:
        self.ignored_stale += 1

    def record_coalesced(self) -> None:
        self.coalesced += 1

    def checkpoint(self) -> HealthCheckpoint:
        """The counters and times a restarted mirror takes back with `restore` (no windows)."""
        return HealthCheckpoint(
            counters=self._counters(),
            last_message_mono=self.last_message_mono,
            last_applied_mono=self.last_applied_mono,
            last_timestamp_ms=self.last_timestamp_ms,
            last_refused_mono=self.last_refused_mono,
            last_refused_reason=self.last_refused_reason,
        )

    def checkpoint_row(self) -> HealthRow:
        """`checkpoint()` as plain values, for a worker's checkpoint of all its arms
        (`HealthCheckpoint.from_row`)."""
        return (
            self.received,
            self.decoded,
            self.applied,
            self.ignored_stale,
            self.coalesced,
            self.overwritten,
            self.errors,
            self.clock_resets,
            self.clamped,
            dict(self.rejected),
            self.last_message_mono,
            self.last_applied_mono,
            self.last_timestamp_ms,
            self.last_refused_mono,
            self.last_refused_reason,
        )

    def restore(self, checkpoint: HealthCheckpoint) -> None:
        """Take back what `checkpoint` carried; counts since it are added on top as messages arrive."""
        c = checkpoint.counters
        self.received = c.received
        self.decoded = c.decoded
        self.applied = c.applied
        self.ignored_stale = c.ignored_stale
        self.coalesced = c.coalesced
        self.overwritten = c.overwritten
        self.errors = c.errors
        self.clock_resets = c.clock_resets
        self.clamped = c.clamped
        self.rejected = Counter(c.rejected)
        self.last_message_mono = checkpoint.last_message_mono
        self.last_applied_mono = checkpoint.last_applied_mono
        self.last_timestamp_ms = checkpoint.last_timestamp_ms
        self.last_refused_mono = checkpoint.last_refused_mono
        self.last_refused_reason = checkpoint.last_refused_reason

    def _counters(self) -> DeviceCounters:
        return DeviceCounters(
            received=self.received,
            decoded=self.decoded,
            applied=self.applied,
            ignored_stale=self.ignored_stale,
            coalesced=self.coalesced,
            overwritten=self.overwritten,
            errors=self.errors,
            clock_resets=self.clock_resets,
            rejected_total=self.rejected_total,
            rejected=dict(sorted(self.rejected.items())),
            clamped=self.clamped,
        )

    def silent_for(self, now: float | None = None) -> float:
        now = self._clock() if now is None else now
        last = self.last_message_mono if self.last_message_mono is not None else self._since
        return max(0.0, now - last)

    def status(self, now: float | None = None) -> DeviceStatus:
        return self.thresholds.classify(self.silent_for(now))

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def rate_hz(self, now: float) -> float:
        """Valid messages per second over the window (what `snapshot` reports, without the rest of it)."""
        return self._rate.rate(now)

    def snapshot(self, now: float | None = None) -> HealthSnapshot:
        """This device's health now (an immutable copy, safe to hand to other threads)."""
        return self.reading(now).snapshot()

    def reading(self, now: float | None = None, behind_s: float = 0.0) -> HealthReading:
        """What `snapshot` needs, copied (the windows trimmed to `now` first): a reader holding the worker's
        lock takes this and builds the snapshot after letting go. The status and rate are read `behind_s`
        before `now`, where the worker stands in its input (service.mirror, "behind"): the messages after it
        are waiting, not missing. So are the latency windows, whose samples go by receive time: read on the
        clock, a worker a window (5 s) behind had none, and InternalLatencyP99, which AgentBehind pages on,
        went missing as the lag grew. The age stays on the clock: it is how old the twin's pose is."""
        now = self._clock() if now is None else now
        at = now - behind_s
        return HealthReading(
            status=self.status(at),
            age_s=None if self.last_message_mono is None else max(0.0, now - self.last_message_mono),
            rate_hz=self._rate.rate(at),
            last_timestamp_ms=self.last_timestamp_ms,
            counters=self._counters(),
            edge_latencies=self._edge_latency.samples(at),
            internal_latencies=self._internal_latency.samples(at),
            refused_age_s=None if self.last_refused_mono is None else max(0.0, now - self.last_refused_mono),
            refused_rate_hz=refused_rate(
                self.last_refused_mono, self._refused_rate, at, self.thresholds.window_s
            ),
        )


# How many ids of devices not tracked, all of whose messages were refused so far, FleetHealth keeps for the
# console (the most recent): garbage under invented ids must not grow it.
MAX_UNHEARD = 64
# ... beside those whose messages were refused for their calibration (core.telemetry's
# RejectReason.CALIBRATION_REFUSED) while they are held (FleetHealth.hold), whatever comes: only the arms held
# by a refused calibration file now get that, so they are few; pushed out by 64 others, a held arm publishing
# was said to have sent nothing.
HELD_REASON = "calibration_refused"


@dataclass(slots=True)
class Unheard:
    """A device not tracked (no valid message yet) whose messages were refused: how many, the last reason,
    and when the last of them came (the fleet's monotonic clock)."""

    rejected: int
    reason: str
    last_mono: float


class FleetHealth:
    """Health of every device: those configured (tracked from start-up, so a silent one goes OFFLINE) and
    those discovered on a fleet subscription. Rejections for a device that never sent a valid message and is
    not configured are counted under UNTRACKED, so garbage on random topics cannot grow the table without
    bound."""

    UNTRACKED = "_untracked"

    def __init__(
        self, thresholds: HealthThresholds, configured: Iterable[str] = (), clock: Clock = time.monotonic
    ) -> None:
        self.thresholds = thresholds
        self._clock = clock
        self._started = clock()
        self.started = self._started
        self.configured: tuple[str, ...] = tuple(configured)
        self._configured = frozenset(self.configured)
        self.devices: dict[str, DeviceHealth] = {}
        self.untracked_rejected: Counter[str] = Counter()
        # The devices behind those untracked rejections, most recent last (MAX_UNHEARD of them): an arm whose
        # every message is refused has no card, and the Fleet page otherwise said no arm was heard at all.
        self.unheard: OrderedDict[str, Unheard] = OrderedDict()
        # The ids held now by a refused calibration (`hold`), whose rows refused for HELD_REASON are kept past
        # MAX_UNHEARD; None until told, when every such row is (a restarted worker takes back its checkpoint
        # before its calibrations come).
        self._held: frozenset[str] | None = None
        for device in self.configured:
            self.device(device)
        # Not configured, not heard since the start, but with alarms kept over a restart (`keep`).
        self._kept: set[str] = set()

    def device(self, device_id: str) -> DeviceHealth:
        health = self.devices.get(device_id)
        if health is None:
            self.unheard.pop(device_id, None)
            health = DeviceHealth(device_id, self.thresholds, self._clock, since=self._started)
            self.devices[device_id] = health
        return health

    def get(self, device_id: str) -> DeviceHealth | None:
        return self.devices.get(device_id)

    def keep(self, device_id: str) -> DeviceHealth:
        """List a device whose alarms were kept over a restart, though it is neither configured nor heard
        since: silent since the start, like a configured one, so a person can see its alarms, acknowledge
        them or forget the arm, rather than find them only in /alarms until the arm publishes again."""
        self._kept.add(device_id)
        return self.device(device_id)

    @property
    def kept(self) -> tuple[str, ...]:
        """The devices listed for their kept alarms (`keep`), so a mirror started again lists them too."""
        return tuple(sorted(self._kept))

    def forget(self, device_id: str) -> DeviceHealth | None:
        """Stop tracking a device that is not configured (an operator retired it); its health record, or None
        for a device not tracked. A configured device stays: the config says it is expected."""
        if device_id in self.configured:
            raise ValueError(f"{device_id} is configured (telemetry.devices): it cannot be forgotten")
        self._kept.discard(device_id)
        return self.devices.pop(device_id, None)

    def shown(self, device_id: str, health: DeviceHealth) -> bool:
        """Whether readers list the device: configured (expected, so shown even silent) or with something
        counted. A discovered arm gets its record when its first valid message is decoded and that message is
        counted a stage later (service.mirror); listed in between, it read OFFLINE with nothing received."""
        return bool(
            health.received
            or health.rejected
            or health.errors
            or health.overwritten
            or device_id in self._configured
            or device_id in self._kept
        )

    def listed(self) -> list[str]:
        """The ids readers list (`shown`), in table order."""
        return [device for device, health in self.devices.items() if self.shown(device, health)]

    def record_rejected(self, device_id: str | None, reason: str, recv_mono: float | None = None) -> None:
        health = self.devices.get(device_id) if device_id is not None else None
        if health is None:
            self.untracked_rejected[str(reason)] += 1
            if device_id is not None:
                self._unheard(device_id, str(reason))
        else:
            health.record_rejected(reason, recv_mono)

    def _unheard(self, device_id: str, reason: str) -> None:
        now = self._clock()
        seen = self.unheard.get(device_id)
        if seen is None:
            self.unheard[device_id] = Unheard(1, reason, now)
            self._trim_unheard()
            return
        seen.rejected, seen.reason, seen.last_mono = seen.rejected + 1, reason, now
        self.unheard.move_to_end(device_id)

    def hold(self, devices: Iterable[str]) -> None:
        """The ids held now by a refused calibration (the decoder's calibration problems). Only they keep
        their refused rows past MAX_UNHEARD: exempt for good, an id whose file was removed, or refused since
        for another reason, stayed so, and the exempt rows grew with every id ever held."""
        self._held = frozenset(devices)
        self._trim_unheard()

    def _trim_unheard(self) -> None:
        held = self._held
        others = [
            device
            for device, seen in self.unheard.items()
            if seen.reason != HELD_REASON or (held is not None and device not in held)
        ]
        for device in others[: max(0, len(others) - MAX_UNHEARD)]:
            del self.unheard[device]

    def restore_unheard(self, rows: Iterable[tuple[str, Unheard]]) -> None:
        """Take back a previous process's `unheard` (oldest first; a restarted worker, before any message), so
        a held arm's refused messages are not counted from zero again. A device tracked here is left out."""
        for device_id, seen in rows:
            if device_id in self.devices or device_id in self.unheard:
                continue
            self.unheard[device_id] = seen
        self._trim_unheard()

    def statuses(self, now: float | None = None, *, heard_only: bool = False) -> dict[str, DeviceStatus]:
        """The status of each device. `heard_only` keeps the devices heard from (a decoded message), for the
        status events: a configured device not yet heard from counts as silent since start-up, so its status
        says nothing of its own (the health check still wants it: an arm expected and silent is OFFLINE)."""
        now = self._clock() if now is None else now
        return {
            device: health.status(now)
            for device, health in self.devices.items()
            if (health.last_message_mono is not None if heard_only else self.shown(device, health))
        }

    def rates(self, now: float | None = None) -> dict[str, float]:
        """The valid messages per second of each device heard from (for service.events.RateWatch)."""
        now = self._clock() if now is None else now
        return {
            device: health.rate_hz(now)
            for device, health in self.devices.items()
            if health.last_message_mono is not None
        }

    def clock_offsets(self, now: float | None = None) -> dict[str, float]:
        """Each device's `clock_offset`, of those with one in the window (for service.events.ClockWatch)."""
        now = self._clock() if now is None else now
        offsets = ((device, health.clock_offset(now)) for device, health in self.devices.items())
        return {device: offset for device, offset in offsets if offset is not None}

    def offline_configured(self, now: float | None = None) -> list[str]:
        now = self._clock() if now is None else now
        return [d for d in self.configured if self.devices[d].status(now) is DeviceStatus.OFFLINE]

    def snapshot(self, now: float | None = None) -> dict[str, HealthSnapshot]:
        now = self._clock() if now is None else now
        return {
            device: health.snapshot(now)
            for device, health in sorted(self.devices.items())
            if self.shown(device, health)
        }

    def readings(self, now: float | None = None, behind_s: float = 0.0) -> dict[str, HealthReading]:
        """`snapshot` as readings, for a reader that holds the worker's lock (`HealthReading`, `behind_s`)."""
        now = self._clock() if now is None else now
        return {
            device: health.reading(now, behind_s)
            for device, health in sorted(self.devices.items())
            if self.shown(device, health)
        }
