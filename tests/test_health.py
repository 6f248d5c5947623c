"""Device health with a fake clock: status thresholds, age, rate, counters and latency windows."""

from __future__ import annotations

import random

import pytest
from twin.core.health import (
    MAX_UNHEARD,
    DeviceStatus,
    FleetHealth,
    HealthSnapshot,
    HealthThresholds,
    RateMeter,
    SampleWindow,
    WindowLatency,
    percentile,
)


class FakeClock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


TH = HealthThresholds(expected_rate_hz=10.0, stale_periods=3, offline_after_s=10.0, window_s=5.0)


def feed(fleet: FleetHealth, clock: FakeClock, device: str, n: int, *, dt: float = 0.1, skew_s: float = 0.0):
    """n messages at 1/dt Hz; the edge clock is the agent's wall clock shifted by skew_s, transit 20 ms."""
    health = fleet.device(device)
    for _ in range(n):
        clock.advance(dt)
        wall = 1.7e9 + clock.t
        ts_ms = round((wall - 0.020 - skew_s) * 1000)
        health.record_received()
        health.record_decoded(clock.t, wall, ts_ms)
        health.record_applied(clock.t, clock.t + 0.0005, ts_ms)


def test_untracked_refused_devices_are_kept_bounded_newest_last_and_leave_once_heard() -> None:
    # The Fleet page names an arm whose every message is refused (no card shows it); garbage under invented
    # ids must not grow what it keeps.
    clock = FakeClock()
    fleet = FleetHealth(TH, ["arm-listed"], clock=clock)
    for n in range(MAX_UNHEARD + 6):
        clock.advance(0.1)
        fleet.record_rejected(f"junk-{n:03d}", "not_json")
    assert (
        len(fleet.unheard) == MAX_UNHEARD and "junk-005" not in fleet.unheard and "junk-006" in fleet.unheard
    )
    clock.advance(1.0)
    fleet.record_rejected("junk-006", "bad_timestamp")
    assert list(fleet.unheard)[-1] == "junk-006"
    seen = fleet.unheard["junk-006"]
    assert (seen.rejected, seen.reason, seen.last_mono) == (2, "bad_timestamp", clock.t)
    fleet.record_rejected("arm-listed", "not_json")  # listed: counted on its own card
    fleet.record_rejected(None, "not_json")  # no device in the topic
    assert "arm-listed" not in fleet.unheard and len(fleet.unheard) == MAX_UNHEARD
    fleet.device("junk-006")  # its first valid message: tracked, with a card
    assert "junk-006" not in fleet.unheard


def test_a_held_arms_refused_messages_are_not_pushed_out_by_other_refused_ids() -> None:
    # A review: a held arm's "nothing has been received" is read from `unheard`, and 64 other refused ids
    # (garbage, arms over max_devices) pushed a publishing one out. Its own restarted worker keeps it too.
    clock = FakeClock()
    fleet = FleetHealth(TH, clock=clock)
    fleet.record_rejected("arm-held", "calibration_refused")
    for n in range(3 * MAX_UNHEARD):
        clock.advance(0.1)
        fleet.record_rejected(f"junk-{n:03d}", "not_json")
    assert fleet.unheard["arm-held"].rejected == 1 and len(fleet.unheard) == MAX_UNHEARD + 1
    restarted = FleetHealth(TH, clock=clock)
    restarted.restore_unheard(list(fleet.unheard.items()))
    for n in range(MAX_UNHEARD):
        restarted.record_rejected(f"more-{n:03d}", "not_json")
    assert "arm-held" in restarted.unheard and len(restarted.unheard) == MAX_UNHEARD + 1
    restarted.device("arm-held")  # its file fixed: tracked, with a card
    restarted.record_rejected("other", "not_json")
    assert "arm-held" not in restarted.unheard and len(restarted.unheard) == MAX_UNHEARD


def test_a_refused_ids_exemption_from_the_cap_lasts_only_while_it_is_held() -> None:
    # A review: exempt for good, an id whose file was removed, or refused since for another reason, stayed
    # so, and the exempt rows grew with every id ever held, in every checkpoint too.
    clock = FakeClock()
    fleet = FleetHealth(TH, clock=clock)

    def refuse(devices: list[str], reason: str = "not_json") -> None:
        for device in devices:
            clock.advance(0.1)
            fleet.record_rejected(device, reason)

    junk = [f"junk-{n:03d}" for n in range(MAX_UNHEARD)]
    fleet.hold(["arm-a", "arm-b"])
    refuse(["arm-a", "arm-b"], "calibration_refused")
    refuse(junk)
    assert {"arm-a", "arm-b"} <= set(fleet.unheard) and len(fleet.unheard) == MAX_UNHEARD + 2
    fleet.hold(["arm-a"])  # arm-b's file removed: no longer held, it goes as the oldest of the others
    assert "arm-b" not in fleet.unheard and len(fleet.unheard) == MAX_UNHEARD + 1
    refuse(["arm-a"])  # held still, but refused since for a payload it cannot read: one of the others
    refuse([f"more-{n:03d}" for n in range(MAX_UNHEARD)])
    assert "arm-a" not in fleet.unheard and len(fleet.unheard) == MAX_UNHEARD
    for n in range(3 * MAX_UNHEARD):  # ids held one after another: only the one held now is beside the cap
        fleet.hold([f"churn-{n:03d}"])
        refuse([f"churn-{n:03d}"], "calibration_refused")
        assert len(fleet.unheard) <= MAX_UNHEARD + 1
    refuse([f"last-{n:03d}" for n in range(MAX_UNHEARD)])  # churn-191, held, is the oldest row now
    # A worker started again takes back its checkpoint before its calibrations come: then as the live one.
    restarted = FleetHealth(TH, clock=clock)
    restarted.restore_unheard(list(fleet.unheard.items()))
    restarted.hold(["churn-191"])
    assert list(restarted.unheard) == list(fleet.unheard) and "churn-191" in restarted.unheard
    restarted.hold([])
    fleet.hold([])
    assert list(restarted.unheard) == list(fleet.unheard) and len(fleet.unheard) == MAX_UNHEARD


def test_a_reading_behind_its_input_keeps_the_latency_windows_of_the_messages_handled() -> None:
    # The latency windows go by receive time. Read on the clock, a worker a window (5 s) or more behind had
    # no sample left: InternalLatencyP99 went unwritten (AgentBehind, its alarm, treats that as fine) while
    # ArmsStale stays quiet by design, so a host 6 s behind paged nothing.
    clock = FakeClock()
    fleet = FleetHealth(TH, [], clock=clock)
    health = fleet.device("arm-001")
    for _ in range(10):
        clock.advance(0.1)
        wall = 1.7e9 + clock.t
        health.record_received()
        health.record_decoded(clock.t, wall, round((wall - 0.020) * 1000))
        health.record_applied(clock.t, clock.t + 6.0, round((wall - 0.020) * 1000))  # handled 6 s late
    clock.advance(6.0)  # the worker stands at the last message handled, 6 s ago
    reading = fleet.readings(clock.t, behind_s=6.0)["arm-001"].snapshot()
    assert reading.status is DeviceStatus.ONLINE
    assert reading.internal_latency_s.p99 == pytest.approx(6.0)
    assert reading.edge_clock_latency_s.samples == 10
    assert fleet.readings(clock.t + 6.0, behind_s=0.0)["arm-001"].snapshot().internal_latency_s.p99 is None


def test_statuses_heard_only_leave_out_devices_not_heard_from() -> None:
    # The status events read these: a configured arm not heard from, or one whose messages were all turned
    # away, is silent since start-up (STALE after 0.3 s) but has not arrived. The health check reads them all.
    clock = FakeClock()
    fleet = FleetHealth(TH, ["arm-001", "arm-002"], clock=clock)
    fleet.device("junk-1").record_rejected("bad_json")
    clock.advance(1.0)
    feed(fleet, clock, "arm-002", 3)
    assert fleet.statuses(heard_only=True) == {"arm-002": DeviceStatus.ONLINE}
    stale = DeviceStatus.STALE
    assert fleet.statuses() == {"arm-001": stale, "arm-002": DeviceStatus.ONLINE, "junk-1": stale}
    assert fleet.device("arm-001").status() is fleet.device("junk-1").status() is DeviceStatus.STALE


def test_thresholds_classify() -> None:
    assert TH.stale_after_s == pytest.approx(0.3)
    assert TH.classify(0.0) is DeviceStatus.ONLINE
    assert TH.classify(0.3) is DeviceStatus.ONLINE
    assert TH.classify(0.31) is DeviceStatus.STALE
    assert TH.classify(9.99) is DeviceStatus.STALE
    assert TH.classify(10.0) is DeviceStatus.OFFLINE


def test_status_follows_silence_and_recovers() -> None:
    clock = FakeClock()
    fleet = FleetHealth(TH, ["arm-001"], clock=clock)
    h = fleet.device("arm-001")
    # Never heard from: silent since tracking began, so it goes STALE then OFFLINE on the same thresholds.
    assert h.status() is DeviceStatus.ONLINE
    clock.advance(1.0)
    assert h.status() is DeviceStatus.STALE
    clock.advance(9.0)
    assert h.status() is DeviceStatus.OFFLINE
    assert fleet.offline_configured() == ["arm-001"]
    assert h.snapshot().age_s is None

    feed(fleet, clock, "arm-001", 20)
    assert h.status() is DeviceStatus.ONLINE
    assert fleet.offline_configured() == []
    clock.advance(0.35)
    assert h.status() is DeviceStatus.STALE
    assert h.snapshot().age_s == pytest.approx(0.35)
    clock.advance(10.0)
    assert h.status() is DeviceStatus.OFFLINE
    feed(fleet, clock, "arm-001", 1)
    assert h.status() is DeviceStatus.ONLINE


def test_age_ignores_the_edge_clock() -> None:
    # An edge clock an hour behind or ahead changes nothing about liveness.
    clock = FakeClock()
    fleet = FleetHealth(TH, clock=clock)
    for device, skew in (("behind", 3600.0), ("ahead", -3600.0)):
        feed(fleet, clock, device, 5, skew_s=skew)
        snap = fleet.device(device).snapshot()
        assert snap.status is DeviceStatus.ONLINE
        assert snap.age_s == 0.0


def test_rate_over_window() -> None:
    clock = FakeClock()
    fleet = FleetHealth(TH, clock=clock)
    feed(fleet, clock, "arm-001", 100, dt=0.1)  # 10 s at 10 Hz
    assert fleet.device("arm-001").snapshot().rate_hz == pytest.approx(10.0, abs=0.3)
    feed(fleet, clock, "arm-001", 150, dt=0.02)  # 3 s at 50 Hz: window holds 2 s of 10 Hz + 3 s of 50 Hz
    assert fleet.device("arm-001").snapshot().rate_hz == pytest.approx((20 + 150) / 5.0, abs=1.0)
    clock.advance(6.0)
    assert fleet.device("arm-001").snapshot().rate_hz == 0.0


def test_rate_meter_young_device_and_flood_memory() -> None:
    meter = RateMeter(5.0)
    assert meter.rate(0.0) == 0.0
    for i in range(20):
        meter.add(i * 0.1)
    assert meter.rate(1.9) == pytest.approx(20 / 1.9, rel=0.01)
    for i in range(100_000):
        meter.add(2.0 + i * 1e-5)  # 100k messages in one second: memory stays in buckets
    assert len(meter._buckets) <= 5.0 / 0.1 + 2
    assert meter.rate(3.0) == pytest.approx(100_020 / 3.0, rel=0.01)


def test_rate_meter_keeps_its_sum_equal_to_its_buckets() -> None:
    # The rate is read from a running sum (cheap for a fleet's sweep); it must equal a sum over the buckets
    # in the window, however messages and reads interleave, gaps included.
    rng = random.Random(7)
    meter = RateMeter(5.0)
    now = 0.0
    for _ in range(20_000):
        now += rng.choice([0.0, 0.001, 0.05, 0.1, 0.3, 2.0, 7.0])
        if rng.random() < 0.8:
            meter.add(now, rng.randint(1, 3))
        else:
            rate = meter.rate(now)
            in_window = sum(c for start, c in meter._buckets if start + 0.1 > now - 5.0)
            oldest = min((start, c) for start, c in meter._buckets) if meter._buckets else None
            if oldest is not None and now - 5.0 > oldest[0]:
                in_window -= oldest[1] * (now - 5.0 - oldest[0]) / 0.1  # only its share inside the window
            span = max(min(5.0, now - (meter._first or now)), 1.0)
            assert rate == pytest.approx(in_window / span, abs=1e-9)


def test_counters_and_rejections() -> None:
    clock = FakeClock()
    fleet = FleetHealth(TH, ["arm-001"], clock=clock)
    feed(fleet, clock, "arm-001", 3)
    h = fleet.device("arm-001")
    h.record_ignored_stale()
    h.overwritten = 7
    h.record_error()
    fleet.record_rejected("arm-001", "not_json")
    fleet.record_rejected("arm-001", "not_json")
    fleet.record_rejected("arm-001", "too_large")
    fleet.record_rejected("ghost-9", "not_json")  # never valid, not configured: not a new table row
    fleet.record_rejected(None, "bad_device_id")
    c = h.snapshot().counters
    assert (c.received, c.decoded, c.applied, c.ignored_stale) == (3, 3, 3, 1)
    assert (c.overwritten, c.errors, c.rejected_total) == (7, 1, 3)
    assert c.rejected == {"not_json": 2, "too_large": 1}
    assert "ghost-9" not in fleet.devices
    assert fleet.untracked_rejected == {"not_json": 1, "bad_device_id": 1}


def test_latency_reports_skew_as_offset() -> None:
    clock = FakeClock()
    fleet = FleetHealth(TH, clock=clock)
    feed(fleet, clock, "ok", 30)
    ok = fleet.device("ok").snapshot()
    feed(fleet, clock, "skewed", 30, skew_s=2.5)  # edge clock 2.5 s behind
    skewed = fleet.device("skewed").snapshot()
    assert ok.edge_clock_latency_s.p50 == pytest.approx(0.020, abs=0.002)
    assert ok.edge_clock_offset_s == pytest.approx(0.020, abs=0.002)
    # The skewed edge looks 2.5 s "late"; the offset estimate carries it and the jitter stays small.
    assert skewed.edge_clock_latency_s.p99 == pytest.approx(2.52, abs=0.002)
    assert skewed.edge_clock_offset_s == pytest.approx(2.52, abs=0.002)
    assert skewed.edge_transit_jitter_p99_s == pytest.approx(0.0, abs=0.002)
    assert ok.internal_latency_s.p50 == pytest.approx(0.0005)
    assert ok.internal_latency_s.samples == 30


def test_latency_window_forgets_old_samples() -> None:
    window = SampleWindow(5.0)
    window.add(0.0, 9.0)
    window.add(4.0, 1.0)
    assert window.values(4.5) == [9.0, 1.0]
    assert window.summary(5.5) == (WindowLatency(p50=1.0, p99=1.0, samples=1), 1.0)
    assert window.summary(20.0) == (WindowLatency(), None)


def test_percentile_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]
    assert percentile(values, 0.5) == 50.0
    assert percentile(values, 0.99) == 99.0
    assert percentile([3.0], 0.99) == 3.0
    assert percentile([], 0.5) is None


def test_a_reading_is_a_copy_summarised_later() -> None:
    """A report copies each device's reading under the worker's lock and summarises it after: the reading
    must not move with messages that arrive in between, and must summarise as `snapshot` did when taken."""
    clock = FakeClock()
    fleet = FleetHealth(TH, clock=clock)
    feed(fleet, clock, "arm", 30, skew_s=0.5)
    readings = fleet.readings()
    then = fleet.snapshot()
    feed(fleet, clock, "arm", 30, skew_s=3.0)  # arrives while the reader builds its report
    feed(fleet, clock, "new", 5)
    assert list(readings) == ["arm"]
    assert {device: reading.snapshot() for device, reading in readings.items()} == then
    assert then["arm"].edge_clock_offset_s == pytest.approx(0.52, abs=0.002)
    assert then["arm"].counters.received == 30
    assert fleet.snapshot()["arm"].counters.received == 60


def test_a_discovered_device_is_listed_once_it_has_counted_something() -> None:
    # The mirror makes a discovered arm's record when its first valid message is decoded, and counts that
    # message a stage later: listed in between, the arm read OFFLINE with nothing received. A configured arm
    # is expected, so it is listed before it is heard from.
    clock = FakeClock()
    fleet = FleetHealth(TH, ["arm-001"], clock=clock)
    fleet.device("arm-new")
    fleet.device("arm-junk")
    assert fleet.listed() == ["arm-001"]
    assert list(fleet.readings()) == list(fleet.snapshot()) == list(fleet.statuses()) == ["arm-001"]
    feed(fleet, clock, "arm-new", 1)
    fleet.record_rejected("arm-junk", "bad_json")
    assert fleet.listed() == ["arm-001", "arm-new", "arm-junk"]
    assert list(fleet.readings()) == ["arm-001", "arm-junk", "arm-new"]
    assert fleet.statuses()["arm-new"] is DeviceStatus.ONLINE
    assert fleet.readings()["arm-new"].snapshot().counters.received == 1


def test_the_rate_of_a_steady_stream_reads_its_rate_whenever_it_is_read() -> None:
    """The window's oldest bucket is partly outside it; counted whole, a steady 10 Hz arm read 10.0-10.2 Hz
    (on the Fleet page, and LossPercent up to 2 points low). Only its share inside the window counts now."""
    meter = RateMeter(5.0)
    for k in range(199):
        meter.add(0.037 + 0.1 * k)  # the last at 19.837
    # Read between that message and the next, at phases all across a bucket: a message of the oldest bucket
    # is inside or outside the window by the read's phase, so a reading is off by up to one message either
    # way (0.2 Hz); their mean is the rate.
    readings = [meter.rate(19.84 + 0.0024 * j) for j in range(40)]
    assert all(abs(r - 10.0) <= 0.2 for r in readings), (min(readings), max(readings))
    assert abs(sum(readings) / len(readings) - 10.0) < 0.03, sum(readings) / len(readings)


def test_a_held_arms_refused_messages_say_when_it_was_last_heard_and_how_often() -> None:
    # A walk's held arm (every message refused) published ten a second while its page read "last seen
    # never, 0.0 Hz": its refused messages still show it is on, apart from its valid ones.
    clock = FakeClock()
    fleet = FleetHealth(TH, ["arm-held"], clock=clock)
    for n in range(50):
        clock.advance(0.1)
        fleet.record_rejected("arm-held", "calibration_refused", clock.t)
        if n == 20:  # its window not filled yet: not known, not the share counted so far
            assert fleet.device("arm-held").snapshot().refused_rate_hz is None
    clock.advance(0.4)
    snap = fleet.device("arm-held").snapshot()
    assert (snap.age_s, snap.rate_hz) == (None, 0.0)
    assert snap.refused_age_s == pytest.approx(0.4)
    assert snap.refused_rate_hz == pytest.approx(10.0, abs=1.0)
    checkpointed = fleet.device("arm-held").checkpoint().snapshot(TH, clock.t + 1.0, 0.0)
    assert checkpointed.refused_age_s == pytest.approx(1.4)
    # A review: from a checkpoint (a worker started again) it read 0.0 Hz beside "a refused one 1.4 s ago".
    assert checkpointed.refused_rate_hz is None
    restarted = FleetHealth(TH, ["arm-held"], clock=clock)
    restarted.device("arm-held").restore(fleet.device("arm-held").checkpoint())
    assert restarted.device("arm-held").snapshot().refused_rate_hz is None
    # None refused for a whole window: 0, known.
    assert fleet.device("arm-held").checkpoint().snapshot(TH, clock.t + 6.0, 0.0).refused_rate_hz == 0.0
    # An arm none of whose messages was refused says none.
    quiet = FleetHealth(TH, ["arm-quiet"], clock=clock).device("arm-quiet").snapshot()
    assert (quiet.refused_age_s, quiet.refused_rate_hz) == (None, 0.0)
    # A snapshot built without them knows nothing of its refused messages: not known, not 0.
    assert (HealthSnapshot().refused_age_s, HealthSnapshot().refused_rate_hz) == (None, None)


def test_a_checkpoints_valid_rate_is_not_known_unless_none_came_for_a_window() -> None:
    # A walk: read from a checkpoint (a worker started again), an arm publishing ten a second read 0.0 Hz
    # beside a valid message 0.1 s old. Its meter starts empty: the rate is not known, unless none came
    # for a whole window, which is 0.
    clock = FakeClock()
    fleet = FleetHealth(TH, ["arm-1"], clock=clock)
    for _ in range(50):
        clock.advance(0.1)
        fleet.device("arm-1").record_decoded(clock.t, 1000.0 + clock.t, int(clock.t * 1000))
    checkpoint = fleet.device("arm-1").checkpoint()
    assert checkpoint.snapshot(TH, clock.t + 0.1, 0.0).rate_hz is None
    assert checkpoint.snapshot(TH, clock.t + TH.window_s + 1.0, 0.0).rate_hz == 0.0
    never = FleetHealth(TH, ["arm-2"], clock=clock).device("arm-2").checkpoint()
    assert never.snapshot(TH, clock.t, 0.0).rate_hz == 0.0
