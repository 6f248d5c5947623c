"""Estimated message loss per device, from the gaps between edge timestamps.

QoS 0 telemetry that a broker discards (IoT Core drops whatever exceeds 100 publishes per second on one
connection, silently) leaves no trace at the receiver except holes in each device's sequence of samples. The
edge stamps each sample when it takes it, at a fixed period, so a device's timestamps sit on a grid: the
period is the largest step of which (almost) every gap between consecutive samples is a whole multiple, and a
gap of n periods means n - 1 samples that never arrived. That works while most messages are lost too (gaps of
3, 7, 12 periods still share the step), needs no sequence number the edge does not send, and does not care
about the offset of the edge clock, only about its rate.

Each gap is rounded to whole periods on its own, so the jitter of the edge clock and a small error in the
period never add up over a long run. Until the period rests on a full history of gaps, the device's first
gaps are kept and recounted with every better estimate, so a rough early period leaves no error behind; when
a settled period moves by more than a quarter (the edge was reconfigured), the newest gaps that fit the new
one are recounted with it. A gap longer than `outage_s` is a pause (the arm was off, or the device was
OFFLINE by the health rules), not loss; five messages in a row further back than `reorder_s` are an edge
clock reset (a new timeline, nothing counted), while other steps back are late deliveries that fill a hole
counted before. Duplicates of a recent timestamp are ignored. A message the decoder rejected still arrived,
so each rejection for the device offsets one missing sample.

What this cannot see: a device none of whose messages arrive, and a loss pattern locked in phase with the
device (every tenth sample passing, always) looks like a device publishing ten times slower. The optional
nominal period (the `[health] expected_rate_hz` setting) resolves the second: when every gap is a whole
multiple of it, it is taken as the period.

Pure bookkeeping with an injected monotonic clock (used only for the recent window), like twin.core.health:
not thread-safe by itself; the agent updates it from one thread and reads it under its lock.
"""

from __future__ import annotations

import itertools
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

Clock = Callable[[], float]
# DeviceLoss.state(): plain values only (numbers, None and tuples of them), so it pickles without a call into
# Python per object. In order: nominal, outage and reorder ms, window s, gaps, new gaps, settle at, period ms,
# early gaps, early missing, missing, recent timestamps, jumps, jump fills, first, last, received,
# duplicates, segments, rejected, window samples.
LossState = tuple[
    float | None, float, float, float, tuple[int, ...], int, int, float | None, tuple[int, ...] | None,
    int, int, tuple[int, ...], int, int, int | None, int, int, int, int, int,
    tuple[tuple[float, int, int], ...],
]  # fmt: skip

# Gaps kept for the period estimate. Once it is settled it is recomputed every GAP_HISTORY new gaps (tens of
# microseconds each, so well under one per message); before that at 1, 2, 4, 8 and 16 gaps.
GAP_HISTORY = 64
# A gap fits a period p when it is within this share of p of a whole multiple of p (timestamps are sampled on
# the edge's grid, so the jitter of one sample does not add up over long gaps). A random gap fits with odds
# 2 * FIT_TOLERANCE, so FIT_SHARE of 64 gaps fitting by chance is out of the question.
FIT_TOLERANCE = 0.25
# This share of the recent gaps must fit a period for it to be believed (outliers are delayed samples).
FIT_SHARE = 0.9
# The candidate periods are a base gap divided by 1, 2, 3, ...: the median of the gaps near the shortest
# ones (up to 1.5 x a low quantile), so one early-delivered outlier does not make every normal gap look like
# several periods and a jittery edge clock still yields its mean step.
BASE_QUANTILE = 0.1
MAX_DIVISOR = 64
# The fastest edge this recognises (100 Hz); gaps on a finer grid leave the period unknown (no loss counted).
MIN_PERIOD_MS = 10.0
# A settled period estimate that moves by more than this share means the edge's rate was changed; smaller
# moves are averaged in with this weight.
PERIOD_CHANGE = 0.25
PERIOD_SMOOTHING = 0.2
# After a speed-up, this many gaps in a row that fit the old period mark the time before the change.
CHANGE_RUN = 8
# This many messages in a row further back than reorder_s mean the edge clock jumped back; fewer are late
# deliveries (a shared subscription spreads one device over several connections, which reorders).
CLOCK_RESET_MESSAGES = 5
# Duplicate detection: the last this many timestamps.
RECENT_TIMESTAMPS = 32
# The recent window is sampled at most this often.
WINDOW_BUCKET_S = 1.0
# "losing": over the recent window at least this many samples and this share of the expected were lost.
LOSING_MIN_LOST = 2
LOSING_RATIO = 0.01
# A device losing now whose newest this many gaps each span the same whole number (2 or more) of periods is
# "steady": an edge slower than [health] expected_rate_hz, or a loss locked in phase with it, which the
# timestamps cannot tell apart (the edge sends no sequence number). Random loss of any share leaves gaps of
# mixed lengths: the odds that 32 in a row agree by chance are nil.
STEADY_GAPS = 32
# ... and whose recent loss ratio is within this of 1 - 1/k for gaps of k periods: a 10 Hz arm with every
# other message rejected (each offsets a hole) has gaps of 2 periods and almost no loss, not a 5 Hz edge.
STEADY_RATIO_TOLERANCE = 0.05


# Spreads the moments many devices settle their estimates (a prime step, so consecutive devices land far
# apart); their re-estimates every GAP_HISTORY gaps after that stay spread.
_STAGGER = itertools.count(0, 37)


def _fits(gap: float, period: float) -> bool:
    multiple = round(gap / period)
    return multiple >= 1 and abs(gap - multiple * period) <= FIT_TOLERANCE * period


def _share_fitting(gaps: Sequence[float], period: float) -> float:
    tolerance = FIT_TOLERANCE * period
    fitting = 0
    for g in gaps:
        m = round(g / period)
        if m >= 1 and abs(g - m * period) <= tolerance:
            fitting += 1
    return fitting / len(gaps)


def _refined(gaps: Sequence[float], period: float) -> float:
    """Least squares over the gaps that fit `period`: sum of gaps / sum of their multiples."""
    tolerance = FIT_TOLERANCE * period
    total: float = 0
    multiples = 0
    for g in gaps:
        m = round(g / period)
        if m >= 1 and abs(g - m * period) <= tolerance:
            total += g
            multiples += m
    return total / multiples if multiples else period


def _fitted(gaps: Sequence[float], candidate: float) -> float | None:
    """`candidate` refined on the short gaps first (a small error in it grows with the multiple), then on
    all; None unless FIT_SHARE of the gaps fit the result."""
    short = [g for g in gaps if g <= 4.5 * candidate]
    period = _refined(short, candidate) if short else candidate
    period = _refined(gaps, period)
    return period if _share_fitting(gaps, period) >= FIT_SHARE else None


def _still_fits(gaps: Sequence[float], period: float) -> bool:
    """True when `period` still explains the gaps: FIT_SHARE of them fit it, and most are exactly one period
    (so it is not a divisor of the true period, as after the edge slowed down)."""
    tolerance = FIT_TOLERANCE * period
    fitting = single = 0
    for g in gaps:
        m = round(g / period)
        if m >= 1 and abs(g - m * period) <= tolerance:
            fitting += 1
            single += m == 1
    return fitting >= FIT_SHARE * len(gaps) and single * 2 > len(gaps)


def estimate_period_ms(
    gaps: Sequence[float], nominal_ms: float | None = None, previous_ms: float | None = None
) -> float | None:
    """The sampling period (ms) the positive `gaps` are whole multiples of, or None when none fits.

    Candidates are a base gap divided by 1, 2, 3, ...; the largest that FIT_SHARE of the gaps fit, refined by
    least squares (sum of gaps / sum of multiples, which recovers a period off the whole milliseconds), wins.
    A `previous_ms` estimate that still explains the gaps is only refined: a fleet that started together
    re-estimates together, and the full search costs several times as much.
    """
    gaps = [g for g in gaps if g > 0]
    if not gaps:
        return None
    if previous_ms is not None and _still_fits(gaps, previous_ms):
        return _refined(gaps, previous_ms)
    ordered = sorted(gaps)
    low = ordered[int(BASE_QUANTILE * (len(ordered) - 1))]
    near = [g for g in ordered if g <= 1.5 * low]
    base = near[len(near) // 2]
    best = None
    for k in range(1, MAX_DIVISOR + 1):
        if base / k < MIN_PERIOD_MS:
            break
        best = _fitted(gaps, base / k)
        if best is not None:
            break
    if nominal_ms is not None and (best is None or best > (1.0 + PERIOD_CHANGE) * nominal_ms):
        # Every gap a whole number of nominal periods: a loss pattern locked in phase with the device, not
        # a slower device (which the health thresholds would call STALE anyway).
        best = _fitted(gaps, nominal_ms) or best
    return best


@dataclass(frozen=True, slots=True)
class LossSnapshot:
    """One device's loss estimate at one instant, as /state and /metrics publish it; `losing` is true while
    the recent window saw losses (docs/agent.md, "Loss")."""

    period_s: float | None = None
    received: int = 0
    lost: int = 0
    loss_ratio: float = 0.0
    recent_lost: int = 0
    recent_loss_ratio: float = 0.0
    losing: bool = False
    # While losing: the whole number of periods each of its newest STEADY_GAPS gaps spans, all alike, its
    # recent loss about 1 - 1/k (None: they differ, it is not losing, or its loss disagrees). 2 for an edge
    # at 5 Hz against expected_rate_hz = 10.
    steady_periods: int | None = None


@dataclass(frozen=True, slots=True)
class FleetLoss:
    """The fleet's totals: lost / (received + lost) over every device, and how many devices lose data now."""

    received: int = 0
    lost: int = 0
    loss_ratio: float = 0.0
    devices_losing: int = 0


class DeviceLoss:
    """Loss estimate of one device. `observe` every valid message's edge timestamp, `record_rejected` every
    rejected message that carried the device's topic."""

    def __init__(
        self,
        *,
        nominal_period_s: float | None = None,
        outage_s: float = 10.0,
        reorder_s: float = 2.0,
        window_s: float = 10.0,
        clock: Clock = time.monotonic,
    ) -> None:
        if outage_s <= 0 or reorder_s <= 0 or window_s <= 0:
            raise ValueError(
                f"outage_s ({outage_s}), reorder_s ({reorder_s}) and window_s ({window_s}) must be positive"
            )
        self._nominal_ms = None if nominal_period_s is None else nominal_period_s * 1000.0
        self._outage_ms = outage_s * 1000.0
        self._reorder_ms = reorder_s * 1000.0
        self._window_s = window_s
        self._clock = clock
        # The newest GAP_HISTORY gaps estimate the period; twice as many are kept so a rate change, which an
        # estimate may take up to GAP_HISTORY more gaps to see, is recounted back to where it happened.
        self._gaps: deque[int] = deque(maxlen=2 * GAP_HISTORY)
        self._new_gaps = 0
        # The estimate settles after GAP_HISTORY gaps and up to half as many again, by device: devices that
        # started together would otherwise settle, and then re-estimate every GAP_HISTORY gaps, in the same
        # instant (a 1,000-arm fleet's estimates cost the worker 50 ms at once).
        self._settle_at = GAP_HISTORY + next(_STAGGER) % (GAP_HISTORY // 2)
        self._period_ms: float | None = None
        # Until the period rests on a full history, the gaps seen so far are kept and recounted with each
        # better estimate; after that each gap is counted once, when it arrives.
        self._early: list[int] | None = []
        self._early_missing = 0
        self._missing = 0
        self._recent: deque[int] = deque(maxlen=RECENT_TIMESTAMPS)
        self._recent_set: set[int] = set()
        self._jumps = 0  # consecutive messages further back than reorder_s, and the holes they filled
        self._jump_fills = 0
        self._first: int | None = None  # current segment's earliest and latest timestamp
        self._last = 0
        self.received = 0
        self.duplicates = 0
        self.segments = 0
        self.rejected = 0
        self._window: deque[tuple[float, int, int]] = deque()  # (when, received, lost) samples

    # -- updates --------------------------------------------------------------------------------------------

    def observe(self, timestamp_ms: int, now: float | None = None) -> None:
        """One valid message's edge timestamp, in arrival order (duplicates and late ones included); `now`
        (the injected clock's time, read when None) places it in the recent window."""
        if timestamp_ms in self._recent_set:
            self.duplicates += 1
            return
        recent = self._recent
        if len(recent) == recent.maxlen:
            self._recent_set.discard(recent[0])
        recent.append(timestamp_ms)
        self._recent_set.add(timestamp_ms)
        self.received += 1

        first = self._first
        if first is None:
            self._open(timestamp_ms)
        elif timestamp_ms > self._last:
            gap = timestamp_ms - self._last
            self._last = timestamp_ms
            if gap > self._outage_ms:
                self._open(timestamp_ms)  # a pause (the arm was off), not loss
            elif self._early is None and self._new_gaps + 1 < GAP_HISTORY:
                # _count_gap's settled case inline (every message of a settled device comes here): the gap
                # kept, its missing samples counted with the period, no re-estimate due yet.
                self._gaps.append(gap)
                self._new_gaps += 1
                period = self._period_ms
                if period is not None:
                    missing = round(gap / period) - 1
                    if missing > 0:
                        self._missing += missing
            else:
                self._count_gap(gap)
        else:
            self._late(timestamp_ms, first)
            self._sample_window(now)
            return
        self._jumps = self._jump_fills = 0
        if now is None:
            now = self._clock()
        window = self._window
        if not window or now - window[-1][0] >= WINDOW_BUCKET_S:
            self._sample_window(now)

    def _late(self, timestamp_ms: int, first: int) -> None:
        """A message older than the newest one: a late delivery that fills a hole an earlier gap counted,
        unless CLOCK_RESET_MESSAGES in a row are all further back than `reorder_s`: then the edge clock jumped
        back, those were a new timeline, and a new segment starts (their hole fills are undone)."""
        if self._last - timestamp_ms > self._reorder_ms:
            self._jumps += 1
            if self._jumps >= CLOCK_RESET_MESSAGES:
                self._missing += self._jump_fills
                self._jumps = self._jump_fills = 0
                self._open(timestamp_ms)
            elif timestamp_ms > first:
                self._missing -= 1
                self._jump_fills += 1
            return
        if timestamp_ms > first:
            self._missing -= 1
        else:
            # Late and older than anything in this segment: the segment reaches back to it.
            self._first = timestamp_ms
            self._count_gap(first - timestamp_ms)

    def record_rejected(self) -> None:
        """A message for this device arrived but was rejected: its sample is not lost in transit. Before the
        first valid sample there is no hole to fill (units=auto rejects a new arm's first messages)."""
        if self._first is not None:
            self.rejected += 1

    def _open(self, timestamp_ms: int) -> None:
        self._first = self._last = timestamp_ms
        self.segments += 1

    def _count_gap(self, gap: int) -> None:
        self._gaps.append(gap)
        self._new_gaps += 1
        period = self._period_ms
        missing = 0 if period is None else max(0, round(gap / period) - 1)
        early = self._early
        if early is not None:
            early.append(gap)
            self._early_missing += missing
            # 1, 2, 4, 8, 16 gaps (a rough period early, corrected at the settling recount), then settled.
            n = len(early)
            if (n & (n - 1) == 0 and n < GAP_HISTORY // 2) or n == self._settle_at:
                self._reestimate()
            return
        self._missing += missing
        if self._new_gaps >= GAP_HISTORY:
            self._reestimate()

    def _reestimate(self) -> None:
        self._new_gaps = 0
        recent = list(self._gaps)[-GAP_HISTORY:]
        period = estimate_period_ms(recent, self._nominal_ms, self._period_ms)
        old = self._period_ms
        early = self._early
        if (
            early is None
            and period is not None
            and old is not None
            and abs(period - old) <= PERIOD_CHANGE * old
        ):
            # Settled: average the windows, since 64 jittery gaps pin the period to about a percent only.
            period = old + PERIOD_SMOOTHING * (period - old)
        if period is not None:  # gaps that fit nothing (an irregular or stalled edge) keep the last period
            self._period_ms = period
        if early is not None:
            p = self._period_ms
            self._early_missing = 0 if p is None else sum(max(0, round(g / p) - 1) for g in early)
            if len(early) == self._settle_at:
                # The estimate rests on a full history: settle the early gaps, count the rest as they come.
                self._missing += self._early_missing
                self._early_missing = 0
                self._early = None
        elif period is not None and old is not None and abs(period - old) > PERIOD_CHANGE * old:
            # The edge's rate changed: the gaps since the change were counted with the old period; count them
            # again with the new one.
            for gap in self._since_change(period, old):
                self._missing += max(0, round(gap / period) - 1) - max(0, round(gap / old) - 1)

    def _since_change(self, period: float, old: float) -> list[int]:
        """The newest gaps from the rate change on. Walking back, a gap that does not fit the new period is
        from before the change. After a speed-up every old gap fits the new period too (as a multiple), so
        there the change is the earliest gap that does not fit the old period, before a run of CHANGE_RUN
        that all do (a lost sample after the change can also make a gap the old period fits)."""
        gaps = list(self._gaps)
        if period >= old:
            start = len(gaps)
            while start and _fits(gaps[start - 1], period):
                start -= 1
            return gaps[start:]
        start = len(gaps)
        run = 0
        for i in range(len(gaps) - 1, -1, -1):
            gap = gaps[i]
            if not _fits(gap, period):
                break
            if _fits(gap, old):
                run += 1
                if run >= CHANGE_RUN:
                    break
            else:
                run = 0
                start = i
        return gaps[start:]

    # -- checkpoints ----------------------------------------------------------------------------------------

    def state(self) -> LossState:
        """Everything the estimate rests on, as one tuple of plain values: a worker's checkpoint carries it
        for a thousand arms a second, and pickling the object itself (its deques and set, through the
        object protocol) cost several times as much. `from_state` builds the estimator back."""
        early = self._early
        return (
            self._nominal_ms,
            self._outage_ms,
            self._reorder_ms,
            self._window_s,
            tuple(self._gaps),
            self._new_gaps,
            self._settle_at,
            self._period_ms,
            None if early is None else tuple(early),
            self._early_missing,
            self._missing,
            tuple(self._recent),
            self._jumps,
            self._jump_fills,
            self._first,
            self._last,
            self.received,
            self.duplicates,
            self.segments,
            self.rejected,
            tuple(self._window),
        )

    @classmethod
    def from_state(cls, state: LossState, clock: Clock = time.monotonic) -> DeviceLoss:
        """The estimator `state()` was taken of, reading `clock` from now on (a checkpoint only crosses
        between processes of one host, which share the monotonic clock its window is on)."""
        (
            nominal_ms, outage_ms, reorder_ms, window_s, gaps, new_gaps, settle_at, period_ms, early,
            early_missing, missing, recent, jumps, jump_fills, first, last,
            received, duplicates, segments, rejected, window,
        ) = state  # fmt: skip
        loss = cls.__new__(cls)
        loss._nominal_ms = nominal_ms
        loss._outage_ms = outage_ms
        loss._reorder_ms = reorder_ms
        loss._window_s = window_s
        loss._clock = clock
        loss._gaps = deque(gaps, maxlen=2 * GAP_HISTORY)
        loss._new_gaps = new_gaps
        loss._settle_at = settle_at
        loss._period_ms = period_ms
        loss._early = None if early is None else list(early)
        loss._early_missing = early_missing
        loss._missing = missing
        loss._recent = deque(recent, maxlen=RECENT_TIMESTAMPS)
        loss._recent_set = set(recent)
        loss._jumps = jumps
        loss._jump_fills = jump_fills
        loss._first = first
        loss._last = last
        loss.received = received
        loss.duplicates = duplicates
        loss.segments = segments
        loss.rejected = rejected
        loss._window = deque(window)
        return loss

    # -- readings -------------------------------------------------------------------------------------------

    @property
    def period_s(self) -> float | None:
        """The estimated sampling period, or None until gaps fit one."""
        return None if self._period_ms is None else self._period_ms / 1000.0

    @property
    def lost(self) -> int:
        """Samples estimated missing, less those that arrived and were rejected."""
        return max(0, self._missing + self._early_missing - self.rejected)

    def _sample_window(self, now: float | None = None) -> None:
        if now is None:
            now = self._clock()
        window = self._window
        if not window or now - window[-1][0] >= WINDOW_BUCKET_S:
            window.append((now, self.received, self.lost))
            horizon = now - self._window_s - WINDOW_BUCKET_S
            while len(window) > 2 and window[1][0] <= horizon:
                window.popleft()

    def recent(self, now: float | None = None) -> tuple[int, int]:
        """(received, lost) over the last `window_s` seconds (at WINDOW_BUCKET_S resolution)."""
        now = self._clock() if now is None else now
        horizon = now - self._window_s
        base = None
        for sample in self._window:
            if sample[0] >= horizon:
                base = sample
                break
        if base is None:
            return 0, 0
        return self.received - base[1], max(0, self.lost - base[2])

    def snapshot(self, now: float | None = None) -> LossSnapshot:
        """The estimate now (`now` on the injected clock; None reads it)."""
        received, lost = self.received, self.lost
        recent_received, recent_lost = self.recent(now)
        recent_expected = recent_received + recent_lost
        recent_ratio = recent_lost / recent_expected if recent_expected else 0.0
        losing = recent_lost >= LOSING_MIN_LOST and recent_ratio >= LOSING_RATIO
        return LossSnapshot(
            period_s=self.period_s,
            received=received,
            lost=lost,
            loss_ratio=lost / (received + lost) if received + lost else 0.0,
            recent_lost=recent_lost,
            recent_loss_ratio=recent_ratio,
            losing=losing,
            steady_periods=self._steady_with(recent_ratio) if losing else None,
        )

    def _steady_with(self, recent_ratio: float) -> int | None:
        periods = self.steady_periods()
        if periods is None or abs(recent_ratio - (1.0 - 1.0 / periods)) > STEADY_RATIO_TOLERANCE:
            return None
        return periods

    def steady_periods(self) -> int | None:
        """The whole number of periods, 2 or more, that each of the newest STEADY_GAPS gaps spans when they
        all span the same (LossSnapshot.steady_periods); else None."""
        period, gaps = self._period_ms, self._gaps
        if period is None or len(gaps) < STEADY_GAPS:
            return None
        periods = round(gaps[-1] / period)
        if periods < 2:
            return None
        for gap in itertools.islice(reversed(gaps), STEADY_GAPS):
            if abs(gap - periods * period) > FIT_TOLERANCE * period:
                return None
        return periods


def fleet_loss(devices: Iterable[LossSnapshot]) -> FleetLoss:
    """The fleet's totals from its devices' snapshots (each device counted once, whichever worker has it)."""
    received = lost = losing = 0
    for snap in devices:
        received += snap.received
        lost += snap.lost
        losing += snap.losing
    return FleetLoss(
        received=received,
        lost=lost,
        loss_ratio=lost / (received + lost) if received + lost else 0.0,
        devices_losing=losing,
    )
