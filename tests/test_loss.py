"""Loss estimation from edge-timestamp gaps: streams with known drops, pure, on an injected clock."""

from __future__ import annotations

import random

import pytest
from twin.core.loss import DeviceLoss, FleetLoss, estimate_period_ms, fleet_loss

T0 = 1_706_000_000_000
PERIOD_MS = 100


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def stream(
    n: int, *, drop: float = 0.0, jitter_ms: int = 0, seed: int = 1, period_ms: int = PERIOD_MS
) -> tuple[list[int], int]:
    """Edge timestamps of n samples with random drops; returns (delivered, drops between the first and last
    delivered sample, which is what any receiver can know of)."""
    rng = random.Random(seed)
    kept = [k for k in range(n) if rng.random() >= drop]
    visible_drops = (kept[-1] - kept[0] + 1) - len(kept)
    return [T0 + k * period_ms + rng.randint(-jitter_ms, jitter_ms) for k in kept], visible_drops


def feed(timestamps: list[int], clock: Clock | None = None, **kw: float) -> DeviceLoss:
    clock = clock or Clock()
    loss = DeviceLoss(clock=clock, **kw)
    for ts in timestamps:
        clock.now = (ts - T0) / 1000.0
        loss.observe(ts)
    return loss


@pytest.mark.parametrize(
    ("drop", "jitter_ms", "tolerance"),
    [
        (0.0, 0, 0),
        (0.0, 15, 0),
        (0.01, 3, 0),
        (0.2, 3, 1),
        (0.2, 15, 0.01),
        (0.5, 3, 0.01),
        (0.9, 3, 0.01),
        (0.95, 3, 0.01),  # IoT Core at 20x its per-connection budget
    ],
)
def test_known_drops_are_estimated(drop: float, jitter_ms: int, tolerance: float) -> None:
    timestamps, truth = stream(3000, drop=drop, jitter_ms=jitter_ms)
    loss = feed(timestamps)
    assert loss.period_s == pytest.approx(0.1, rel=0.01)
    allowed = tolerance if tolerance >= 1 else tolerance * 3000
    assert abs(loss.lost - truth) <= allowed, (loss.lost, truth)
    assert loss.received == len(timestamps)
    snap = loss.snapshot()
    assert snap.loss_ratio == pytest.approx(loss.lost / (loss.lost + loss.received))


def test_duplicates_are_ignored_and_late_messages_fill_their_hole() -> None:
    timestamps, truth = stream(1000, drop=0.1)
    rng = random.Random(5)
    delivered = []
    for ts in timestamps:
        delivered.append(ts)
        if rng.random() < 0.1:
            delivered.append(ts)  # a duplicate
    for i in range(0, len(delivered) - 1, 7):
        delivered[i], delivered[i + 1] = delivered[i + 1], delivered[i]  # reordered neighbours
    loss = feed(delivered)
    assert loss.lost == truth
    assert loss.duplicates > 50
    assert loss.received == len(timestamps)


def test_a_pause_longer_than_the_outage_is_not_loss() -> None:
    first, _ = stream(100)
    second = [ts + 60_000 for ts in first]  # the arm was off for a minute
    loss = feed(first + second, outage_s=10.0)
    assert loss.lost == 0
    assert loss.segments == 2


def test_an_edge_clock_jumping_back_starts_a_new_timeline() -> None:
    first, _ = stream(100)
    rebooted = [ts - 3_600_000 for ts in first]  # an edge without NTP reboots an hour back
    loss = feed(first + rebooted[::2])  # and from then on half the messages are lost
    assert loss.segments == 2
    # The new timeline is recognised on its fifth message (fewer could be late deliveries); its first four
    # gaps (4 lost) go uncounted, the remaining 45 are.
    assert loss.lost == 45


def test_deliveries_seconds_late_are_not_a_clock_reset() -> None:
    # A shared subscription spreads one device over several connections: some messages arrive seconds late.
    timestamps, truth = stream(600, drop=0.1)
    rng = random.Random(8)
    delivered = sorted(timestamps, key=lambda ts: ts + (rng.random() < 0.05) * rng.uniform(2500, 4000))
    loss = feed(delivered)
    assert loss.segments == 1
    assert loss.lost == truth


def test_a_changed_rate_is_followed() -> None:
    rng = random.Random(3)
    ts, timestamps, dropped = T0, [], 0
    for k in range(1000):
        ts += 100 if k < 500 else 200  # the edge is reconfigured from 10 Hz to 5 Hz
        if rng.random() < 0.1 and 10 < k < 990:
            dropped += 1
            continue
        timestamps.append(ts)
    loss = feed(timestamps)
    assert loss.period_s == pytest.approx(0.2, rel=0.01)
    # A gap of two 10 Hz periods just before the change also fits 5 Hz: it may be recounted as no loss.
    assert dropped - 1 <= loss.lost <= dropped


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize(("before", "after"), [(100, 200), (200, 100)], ids=["slowed down", "sped up"])
def test_a_changed_rate_is_recounted_from_the_change_on(before: int, after: int, seed: int) -> None:
    # Whenever the change falls between two estimates (the estimators of a fleet do not run in step), the
    # gaps since the change are recounted with the new period, and none from before it. After a speed-up
    # every old gap is also a whole number of new periods, which must not be counted as loss.
    rng = random.Random(seed)
    ts, timestamps, dropped = T0, [], 0
    for k in range(1000):
        ts += before if k < 500 else after
        if rng.random() < 0.1 and 10 < k < 990:
            dropped += 1
            continue
        timestamps.append(ts)
    loss = feed(timestamps)
    assert loss.period_s == pytest.approx(after / 1000, rel=0.01)
    # A gap of one old period just after a speed-up is also one lost new sample: it may go uncounted.
    assert dropped - 2 <= loss.lost <= dropped, (loss.lost, dropped)


def test_a_loss_locked_in_phase_needs_the_nominal_rate() -> None:
    # Every tenth sample passes, always: by the gaps alone a 1 Hz device.
    every_tenth = [T0 + k * PERIOD_MS for k in range(0, 2000, 10)]
    assert feed(every_tenth).lost == 0
    loss = feed(every_tenth, nominal_period_s=0.1)
    assert loss.period_s == pytest.approx(0.1)
    assert loss.lost == 1990 - 199


@pytest.mark.parametrize("jitter_ms", [0, 3])
def test_an_edge_slower_than_the_nominal_rate_reads_as_steady_gaps_and_random_loss_does_not(
    jitter_ms: int,
) -> None:
    # A walk's edge at 5 Hz against expected_rate_hz = 10 showed a steady 50 % loss, and the page could not
    # tell it from random loss of the same share: each gap is two periods, every time.
    slow, _ = stream(600, jitter_ms=jitter_ms, period_ms=2 * PERIOD_MS)
    assert feed(slow, nominal_period_s=0.1).snapshot().steady_periods == 2
    halved, _ = stream(1200, drop=0.5, jitter_ms=jitter_ms)
    random_loss = feed(halved, nominal_period_s=0.1).snapshot()
    assert random_loss.losing and random_loss.steady_periods is None
    # Not losing: nothing to explain.
    whole, _ = stream(600, jitter_ms=jitter_ms)
    assert feed(whole, nominal_period_s=0.1).snapshot().steady_periods is None


def test_gaps_of_two_periods_left_by_rejected_messages_are_not_steady_loss() -> None:
    # A review: a 10 Hz arm with every other message rejected, and a few lost, read as "likely publishes at
    # ~5 Hz" (gaps of 2 periods) at a recent loss of 6 %: each rejection offsets its hole.
    clock = Clock()
    loss = DeviceLoss(clock=clock, nominal_period_s=0.1)
    for k in range(600):
        clock.now = k / 10
        if k % 2:
            loss.record_rejected()
        elif k not in (510, 514, 520):
            loss.observe(T0 + k * PERIOD_MS)
    snap = loss.snapshot()
    assert snap.losing and snap.recent_loss_ratio < 0.1, snap
    assert loss.steady_periods() == 2 and snap.steady_periods is None, snap


def test_rejected_messages_arrived() -> None:
    timestamps, truth = stream(500, drop=0.1)
    loss = feed(timestamps)
    for _ in range(10):
        loss.record_rejected()  # ten of the holes were messages that arrived and were refused
    assert loss.lost == truth - 10


def test_recent_window_marks_a_device_losing_data_and_clears() -> None:
    clock = Clock()
    loss = DeviceLoss(clock=clock, window_s=10.0)
    rng = random.Random(2)
    states = {}
    for k in range(600):  # 60 s at 10 Hz; samples 200..299 (20..30 s) lose half
        clock.now = k / 10
        if 200 <= k < 300 and rng.random() < 0.5:
            continue
        loss.observe(T0 + k * PERIOD_MS)
        for mark in (150, 290, 450):
            if k >= mark and mark not in states:
                states[mark] = loss.snapshot()
    assert not states[150].losing and states[150].recent_lost == 0
    assert states[290].losing and 0.3 < states[290].recent_loss_ratio < 0.7
    assert not states[450].losing  # the window moved past the losses; the total keeps them
    assert loss.snapshot().lost == states[450].lost > states[290].lost > 0


def test_fleet_ratio_sums_devices() -> None:
    clean, _ = stream(1000)
    lossy, truth = stream(1000, drop=0.3, seed=4)
    devices = [feed(clean), feed(lossy)]
    fleet = fleet_loss(d.snapshot() for d in devices)
    assert fleet.lost == truth
    assert fleet.received == len(clean) + len(lossy)
    assert fleet.loss_ratio == pytest.approx(truth / (truth + fleet.received))
    assert fleet_loss([]) == FleetLoss()


@pytest.mark.parametrize(
    ("gaps", "expected"),
    [
        ([100, 100, 101, 99, 100], 100.0),
        ([300, 700, 1200, 200, 900, 400, 1100, 500], 100.0),  # only multiples: 95 % loss
        ([33, 34, 33, 67, 33, 100], 100 / 3),  # 30 Hz, whole milliseconds
        ([1000, 1000, 1000], 1000.0),
    ],
)
def test_period_estimate(gaps: list[int], expected: float) -> None:
    assert estimate_period_ms(gaps) == pytest.approx(expected, rel=0.01)


def test_period_estimate_refuses_irregular_gaps() -> None:
    rng = random.Random(9)
    assert estimate_period_ms([rng.uniform(50, 5000) for _ in range(64)]) is None
    assert estimate_period_ms([]) is None


def _plain(value: object) -> bool:
    """Only what pickles without a call into Python: numbers, None and tuples of them."""
    if isinstance(value, tuple):
        return all(_plain(v) for v in value)
    return value is None or type(value) in (int, float)


@pytest.mark.parametrize(
    "cut",
    [
        5,  # still early: the first gaps are recounted with each better estimate
        90,  # settled
        400,  # settled, after the rate change below
    ],
)
def test_an_estimator_from_its_state_goes_on_as_the_original(cut: int) -> None:
    """A restarted worker takes each arm's estimator back from its checkpoint (`state`, `from_state`): fed
    the same messages after that, it must count exactly what the original counts."""
    rng = random.Random(cut)
    fast, _ = stream(300, drop=0.2, jitter_ms=3, seed=7)
    slow = [fast[-1] + 200 * (k + 1) for k in range(300) if rng.random() >= 0.1]  # 5 Hz from here on
    timestamps = fast + slow
    timestamps[cut + 3], timestamps[cut + 4] = timestamps[cut + 4], timestamps[cut + 3]  # one late delivery
    timestamps.insert(cut + 10, timestamps[cut + 8])  # a duplicate
    timestamps.insert(cut + 1, timestamps[cut - 2])  # and one of a message from before the checkpoint
    clock = Clock()
    original = feed(timestamps[:cut], clock)
    for _ in range(3):
        original.record_rejected()
    state = original.state()
    assert _plain(state)
    copy = DeviceLoss.from_state(state, clock)
    assert copy.state() == state
    for ts in timestamps[cut:]:
        clock.now = (ts - T0) / 1000.0
        original.observe(ts)
        copy.observe(ts)
        assert (copy.lost, copy.received, copy.duplicates) == (
            original.lost,
            original.received,
            original.duplicates,
        )
    assert copy.state() == original.state()
    assert copy.snapshot() == original.snapshot()
    assert original.period_s == pytest.approx(0.2, rel=0.01)
