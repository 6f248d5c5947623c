"""Arms slower than `[health] expected_rate_hz`: the rate watch's slow side (one warning an episode naming the
arm, its rate, the expected rate and the two readings; one info once back) and the status watch's flapping
(an arm that goes STALE and back over and over makes one warning and a summary an interval, not two events a
cycle). All on injected clocks: the watches are fed readings, the mirror batches, both at chosen times."""

from __future__ import annotations

import pickle
import random
from multiprocessing import Pipe

import pytest
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.service import events
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.events import EventKind, EventQuery, EventStore, FleetWatch, RateWatch, StatusWatch
from twin.service.mirror import Mirror, PipeInbox
from twin.transport.pipe import Batch

# The edges' clocks: the epoch seconds their timestamps start from (the agent's wall clock agrees with them).
_EPOCH = 1.7e9


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.now = t

    def __call__(self) -> float:
        return self.now


def _rate_events(s: EventStore) -> list[tuple[str, str, str, float]]:
    return [
        (e.device, e.level, e.data["rate"], float(e.data["rate_hz"]))
        for e in s.query(EventQuery())
        if "rate" in e.data
    ]


def test_rate_watch_reports_an_arm_held_well_under_the_rate_once_and_its_return() -> None:
    s = EventStore(100)
    watch = RateWatch(s, expected_rate_hz=10.0, stale_after_s=0.3)
    hold = events.SLOW_HOLD_S

    def sweep(at: float, **rates: float) -> list[tuple[str, str, str, float]]:
        watch.sweep({d.replace("_", "-"): r for d, r in rates.items()}, at)
        return _rate_events(s)

    # A dip shorter than the hold (a pause fills a 5 s window again) is no report; nor is an arm that stopped.
    assert sweep(0.0, arm_001=3.0, arm_002=10.0, arm_003=0.0) == []
    assert sweep(hold - 1.0, arm_001=3.0, arm_002=10.0, arm_003=0.0) == []
    assert sweep(hold, arm_001=10.0, arm_002=10.0, arm_003=0.0) == []
    # A 2 Hz edge held under the line for the hold: once, however long it lasts.
    assert sweep(hold + 1.0, arm_001=2.0, arm_002=10.0, arm_003=0.0) == []
    assert sweep(2 * hold + 1.0, arm_001=2.0, arm_002=10.0, arm_003=0.0) == [
        ("arm-001", "warning", "slow", 2.0)
    ]
    assert watch.slow == ("arm-001",) and watch.reported == ()
    # Over the report line but under the clearing one, or stopped: still reported, no new event.
    for at, rate in ((3 * hold, 2.1), (3 * hold + 5.0, 6.5), (3 * hold + 10.0, 0.0), (4 * hold, 2.0)):
        assert len(sweep(at, arm_001=rate, arm_002=10.0, arm_003=0.0)) == 1
    # Back near the expected rate: one info event.
    assert sweep(4 * hold + 5.0, arm_001=9.8, arm_002=10.0)[1:] == [("arm-001", "info", "expected", 9.8)]
    assert watch.slow == ()
    (warning, back) = s.query(EventQuery())
    assert warning.kind == "twin" and warning.device == "arm-001"
    assert "arm-001 sends 2.0 valid messages/s, well under the expected 10 Hz" in warning.message
    # The checks before the setting: set on a guess it hid a loss as a slower edge (a walk).
    check, setting = (
        "Read the rate configured on its edge",
        "only if it is 2.0 Hz set [health] expected_rate_hz = 2 ",
    )
    assert 0 <= warning.message.index(check) < warning.message.index(setting), warning.message
    assert "its loss reads about 80%" in warning.message and "a gap passes 0.3 s" in warning.message
    assert "its messages are lost on the way in, or its edge publishes slower" in warning.message
    assert "quota" not in warning.message  # no broker limit given: no quota to name
    assert warning.data == {"rate_hz": "2.00", "expected_rate_hz": "10", "rate": "slow"}
    assert back.message == "arm-001 sends 9.8 valid messages/s now, no longer far under the expected 10 Hz"
    # Forgotten, nothing of it stays.
    sweep(5 * hold, arm_001=2.0)
    watch.forget("arm-001")
    sweep(6 * hold, arm_001=2.0)
    assert len(_rate_events(s)) == 2


def test_a_normal_arm_and_one_a_little_slow_are_not_reported() -> None:
    s = EventStore(100)
    watch = RateWatch(s, expected_rate_hz=10.0)
    for k in range(100):  # 500 s of readings
        watch.sweep({"arm-001": 10.0, "arm-002": 9.2, "arm-003": 6.0}, 5.0 * k)
    assert _rate_events(s) == [] and watch.slowing == frozenset()


def test_rate_watch_takes_back_a_slow_report_and_waits_for_the_rates_to_fill_before_a_return() -> None:
    s = EventStore(100)
    watch = RateWatch(s, expected_rate_hz=10.0)
    watch.restore([], 100.0, slow=["arm-001"])
    assert watch.slow == ("arm-001",)
    watch.sweep({"arm-001": 10.0}, 100.0 + events.RESTORED_SETTLE_S / 2)  # a fresh meter reads anything
    for at in (120.0, 140.0, 160.0):
        watch.sweep({"arm-001": 1.0}, at)
    assert _rate_events(s) == []
    watch.sweep({"arm-001": 10.0}, 165.0)
    assert _rate_events(s) == [("arm-001", "info", "expected", 10.0)] and watch.slow == ()


def test_a_slow_arm_is_not_also_reported_as_losing_but_a_lossy_arm_at_its_rate_is() -> None:
    """A walk: 300 edges at 2 Hz against 10 each read "loss 80 %" (their gaps are five nominal periods); the
    slow warning names that reading, so the loss watch does not add a second warning an arm."""
    s = EventStore(100)
    watch = FleetWatch(s)
    hold = max(events.SLOW_HOLD_S, events.LOSING_HOLD_S)
    for at in (0.0, hold / 2, hold):  # as the mirror: rates, then losses
        watch.rates({"arm-001": 2.0, "arm-002": 8.0}, at)
        watch.losses({"arm-001": (20, 80), "arm-002": (80, 20)}, at)
    found = sorted((e.device, e.data.get("rate") or e.data.get("loss")) for e in s.query(EventQuery()))
    assert found == [("arm-001", "slow"), ("arm-002", "losing")]


# --- through a mirror --------------------------------------------------------------------------------------


def _mirror(clock: Clock, **overrides: object) -> Mirror:
    config = load_config(
        None,
        {"telemetry.devices": ["*"], "telemetry.units": "auto", "telemetry.max_devices": 64, **overrides},
    )
    return Mirror(
        config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(64), clock=clock, wall_clock=clock
    )


def _run(mirror: Mirror, clock: Clock, seconds: float, arms: dict[str, float], rng: random.Random) -> None:
    """Each arm of `arms` (id -> rate, 0 for silent) publishes at its rate with a few ms of jitter on its
    arrival; the mirror takes a batch every 0.1 s and sweeps after each, as its worker does."""
    due = dict.fromkeys(arms, clock.now)
    for _ in range(round(seconds * 10)):
        clock.now += 0.1
        sent: list[tuple[str, float]] = []
        for device, hz in arms.items():
            while hz and due[device] <= clock.now:
                sent.append((device, due[device]))
                due[device] += 1.0 / hz
            if not hz:
                due[device] = clock.now
        if sent:
            # Each message arrives a few ms after it was stamped, by the time of the batch that carries it.
            received = tuple(min(clock.now, t + rng.uniform(0.0, 0.05)) for _, t in sent)
            payloads = tuple(
                encode(make_payload(d, _EPOCH + t, "ticks", rng, timestamp_ms=round((_EPOCH + t) * 1000)))
                for d, t in sent
            )
            topics = tuple(telemetry_topic(DEFAULT_TOPIC_PREFIX, d) for d, _ in sent)
            devices = tuple(d for d, _ in sent)
            walls = tuple(_EPOCH + r for r in received)
            mirror._handle(Batch(devices, topics, payloads, received, walls), 0)
        mirror._watch_statuses()


def _twin_events(mirror: Mirror, key: str) -> list[tuple[str, str, str]]:
    found = mirror.events(EventQuery(kinds=frozenset({EventKind.TWIN.value})))
    return [(e.device, e.level, e.data[key]) for e in found if key in e.data]


def test_a_slow_arm_is_reported_once_through_the_mirror_and_not_twice_by_a_mirror_started_again() -> None:
    clock, rng = Clock(), random.Random(3)
    first = _mirror(clock)
    arms = {"arm-001": 10.0, "arm-002": 2.0}
    _run(first, clock, events.SLOW_HOLD_S + 3 * events.RATE_INTERVAL_S, arms, rng)
    assert _twin_events(first, "rate") == [("arm-002", "warning", "slow")]
    assert _twin_events(first, "loss") == []
    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    assert checkpoint.slow == ("arm-002",)

    again = _mirror(clock)
    again.restore(checkpoint)
    _run(again, clock, events.SLOW_HOLD_S + 3 * events.RATE_INTERVAL_S, arms, rng)
    assert _twin_events(again, "rate") == [] and _twin_events(again, "loss") == []
    # The edge set to its rate again: back, once its rate has filled.
    _run(again, clock, events.RESTORED_SETTLE_S + 3 * events.RATE_INTERVAL_S, {"arm-002": 10.0}, rng)
    assert _twin_events(again, "rate") == [("arm-002", "info", "expected")]


# --- flapping ----------------------------------------------------------------------------------------------


def _status_events(s: EventStore) -> list[tuple[str, str, str, str]]:
    return [(e.device, e.level, e.data["status"], e.data.get("flapping", "")) for e in s.query(EventQuery())]


def test_an_arm_that_goes_stale_and_back_over_and_over_is_told_as_flapping_then_summarised() -> None:
    s = EventStore(1000)
    watch = StatusWatch(s)
    watch.arrived("arm-001")
    watch.arrived("arm-002")
    t = 0.0
    # arm-002 pauses once a minute and a half: each pause is told as ever, however many there are.
    for k in range(events.FLAP_ROUND_TRIPS + 2):
        t = 90.0 * k
        watch.sweep({"arm-001": "ONLINE", "arm-002": "STALE"}, t)
        watch.sweep({"arm-001": "ONLINE", "arm-002": "ONLINE"}, t + 1.0)
    assert [e[2] for e in _status_events(s) if e[0] == "arm-002"] == ["ONLINE"] + ["STALE", "ONLINE"] * (
        events.FLAP_ROUND_TRIPS + 2
    )
    assert watch.flapping == ()
    start = len(s.query(EventQuery()))
    # arm-001 crosses its stale line at every sweep (half a second) for ten minutes.
    t += 10.0
    for k in range(1200):
        watch.sweep({"arm-001": "STALE" if k % 2 else "ONLINE", "arm-002": "ONLINE"}, t + 0.5 * k)
    got = _status_events(s)[start:]
    told = events.FLAP_ROUND_TRIPS - 1  # the round trips told as such before the rule
    went = [("arm-001", "warning", "STALE", ""), ("arm-001", "info", "ONLINE", "")]
    assert got[: 2 * told] == went * told
    assert got[2 * told :] == [
        ("arm-001", "warning", "STALE", ""),
        ("arm-001", "warning", "ONLINE", "started"),  # instead of its third return
        ("arm-001", "warning", "ONLINE", "still"),  # after FLAP_SUMMARY_S: where it stands then
    ]
    (started, still) = s.query(EventQuery())[-2:]
    assert started.message.startswith("arm-001 is flapping between ONLINE and STALE: back ONLINE 3 times")
    assert started.data["round_trips"] == str(events.FLAP_ROUND_TRIPS) and started.data["previous"] == "STALE"
    summarised = round(events.FLAP_SUMMARY_S)  # round trips since the warning: one a second
    assert still.data["round_trips"] == str(summarised) and f": {summarised} round trips" in still.message
    assert watch.flapping == ("arm-001",)
    # It settles ONLINE: after FLAP_SETTLE_S, one info event; a later pause is told as ever.
    t += 600.0
    for k in range(round(events.FLAP_SETTLE_S) + 2):
        watch.sweep({"arm-001": "ONLINE", "arm-002": "ONLINE"}, t + k)
    t += events.FLAP_SETTLE_S + 2
    watch.sweep({"arm-001": "STALE", "arm-002": "ONLINE"}, t)
    watch.sweep({"arm-001": "ONLINE", "arm-002": "ONLINE"}, t + 1.0)
    assert _status_events(s)[-3:] == [
        ("arm-001", "info", "ONLINE", "settled"),
        ("arm-001", "warning", "STALE", ""),
        ("arm-001", "info", "ONLINE", ""),
    ]
    assert watch.flapping == ()


def test_a_flapping_arm_that_goes_offline_is_told_so_and_its_episode_ends() -> None:
    s = EventStore(100)
    watch = StatusWatch(s)
    watch.arrived("arm-001")
    for k in range(2 * events.FLAP_ROUND_TRIPS + 5):  # ends STALE
        watch.sweep({"arm-001": "ONLINE" if k % 2 else "STALE"}, 0.5 * k)
    assert watch.flapping == ("arm-001",)
    watch.sweep({"arm-001": "OFFLINE"}, 20.0)
    assert watch.flapping == () and _status_events(s)[-1] == ("arm-001", "warning", "OFFLINE", "")
    assert s.query(EventQuery())[-1].message == "arm-001 went OFFLINE (was STALE)"


def test_a_fleet_at_2_hz_against_10_makes_one_slow_warning_an_arm_and_few_status_events() -> None:
    """The walk's fleet in small, over ten simulated minutes through a mirror: arms at 2 Hz against the
    default 10 each get one slow warning and no loss warning, and a bounded number of status events (their
    gaps pass the 0.3 s stale line at most sweeps); an arm at 10 Hz gets none of it; one that pauses for a
    second goes STALE and comes back ONLINE, told as ever."""
    clock, rng = Clock(), random.Random(11)
    mirror = _mirror(clock)
    slow = [f"arm-{i:03d}" for i in range(1, 9)]
    arms = dict.fromkeys(slow, 2.0) | {"arm-100": 10.0, "arm-101": 10.0}
    _run(mirror, clock, 120.0, arms, rng)
    _run(mirror, clock, 1.0, arms | {"arm-101": 0.0}, rng)  # arm-101 pauses for a second
    _run(mirror, clock, 480.0, arms, rng)

    rates = _twin_events(mirror, "rate")
    assert sorted(rates) == [(d, "warning", "slow") for d in slow]
    assert _twin_events(mirror, "loss") == []
    statuses = mirror.events(EventQuery(kinds=frozenset({EventKind.STATUS.value})))
    per_arm = {d: [e for e in statuses if e.device == d] for d in arms}
    # The arrival, the round trips before the flapping rule, its warning, a summary each FLAP_SUMMARY_S.
    bound = 1 + 2 * events.FLAP_ROUND_TRIPS + 600.0 / events.FLAP_SUMMARY_S
    assert all(0 < len(per_arm[d]) <= bound for d in slow), {d: len(per_arm[d]) for d in slow}
    # Flapping, told on the mirror's clock: started, then a summary after FLAP_SUMMARY_S.
    told = {d: [e.data.get("flapping", "") for e in per_arm[d]] for d in slow}
    assert all("started" in told[d] and "still" in told[d] for d in slow), told
    assert [e.data["status"] for e in per_arm["arm-100"]] == ["ONLINE"]
    assert [(e.data["status"], e.data["previous"]) for e in per_arm["arm-101"]] == [
        ("ONLINE", ""),
        ("STALE", "ONLINE"),
        ("ONLINE", "STALE"),
    ]
    # What the Fleet page shows is the arms' status as it is, whatever the events held back.
    shown = mirror.statuses()
    assert shown["arm-100"] == "ONLINE" and {str(shown[d]) for d in slow} <= {"ONLINE", "STALE"}


def test_a_worker_started_again_keeps_a_flapping_arms_episode_and_its_settle_timer() -> None:
    """The checkpoint carries the status watch's flapping episodes: a worker started again told an arm known
    to flap as "(restored)", then each of its round trips until a third made a second "is flapping" warning,
    and the info that it settled never came (the episode, and its timer, were lost)."""
    clock, rng = Clock(), random.Random(13)
    first = _mirror(clock)
    _run(first, clock, 20.0, {"arm-001": 1.0}, rng)
    told = [e.data.get("flapping", "") for e in first.events(EventQuery(device="arm-001"))]
    assert "started" in told
    checkpoint = pickle.loads(pickle.dumps(first.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL))
    assert [row[0] for row in checkpoint.flapping] == ["arm-001"]

    again = _mirror(clock)
    again.restore(checkpoint)
    _run(again, clock, 20.0, {"arm-001": 1.0}, rng)
    assert again.events(EventQuery(kinds=frozenset({EventKind.STATUS.value}))) == []
    # It settles at its rate: the episode's end is told once it has kept ONLINE for FLAP_SETTLE_S.
    _run(again, clock, events.FLAP_SETTLE_S + 2.0, {"arm-001": 10.0}, rng)
    found = again.events(EventQuery(kinds=frozenset({EventKind.STATUS.value})))
    assert [(e.level, e.data["status"], e.data.get("flapping", "")) for e in found] == [
        ("info", "ONLINE", "settled")
    ]


def test_a_checkpoint_without_the_flapping_episodes_still_loads_and_restores() -> None:
    """A checkpoint pickled before the field was added (its state has no `flapping`) reads as none."""
    clock, rng = Clock(), random.Random(14)
    first = _mirror(clock)
    _run(first, clock, 20.0, {"arm-001": 1.0}, rng)
    checkpoint = first.checkpoint()
    vars(checkpoint).pop("flapping")
    old = pickle.loads(pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL))
    assert old.flapping == ()
    again = _mirror(clock)
    assert again.restore(old).devices == 1
    _run(again, clock, 2.0, {"arm-001": 10.0}, rng)
    found = again.events(EventQuery(kinds=frozenset({EventKind.STATUS.value})))
    assert [e.message for e in found] == ["arm-001 is ONLINE (restored)"]


def _status_of(mirror: Mirror, device: str) -> list[tuple[str, str, str, str]]:
    found = mirror.events(EventQuery(device=device, kinds=frozenset({EventKind.STATUS.value})))
    return [(e.level, e.data["status"], e.data["previous"], e.data.get("flapping", "")) for e in found]


def test_an_arm_quieter_than_offline_after_s_is_told_as_flapping_and_its_outage_still_told() -> None:
    """An edge sending every 12 s against offline_after_s = 10 went STALE, OFFLINE and back ONLINE with each
    message, three events an operator sees every 12 s and no flapping warning: its round trips went through
    OFFLINE, which the rule did not count. They count: one warning naming the fix, its changes held, a
    restarted worker holds them too; an arm that then stops is told OFFLINE once it has been silent past the
    hold, and its next OFFLINE, once heard again, at once."""
    clock, rng = Clock(), random.Random(21)
    mirror = _mirror(clock)
    arms = {"arm-001": 1 / 12, "arm-002": 10.0}
    _run(mirror, clock, 180.0, arms, rng)
    got = _status_of(mirror, "arm-001")
    cycle = [("warning", "STALE", "ONLINE", ""), ("warning", "OFFLINE", "STALE", "")]
    told = events.FLAP_ROUND_TRIPS - 1  # the round trips told as such before the rule
    returned = [*cycle, ("info", "ONLINE", "OFFLINE", "")]
    assert got == [
        ("info", "ONLINE", "", ""),
        *returned * told,
        *cycle,
        ("warning", "ONLINE", "OFFLINE", "started"),
    ]
    (started,) = [e for e in mirror.events(EventQuery(device="arm-001")) if e.data.get("flapping")]
    assert started.message.startswith("arm-001 is flapping between ONLINE and OFFLINE: back ONLINE 3 times")
    assert "less often than [health] offline_after_s (10 s)" in started.message
    assert "publish more often, or set offline_after_s above its period" in started.message
    assert _status_of(mirror, "arm-002") == [("info", "ONLINE", "", "")]
    # A worker started again carries the episode: no event of the arm's own, nor a second warning.
    again = _mirror(clock)
    again.restore(pickle.loads(pickle.dumps(mirror.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL)))
    _run(again, clock, 120.0, arms, rng)
    assert _status_of(again, "arm-001") == []
    # It stops (after a last burst, held too): STALE and OFFLINE held, then told once it has been OFFLINE for
    # FLAP_OFFLINE_HOLD_S, offline_after_s + the hold after its last message; the episode ends.
    _run(again, clock, 1.0, arms | {"arm-001": 10.0}, rng)
    silent = arms | {"arm-001": 0.0}
    _run(again, clock, 10.0 + events.FLAP_OFFLINE_HOLD_S - 2.0, silent, rng)
    assert _status_of(again, "arm-001") == []
    _run(again, clock, 4.0, silent, rng)
    assert _status_of(again, "arm-001") == [("warning", "OFFLINE", "", "settled")]
    assert again.events(EventQuery(device="arm-001"))[-1].message.startswith(
        "arm-001 no longer flaps: OFFLINE for"
    )
    # Heard again, then silent: each change told as itself, the OFFLINE at once.
    _run(again, clock, 5.0, arms | {"arm-001": 10.0}, rng)
    _run(again, clock, 10.0 + 1.0, silent, rng)
    assert _status_of(again, "arm-001")[1:] == [
        ("info", "ONLINE", "OFFLINE", ""),
        ("warning", "STALE", "ONLINE", ""),
        ("warning", "OFFLINE", "STALE", ""),
    ]


def test_an_arm_that_goes_offline_and_stays_so_is_told_at_once_every_time() -> None:
    """OFFLINE round trips count as returns for the flapping rule, but the rule begins at a return: an arm
    that goes OFFLINE and stays so is told at once however often it came back before, an arm flapping
    between ONLINE and STALE is told OFFLINE at once, and so is one that settled after flapping through
    OFFLINE."""
    s = EventStore(1000)
    watch = StatusWatch(s)
    for device in ("arm-001", "arm-002", "arm-003"):
        watch.arrived(device)
    # arm-001 back from OFFLINE twice within the window, then OFFLINE for good: each OFFLINE told at once.
    for k in range(events.FLAP_ROUND_TRIPS - 1):
        watch.sweep({"arm-001": "OFFLINE"}, 10.0 * k)
        assert _status_events(s)[-1] == ("arm-001", "warning", "OFFLINE", "")
        watch.sweep({"arm-001": "ONLINE"}, 10.0 * k + 1.0)
    watch.sweep({"arm-001": "OFFLINE"}, 30.0)
    assert _status_events(s)[-1] == ("arm-001", "warning", "OFFLINE", "") and watch.flapping == ()
    # arm-002 flaps between ONLINE and STALE, then goes OFFLINE: told at once, the episode over.
    for k in range(2 * events.FLAP_ROUND_TRIPS + 1):
        watch.sweep({"arm-002": "ONLINE" if k % 2 else "STALE"}, 100.0 + k)
    assert watch.flapping == ("arm-002",)
    watch.sweep({"arm-002": "OFFLINE"}, 120.0)
    assert watch.flapping == () and _status_events(s)[-1] == ("arm-002", "warning", "OFFLINE", "")
    # arm-003 flaps through OFFLINE, held, settles ONLINE; its first OFFLINE after that is told at once.
    for k in range(3 * events.FLAP_ROUND_TRIPS):
        watch.sweep({"arm-003": ("STALE", "OFFLINE", "ONLINE")[k % 3]}, 200.0 + k)
    assert watch.flapping == ("arm-003",) and _status_events(s)[-1][3] == "started"
    for k in range(6):
        watch.sweep({"arm-003": ("STALE", "OFFLINE", "ONLINE")[k % 3]}, 210.0 + k)
    assert _status_events(s)[-1][3] == "started"
    watch.sweep({"arm-003": "ONLINE"}, 215.0 + events.FLAP_SETTLE_S)
    watch.sweep({"arm-003": "OFFLINE"}, 216.0 + events.FLAP_SETTLE_S)
    assert _status_events(s)[-2:] == [
        ("arm-003", "info", "ONLINE", "settled"),
        ("arm-003", "warning", "OFFLINE", ""),
    ]


def test_a_checkpoint_row_without_the_offline_field_restores_an_episode_between_online_and_stale() -> None:
    """Rows pickled before the field: six values, an episode between ONLINE and STALE (all were then)."""
    s = EventStore(100)
    watch = StatusWatch(s)
    watch.restored("arm-001")
    watch.restore_flapping([("arm-001", 0.0, 5.0, 7, 1, 300.0)])
    watch.sweep({"arm-001": "STALE"}, 6.0)
    watch.sweep({"arm-001": "ONLINE"}, 7.0)
    assert _status_events(s) == [] and watch.flapping_rows() == (("arm-001", 0.0, 7.0, 8, 2, 300.0, False),)
    watch.sweep({"arm-001": "OFFLINE"}, 20.0)
    assert _status_events(s) == [("arm-001", "warning", "OFFLINE", "")] and watch.flapping == ()


def test_an_arm_sending_less_than_once_a_rate_window_is_reported_slow_through_the_mirror() -> None:
    """An edge sending one message every 8 s against 10 Hz: its 5 s rate windows read 0.2 or 0, and every 0
    ended its time under the slow line, so it was never held there and never reported. Not OFFLINE, it has
    not stopped: it is slow, and told so once with its rate over the hold (about 0.125 Hz)."""
    clock, rng = Clock(), random.Random(15)
    mirror = _mirror(clock, **{"broker.per_connection_limit": 100})
    # units=auto decides its units from its first few messages (about 20 s), then the hold runs.
    _run(mirror, clock, events.SLOW_HOLD_S + 40.0, {"arm-001": 10.0, "arm-002": 0.125}, rng)
    assert _twin_events(mirror, "rate") == [("arm-002", "warning", "slow")]
    (warning,) = [e for e in mirror.events(EventQuery(device="arm-002")) if "rate" in e.data]
    assert 0.08 <= float(warning.data["rate_hz"]) <= 0.2, warning.data
    assert "expected_rate_hz = 0.1 " in warning.message
    # Where the broker limits each connection (100 messages/s here), its quota comes before the edge.
    message = warning.message
    assert "per-connection quota (100 messages/s a connection" in message, message
    assert message.index("quota") < message.index("Read the rate configured on its edge"), message


def test_rate_watch_holds_a_slow_arm_between_its_messages_but_not_one_that_stopped() -> None:
    s = EventStore(100)
    watch = RateWatch(s, expected_rate_hz=10.0)
    live = {"arm-001": "STALE", "arm-002": "STALE", "arm-003": "ONLINE"}
    # arm-001 sends every 8 s: its windows read 0.2 and 0; arm-002 sent some, then stopped (OFFLINE at 10 s).
    # arm-003 sent at 3 Hz for 25 s, then stopped: STALE, its hold passing in the silence, then OFFLINE.
    readings = [0.2, 0.2, 0.0, 0.2, 0.2, 0.0, 0.2, 0.0]
    for k, rate in enumerate(readings):
        live["arm-002"] = "OFFLINE" if k >= 2 else "STALE"
        live["arm-003"] = "ONLINE" if k <= 5 else "STALE" if k <= 7 else "OFFLINE"
        rates = {"arm-001": rate, "arm-002": 1.0 if k == 0 else 0.0, "arm-003": 3.0 if k <= 5 else 0.0}
        watch.sweep(rates, 5.0 * k, statuses=live)
    assert _rate_events(s) == [("arm-001", "warning", "slow", 0.14)]
    assert watch.slow == ("arm-001",) and "arm-002" not in watch.slowing
    live["arm-003"] = "OFFLINE"
    watch.sweep({"arm-001": 0.2, "arm-003": 0.0}, 40.0, statuses=live)
    assert len(_rate_events(s)) == 1 and watch.slowing == {"arm-001"}
    # Without the statuses (or OFFLINE), a reading of 0 ends the time under the line, as before.
    other = RateWatch(EventStore(100), expected_rate_hz=10.0)
    for k, rate in enumerate(readings):
        other.sweep({"arm-001": rate}, 5.0 * k)
    assert other.slow == ()


@pytest.mark.parametrize(
    ("settings", "named", "not_named"),
    [
        (
            {"broker.url": "mqtt://127.0.0.1:1883", "broker.per_connection_limit": 40},
            "40 messages/s a connection, [broker] per_connection_limit)",
            "IoT Core",
        ),
        ({"broker.url": "iot"}, "100 messages/s a connection, IoT Core's quota)", "per_connection_limit"),
    ],
)
def test_the_slow_warning_names_the_quota_that_applies(
    settings: dict[str, object], named: str, not_named: str
) -> None:
    """The slow warning named "IoT Core's or [broker] per_connection_limit" whichever applied: the mirror
    knows which (transport.plan.default_limit), and names that one."""
    mirror = Mirror(
        load_config(None, {"telemetry.devices": ["arm-001"], **settings}),
        inbox=PipeInbox(Pipe(duplex=False)[0]),
        budget=DeviceBudget(1),
    )
    hold = events.SLOW_HOLD_S
    for at in (0.0, hold / 2, hold + 1.0):
        mirror._watch.rates({"arm-001": 2.0}, at)
    said = [e.message for e in mirror.events(EventQuery()) if e.data.get("rate") == "slow"]
    assert len(said) == 1 and named in said[0] and not_named not in said[0], said
