"""Forgetting an arm (docs/console.md, "Forget an arm"): an OFFLINE arm an operator retired leaves the fleet.

The alarm engine and the mirror are driven here on a clock of their own; the HTTP endpoint on an agent with
two worker processes behind a real mosquitto.
"""

from __future__ import annotations

import contextlib
import json
import pickle
import random
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from multiprocessing import Pipe
from pathlib import Path
from typing import Any

import pytest
from conftest import NO_BROKER, signal_and_await_restart, wait_for
from test_alerts import hot, hot_arm_settings
from test_servo_alarms_e2e import alarms, post
from twin.core.alarms import AlarmKind, AlarmRecord, AlarmState, ServoAlarms
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.edge.servo_faults import ServoFault
from twin.rig.local import LocalRig
from twin.service import agent as agent_module
from twin.service import mirror as mirror_module
from twin.service.admission import DeviceBudget
from twin.service.agent import AgentService, long_offline
from twin.service.config import ConfigError, load_config
from twin.service.console import FleetRow
from twin.service.events import EventKind, EventQuery
from twin.service.mirror import Mirror, PipeInbox
from twin.service.shards import ArmNotForgettableError, ArmNotFoundError, WorkerPlan, WorkerShard
from twin.service.state import DeviceState
from twin.transport.mailbox import InboundQueue
from twin.transport.pipe import Batch

# --- the alarm engine ---------------------------------------------------------------------------------------


def _record(device: str, joint: str, kind: AlarmKind, state: AlarmState, message: str) -> AlarmRecord:
    return AlarmRecord(
        device=device, joint=joint, kind=kind, state=state, since=5.0, present=True, raised=1, message=message
    )


def test_the_engine_forgets_every_alarm_of_one_arm_and_keeps_the_others_rows() -> None:
    engine = ServoAlarms()
    engine.restore(
        [
            _record("a", "wrist_roll", AlarmKind.OVER_TEMPERATURE, AlarmState.ACTIVE, "a hot"),
            _record("b", "wrist_roll", AlarmKind.OVER_TEMPERATURE, AlarmState.ACKNOWLEDGED, "b hot"),
            _record("b", "gripper", AlarmKind.OVER_CURRENT, AlarmState.ACKNOWLEDGED, "b current"),
            _record("b", "elbow_flex", AlarmKind.OVERLOAD, AlarmState.LATCHED, "b load"),
            _record("c", "shoulder_pan", AlarmKind.OVERLOAD, AlarmState.LATCHED, "c load"),
        ]
    )
    before = {v.alarm_id: v for v in engine.views() if v.device != "b"}
    removed = engine.forget("b")
    assert removed == {AlarmState.ACKNOWLEDGED: 2, AlarmState.LATCHED: 1}
    # The last arm's row moved into b's: its alarms are the same, messages and all.
    assert {v.alarm_id: v for v in engine.views(include_normal=True)} == before
    assert {r.device for r in engine.records()} == {"a", "c"}
    assert engine.worst_by_device().keys() == {"a", "c"}
    assert engine.forget("b") == {}  # gone already
    # A later message of the same id makes a fresh row: nothing of before.
    engine.restore([_record("b", "gripper", AlarmKind.OVER_CURRENT, AlarmState.ACTIVE, "b again")])
    assert [(v.alarm_id, v.state, v.message) for v in engine.views(device="b")] == [
        ("b/gripper/over_current", AlarmState.ACTIVE, "b again")
    ]
    assert {v.alarm_id for v in engine.views()} == {*before, "b/gripper/over_current"}


# --- the mirror -------------------------------------------------------------------------------------------


class _Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


OFFLINE_AFTER_S = 3.0
HOT = (ServoFault("heat", "wrist_roll", 0.0, 30.0),)


def _round(mirror: Mirror, clock: _Clock, devices: list[str], rng: random.Random, t: float) -> None:
    """One message of each of `devices` (edge time `t`, hot wrist for arm-002), 0.1 s after the last."""
    clock.now += 0.1
    payloads = tuple(
        encode(
            make_payload(
                d,
                t,
                "ticks",
                rng,
                timestamp_ms=round((1.7e9 + clock.now) * 1000),
                servo_faults=HOT if d == "arm-002" else (),
            )
        )
        for d in devices
    )
    n = len(devices)
    topics = tuple(telemetry_topic(DEFAULT_TOPIC_PREFIX, d) for d in devices)
    mirror._handle(Batch(tuple(devices), topics, payloads, (clock.now,) * n, (1.7e9 + clock.now,) * n), 0)
    mirror._watch_statuses()


def test_a_mirror_forgets_an_offline_arm_and_a_later_message_makes_a_new_arm() -> None:
    clock, rng = _Clock(), random.Random(3)
    config = load_config(
        None,
        {
            "telemetry.devices": ["*"],
            "telemetry.units": "ticks",
            "health.offline_after_s": OFFLINE_AFTER_S,
        },
    )
    budget = DeviceBudget(3)
    mirror = Mirror(
        config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=budget, clock=clock, wall_clock=clock
    )
    arms = ["arm-001", "arm-002", "arm-003"]
    t = 0.0
    while not any(a.device == "arm-002" for a in mirror.alarms()):
        assert t < 20.0, "arm-002's hot wrist raised no alarm"
        t += 0.1
        _round(mirror, clock, arms, rng, t)
    hot = mirror.alarms()[0].alarm_id
    mirror.acknowledge_alarm(hot)
    with pytest.raises(ArmNotForgettableError) as refused:
        mirror.forget_arm("arm-002")
    assert refused.value.code == "arm_not_offline" and "ONLINE" in str(refused.value)
    with pytest.raises(ArmNotFoundError):
        mirror.forget_arm("arm-404")
    others_before = mirror.report().devices["arm-001"].health.counters
    for _ in range(round(OFFLINE_AFTER_S * 10) + 1):
        t += 0.1
        _round(mirror, clock, ["arm-001", "arm-003"], rng, t)
    assert mirror.statuses()["arm-002"] == "OFFLINE"
    assert budget.taken == 3

    forgotten = mirror.forget_arm("arm-002")

    assert forgotten.status == "OFFLINE" and forgotten.alarms_removed.get("ACKNOWLEDGED", 0) >= 1
    assert budget.taken == 2  # its place is free
    report = mirror.report()
    assert sorted(report.devices) == ["arm-001", "arm-003"]
    assert sum(report.alarms.present.values()) == 0
    assert not [a for a in mirror.alarms(include_normal=True) if a.device == "arm-002"]
    assert [r.device for r in mirror.fleet_rows()] == ["arm-001", "arm-003"]
    assert all(r.device != "arm-002" for r in mirror.checkpoint().alarms)
    assert report.devices["arm-001"].health.counters.received > others_before.received
    event = mirror.events(EventQuery(kinds=frozenset({EventKind.TWIN.value}), device="arm-002"))[-1]
    assert event.data["action"] == "forgotten" and "forgotten by an operator" in event.message
    # It publishes again: a new arm, counted from its first message, ONLINE on arrival, no alarm of before.
    t += 0.1
    _round(mirror, clock, ["arm-002"], rng, 0.0)
    again = mirror.report().devices["arm-002"]
    assert again.health.counters.received == 1 and again.health.status == "ONLINE"
    assert budget.taken == 3
    assert not [a for a in mirror.alarms() if a.device == "arm-002"]
    statuses = mirror.events(EventQuery(kinds=frozenset({EventKind.STATUS.value}), device="arm-002"))
    assert statuses[-1].message == "arm-002 is ONLINE (first message)"


def _fleet_mirror(clock: _Clock, places: int) -> Mirror:
    """A mirror of the whole fleet in ticks, on `clock`, with `places` in its device budget."""
    settings = {
        "telemetry.devices": ["*"],
        "telemetry.units": "ticks",
        "health.offline_after_s": OFFLINE_AFTER_S,
    }
    return Mirror(
        load_config(None, settings),
        inbox=PipeInbox(Pipe(duplex=False)[0]),
        budget=DeviceBudget(places),
        clock=clock,
        wall_clock=clock,
    )


def test_an_offline_arm_whose_refused_messages_still_arrive_is_not_forgotten() -> None:
    """An arm whose every message is refused is OFFLINE (its status is of valid messages) yet publishes: a
    held arm listed after a restart for its kept alarms lost them to a forget, and they came back
    unacknowledged. Once it is silent for health.offline_after_s it can be forgotten. A worker started again
    from its checkpoint refuses too, before the arm's next message (it let such a forget through)."""
    clock, rng = _Clock(), random.Random(5)
    mirror = _fleet_mirror(clock, places=3)
    _round(mirror, clock, ["arm-001"], rng, 0.0)
    topic = telemetry_topic(DEFAULT_TOPIC_PREFIX, "arm-001")
    for _ in range(round(OFFLINE_AFTER_S * 10) + 5):  # garbage only, until it is OFFLINE, and on
        clock.now += 0.1
        mirror._handle(Batch(("arm-001",), (topic,), (b"{not json",), (clock.now,), (1.7e9 + clock.now,)), 0)
    assert mirror.statuses()["arm-001"] == "OFFLINE"
    with pytest.raises(ArmNotForgettableError) as refused:
        mirror.forget_arm("arm-001")
    said = str(refused.value)
    assert refused.value.code == "arm_not_offline" and "arm-001 still publishes" in said, said
    assert "was refused (not_json)" in said and "stop its edge" in said, said
    # The Arm page shows the mirror's own answer, in the same words: its own rule offered what was refused.
    assert mirror.arm("arm-001").forget == (False, said)
    again = _fleet_mirror(clock, places=3)
    again.restore(pickle.loads(pickle.dumps(mirror.checkpoint(), protocol=pickle.HIGHEST_PROTOCOL)))
    with pytest.raises(ArmNotForgettableError) as refused_again:
        again.forget_arm("arm-001")
    assert str(refused_again.value) == said
    clock.now += OFFLINE_AFTER_S
    # A worker behind its input reads on its own clock, which the page's rule had not (a review).
    mirror._swept_behind_s = 0.5
    offer = mirror.arm("arm-001").forget
    assert offer is not None and not offer.allowed and "still publishes" in offer.why, offer
    mirror._swept_behind_s = 0.0
    assert mirror.arm("arm-001").forget == (True, "")
    assert mirror.forget_arm("arm-001").status == "OFFLINE"


def test_an_arm_kept_for_its_alarms_without_a_place_is_not_forgotten_while_it_publishes() -> None:
    """An arm listed after a restart for its kept alarms takes a place only when one is left: with none, its
    valid messages are refused as too_many_devices, and it still publishes."""
    clock, rng = _Clock(), random.Random(7)
    mirror = _fleet_mirror(clock, places=1)
    _round(mirror, clock, ["arm-001"], rng, 0.0)  # the one place
    kept = _record("arm-002", "wrist_roll", AlarmKind.OVER_TEMPERATURE, AlarmState.LATCHED, "hot")
    mirror.restore(None, [kept])
    for _ in range(round(OFFLINE_AFTER_S * 10) + 5):
        _round(mirror, clock, ["arm-002"], rng, 0.0)
    assert mirror.statuses()["arm-002"] == "OFFLINE"
    with pytest.raises(ArmNotForgettableError) as refused:
        mirror.forget_arm("arm-002")
    said = str(refused.value)
    assert "was refused (too_many_devices)" in said and "raise telemetry.max_devices" in said, said
    assert mirror.arm("arm-002").forget == (False, said)  # the page names the same fix


class _CountingLock:
    """The mirror's lock, recording how many Fleet rows each hold of it built."""

    def __init__(self, lock: Any) -> None:
        self._lock = lock
        self.rows_per_hold: list[int] = []

    def __enter__(self) -> None:
        self._lock.__enter__()
        self.rows_per_hold.append(0)

    def __exit__(self, *exc: object) -> None:
        self._lock.__exit__(*exc)


def test_the_fleet_rows_are_read_a_chunk_of_arms_per_hold_of_the_lock(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The worker thread needs the lock for every batch: a console tick must not hold it for the whole fleet.
    monkeypatch.setattr(mirror_module, "FLEET_ROWS_CHUNK", 40)
    clock, rng = _Clock(), random.Random(4)
    config = load_config(None, {"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    inbox = PipeInbox(Pipe(duplex=False)[0])
    mirror = Mirror(config, inbox=inbox, budget=DeviceBudget(200), clock=clock, wall_clock=clock)
    arms = [f"arm-{n:03d}" for n in range(101)]
    _round(mirror, clock, arms, rng, 0.0)
    lock = mirror._lock = _CountingLock(mirror._lock)  # type: ignore[assignment]
    row_of = mirror._fleet_row

    def counted(*args: Any) -> Any:
        lock.rows_per_hold[-1] += 1
        return row_of(*args)

    monkeypatch.setattr(mirror, "_fleet_row", counted)

    rows = mirror.fleet_rows()

    assert [r.device for r in rows] == arms
    assert lock.rows_per_hold == [0, 40, 40, 21]  # the alarms and the arms' names first, then 40 arms a hold


def test_a_configured_arm_is_not_forgotten() -> None:
    clock = _Clock()
    config = load_config(None, {"telemetry.devices": ["arm-001"], "health.offline_after_s": 1.0})
    mirror = Mirror(
        config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(3), clock=clock, wall_clock=clock
    )
    clock.now += 2.0
    assert mirror.statuses()["arm-001"] == "OFFLINE"
    with pytest.raises(ArmNotForgettableError) as refused:
        mirror.forget_arm("arm-001")
    assert refused.value.code == "arm_configured"
    assert "arm-001" in mirror.statuses()


# --- the HTTP endpoint, two worker processes ------------------------------------------------------------


def _post(url: str, headers: dict[str, str]) -> tuple[int, Any]:
    request = urllib.request.Request(url, data=b"", method="POST", headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=30) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())


def _get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=30) as resp:
        return json.loads(resp.read())


@pytest.mark.slow
def test_forgetting_an_arm_over_http_on_a_sharded_agent(rig: LocalRig, tmp_path: Path) -> None:
    plan = WorkerPlan(2)
    retired, kept = "arm-002", ["arm-001", "arm-003", "arm-004"]
    assert {plan.worker_of(d) for d in [retired, *kept]} == {0, 1}  # both workers hold arms
    state_file = tmp_path / "state.json"
    agent = rig.start_agent(
        {
            "telemetry.units": "ticks",
            "health.offline_after_s": 2.0,
            "twin.state_file": str(state_file),
        },
        workers=2,
    )
    url = agent.http_url
    faults = (ServoFault("heat", "wrist_roll", 0.0, 60.0),)
    edge = rig.start_edge([retired], rate_hz=10.0, servo_faults=faults, seconds=60.0)
    others = rig.start_edge(kept, rate_hz=10.0)
    try:
        wait_for(
            lambda: any(a.device == retired for a in alarms(url).alarms),
            60,
            f"an alarm of {retired}",
            interval=0.2,
        )
        wait_for(
            lambda: retired in {a["alarm_id"].split("/")[0] for a in _saved_alarms(state_file)},
            30,
            f"{retired}'s alarm in the state file",
            interval=0.2,
        )
        # While it publishes: refused, naming its status and the rule.
        status, body = post(f"{url}/api/arm/{retired}/forget")
        assert status == 409 and body["error"] == "arm_not_offline", body
        assert "ONLINE" in body["detail"] and "offline_after_s" in body["detail"]
        status, body = post(f"{url}/api/arm/arm-404/forget")
        assert status == 404 and body["error"] == "arm_not_found", body
        edge.stop()
        wait_for(lambda: agent.state().devices[retired].health.status == "OFFLINE", 30, f"{retired} OFFLINE")
        before = {d: agent.state().devices[d].health.counters.received for d in kept}
        # A browser request without the console's CSRF token is refused by the guard: the arm stays.
        status, body = _post(f"{url}/api/arm/{retired}/forget", {"Origin": url.rstrip("/")})
        assert status == 403 and body["error"] == "csrf_token_missing", body
        assert retired in _get(f"{url}/state")["devices"]

        status, body = post(f"{url}/api/arm/{retired}/forget")

        assert status == 200, body
        assert body["device"] == retired and sum(body["alarms_removed"].values()) >= 1, body
        assert retired not in _get(f"{url}/state")["devices"]
        assert not [a for a in alarms(url, everything=True).alarms if a.device == retired]
        assert retired not in json.dumps(_get(f"{url}/api/fleet")["rows"])
        wait_for(
            lambda: retired not in {a["alarm_id"].split("/")[0] for a in _saved_alarms(state_file)},
            30,
            f"{retired}'s alarms gone from the state file",
            interval=0.1,
        )
        wait_for(
            lambda: any(
                e["data"].get("action") == "forgotten"
                for e in _get(f"{url}/api/events?device={retired}&kind=twin")["events"]
            ),
            30,
            "an event of the arm forgotten",
            interval=0.1,
        )
        status, body = post(f"{url}/api/arm/{retired}/forget")
        assert status == 404, body
        # The other arms go on as before.
        wait_for(
            lambda: all(agent.state().devices[d].health.counters.received > before[d] for d in kept),
            30,
            "the other arms still counted",
        )
        assert all(agent.state().devices[d].health.status == "ONLINE" for d in kept)
    finally:
        edge.stop()
        others.stop()


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_an_arm_with_alarms_kept_over_a_restart_is_listed_before_it_is_heard_again(
    tmp_path: Path, workers: int
) -> None:
    """A walk: after a restart an arm's kept alarms were in /alarms and /metrics, but not on the Fleet page,
    its Arm page said "not known to this agent" and Forget answered 404, until the arm published again."""
    state_file, device = tmp_path / "state.json", "race-1"
    _alarm_kept_over_a_stop(state_file, device)
    again = _hot_arm_agent(state_file, workers=workers)
    again.start()
    try:
        kept = {a.alarm_id for a in again.alarms() if a.device == device}
        assert kept, again.alarms()
        (row,) = [r for r in again.fleet_rows() if r.device == device]
        assert row.alarm_severity and row.last_seen is None, row
        view = again.arm_view(device)
        assert view.state is not None and {a.alarm_id for a in view.alarms} == kept
        assert device in again.state().devices
        # Silent since the start: OFFLINE once past offline_after_s, and then it can be forgotten.
        wait_for(lambda: _row_status(again, device) == "OFFLINE", 30, f"{device} OFFLINE")
        forgotten = again.forget_arm(device)
        assert sum(forgotten.alarms_removed.values()) == len(kept)
        assert _gone(again, device)
    finally:
        again.stop()


def test_a_held_arm_listed_after_a_restart_for_its_alarms_is_not_forgotten_while_it_publishes(
    tmp_path: Path,
) -> None:
    """A review: an arm held by its refused calibration raises servo alarms from its refused messages; after
    a restart it is listed for them, OFFLINE (no message of it is valid), and a forget removed the alarms of
    an arm still publishing: they came back seconds later, unacknowledged."""
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "held-1.json").write_text('{"shoulder_pan": {}}')
    state_file, device = tmp_path / "state.json", "held-1"
    store = {"telemetry.calibrations": str(tmp_path / "cal")}
    _alarm_kept_over_a_stop(state_file, device, **store)
    again = _hot_arm_agent(state_file, workers=1, **store)
    again.start()
    try:

        def publishing_and_offline() -> bool:
            again.feed(f"dt/lerobot/{device}/telemetry", hot(device, int(time.time() * 1000), 68))
            return _row_status(again, device) == "OFFLINE"

        wait_for(publishing_and_offline, 30, f"{device} OFFLINE while it publishes", interval=0.1)
        again.feed(f"dt/lerobot/{device}/telemetry", hot(device, int(time.time() * 1000), 68))
        with pytest.raises(ArmNotForgettableError) as refused:
            again.forget_arm(device)
        said = str(refused.value)
        assert refused.value.code == "arm_not_offline" and "calibration_refused" in said, said
        assert "push a valid calibration for it" in said, said
        assert [a for a in again.alarms() if a.device == device]
    finally:
        again.stop()


def _alarm_kept_over_a_stop(state_file: Path, device: str, **overrides: Any) -> None:
    """An agent of one worker heats `device` until it raises an alarm, waits for the state file to keep
    it, and stops: the next agent on `state_file` starts with it."""
    first = _hot_arm_agent(state_file, workers=1, **overrides)
    first.start()
    try:
        _heat_until_alarmed(first, device)
        wait_for(lambda: _saved_alarms(state_file), 30, "the alarm in the state file")
    finally:
        first.stop()


def _row_status(agent: AgentService, device: str) -> str | None:
    return next((r.status for r in agent.fleet_rows() if r.device == device), None)


def _saved_alarms(state_file: Path) -> list[dict[str, Any]]:
    if not state_file.exists():
        return []
    alarms_: list[dict[str, Any]] = json.loads(state_file.read_text())["alarms"]
    return alarms_


# --- durable: neither a worker restart nor an agent restart brings it back ----------------------------------


def _hot_arm_agent(state_file: Path, workers: int, **overrides: Any) -> AgentService:
    """An agent of the whole fleet (`*`: a listed arm cannot be forgotten), fed through feed(), whose heat
    alarms raise at once and whose arms go OFFLINE after 2 s of silence."""
    settings = hot_arm_settings(
        **{
            "telemetry.devices": ["*"],
            "health.offline_after_s": 2.0,
            "twin.state_file": str(state_file),
            **overrides,
        }
    )
    return AgentService(load_config(None, settings), workers=workers)


def _heat_until_alarmed(agent: AgentService, device: str) -> None:
    def alarmed() -> bool:
        agent.feed(f"dt/lerobot/{device}/telemetry", hot(device, int(time.time() * 1000), 68))
        return any(a.device == device for a in agent.alarms())

    wait_for(alarmed, 60, f"a heat alarm of {device}", interval=0.1)


def _gone(agent: AgentService, device: str) -> bool:
    """`device` in none of the agent's readers (its state, its alarms, the console's fleet rows)."""
    return (
        device not in agent.state().devices
        and not [a for a in agent.alarms(include_normal=True) if a.device == device]
        and device not in [row.device for row in agent.fleet_rows()]
    )


@contextlib.contextmanager
def _two_workers_alarmed(state_file: Path, device: str) -> Iterator[tuple[AgentService, WorkerShard]]:
    """A started agent of two worker processes whose `device` has raised a heat alarm, and that device's
    shard; stopped after."""
    agent = _hot_arm_agent(state_file, workers=2)
    agent.start()
    try:
        shard = agent._shards[agent.plan.worker_of(device)]
        assert isinstance(shard, WorkerShard)
        _heat_until_alarmed(agent, device)
        yield agent, shard
    finally:
        agent.stop()


@pytest.mark.slow
def test_a_forgotten_arm_stays_forgotten_when_its_worker_dies_before_the_next_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The agent holds each worker's last checkpoint: a worker killed right after a forget, before the
    supervisor's next checkpoint, is started again from the one the forget took, not from one that holds the
    arm. The supervisor's checkpoints are switched off meanwhile, so only the forget's can count. Then the
    agent starts again from its state file: the arm is not back either."""
    retired = "arm-002"
    state_file = tmp_path / "state.json"
    with _two_workers_alarmed(state_file, retired) as (agent, shard):
        wait_for(
            lambda: (
                shard.checkpoint is not None
                and retired in shard.checkpoint.devices
                and any(r.device == retired for r in shard.checkpoint.alarms)
            ),
            30,
            f"a held checkpoint with {retired} and its alarm",
        )
        monkeypatch.setattr(agent, "_keep_state", lambda **_: None)
        wait_for(lambda: agent.state().devices[retired].health.status == "OFFLINE", 30, f"{retired} OFFLINE")
        agent.forget_arm(retired)
        signal_and_await_restart(shard)
        assert _gone(agent, retired)
        # The supervisor's checkpoints again (one taken here, as its next round takes it): what the restarted
        # worker holds reaches the state file.
        monkeypatch.undo()
        agent._keep_state()
        assert retired not in {a["alarm_id"].split("/")[0] for a in _saved_alarms(state_file)}
    again = _hot_arm_agent(state_file, workers=2)
    again.start()
    try:
        assert _gone(again, retired)
    finally:
        again.stop()


@pytest.mark.slow
def test_an_acknowledgement_survives_a_worker_that_dies_before_the_next_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An acknowledgement is a person's act, kept like a forget: a worker killed right after it, before the
    supervisor's next checkpoint, starts again from the checkpoint the acknowledgement took, and the alarm
    comes back ACKNOWLEDGED, not ACTIVE (the supervisor's checkpoints are switched off meanwhile, so only
    the acknowledgement's can count); the state file says so too."""
    device = "arm-002"
    state_file = tmp_path / "state.json"
    with _two_workers_alarmed(state_file, device) as (agent, shard):
        alarm = next(a for a in agent.alarms() if a.device == device)
        wait_for(
            lambda: (
                shard.checkpoint is not None
                and any(r.alarm_id == alarm.alarm_id and r.state == "ACTIVE" for r in shard.checkpoint.alarms)
            ),
            30,
            f"a held checkpoint with {alarm.alarm_id} ACTIVE",
        )
        monkeypatch.setattr(agent, "_keep_state", lambda **_: None)
        assert agent.acknowledge_alarm(alarm.alarm_id).state == "ACKNOWLEDGED"
        signal_and_await_restart(shard)
        states = {a.alarm_id: a.state for a in agent.alarms(include_normal=True)}
        assert states.get(alarm.alarm_id) == "ACKNOWLEDGED", states
        saved = {a["alarm_id"]: a["state"] for a in _saved_alarms(state_file)}
        assert saved.get(alarm.alarm_id) == "ACKNOWLEDGED", saved


def _queue_of(agent: AgentService, device: str) -> InboundQueue[Any]:
    """The agent's queue that `device`'s messages wait in: its worker's, or the in-process mirror's inbox."""
    shard = agent._shards[agent.plan.worker_of(device)]
    return shard.queue if isinstance(shard, WorkerShard) else shard._inbox  # type: ignore[attr-defined]


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_a_forgotten_arm_that_publishes_again_has_no_drops_of_before(tmp_path: Path, workers: int) -> None:
    """The agent's queue counts the messages it drops per device: a forget clears the arm's count, so the
    arm that publishes again starts from nothing there too; the fleet's total keeps what was dropped."""
    retired = "arm-002"
    agent = _hot_arm_agent(tmp_path / "state.json", workers=workers)
    agent.start()
    try:
        queue = _queue_of(agent, retired)
        roomy, queue.max_items = queue.max_items, 4  # a queue this short drops some of a burst

        def dropped() -> bool:
            for _ in range(200):
                agent.feed(f"dt/lerobot/{retired}/telemetry", hot(retired, int(time.time() * 1000), 35))
            device = agent.state().devices.get(retired)
            return device is not None and device.health.counters.overwritten > 0

        wait_for(dropped, 60, f"messages of {retired} dropped by the agent's queue", interval=0.1)
        queue.max_items = roomy
        total = agent.state().agent.mailbox.overwritten_total
        wait_for(lambda: agent.state().devices[retired].health.status == "OFFLINE", 30, f"{retired} OFFLINE")
        agent.forget_arm(retired)
        agent.feed(f"dt/lerobot/{retired}/telemetry", hot(retired, int(time.time() * 1000), 35))

        # Heard from again once its message is counted: a read in the middle of the worker's batch can list
        # the arm it admitted before the batch's counts reach it (the counts are what this test is about).
        def heard() -> DeviceState | None:
            device = agent.state().devices.get(retired)
            return device if device is not None and device.health.counters.received else None

        again = wait_for(heard, 30, f"{retired} heard from again", interval=0.1)
        assert again.health.counters.received == 1 and again.health.counters.overwritten == 0, again.health
        assert agent.state().agent.mailbox.overwritten_total >= total
    finally:
        agent.stop()


def _row(device: str, status: str = "OFFLINE", last_seen: float | None = 0.0, **kw: Any) -> FleetRow:
    return FleetRow(device, status, last_seen, None, None, None, None, None, None, None, None, 0, **kw)


def test_the_agent_forgets_only_arms_offline_that_long_with_nothing_waiting_for_a_person() -> None:
    rows = [
        _row("gone", last_seen=1000.0),
        _row("recent", last_seen=9000.0),  # OFFLINE, not yet that long
        _row("alarmed", last_seen=1000.0, unacknowledged=1),  # an alarm ACTIVE or LATCHED
        _row("listed", last_seen=1000.0),  # in telemetry.devices
        _row("restarting", last_seen=1000.0, mirror="restarting"),  # rows of a checkpoint
        _row("stale", "STALE", last_seen=1000.0),
        _row("kept", last_seen=None),  # listed for its kept alarms, not heard since the start (at 500)
    ]
    forgotten = long_offline(rows, 10_000.0, 7200.0, 500.0, frozenset({"listed"}))
    assert forgotten == [("gone", 9000.0), ("kept", 9500.0)]
    assert long_offline(rows, 10_000.0, 9600.0, 500.0, frozenset()) == []


@pytest.mark.parametrize("after", [0.5, -1.0, float("nan")])
def test_forget_offline_after_must_be_longer_than_offline(after: float) -> None:
    with pytest.raises(ConfigError, match="forget_offline_after_s"):
        load_config(None, {"health.offline_after_s": 1.0, "telemetry.forget_offline_after_s": after})


def test_an_arm_offline_longer_than_forget_offline_after_s_is_forgotten_by_the_agent(
    rig: LocalRig, tmp_path: Path
) -> None:
    """A churning fleet filled every max_devices place with arms retired long ago, and new ones were refused
    until a person forgot them one by one: with the setting, the agent forgets them itself, as a person's
    forget does (the state file too), and says so."""
    state_file = tmp_path / "state.json"
    agent = rig.start_agent(
        {
            "telemetry.units": "ticks",
            "health.offline_after_s": 1.0,
            "telemetry.forget_offline_after_s": 2.0,
            "twin.state_file": str(state_file),
        },
        workers=2,
    )
    url = agent.http_url
    # Model loads, not the mock servos' random currents: one over 1.3 A raises a critical over_current alarm
    # that stays ACTIVE, and an arm with an alarm no person has seen is rightly never forgotten. How many
    # messages the arm sends before it stops, and so whether one of them is such, depended on the load.
    retired = rig.start_edge(["arm-002"], rate_hz=10.0, seconds=None, model_loads=True)
    stays = rig.start_edge(["arm-001"], rate_hz=10.0, seed=3)
    try:
        wait_for(lambda: {"arm-001", "arm-002"} <= set(agent.state().devices), 60, "both arms")
        retired.stop()
        wait_for(lambda: "arm-002" not in agent.state().devices, 60, "arm-002 forgotten")

        def told() -> list[dict[str, Any]]:
            found = _get(f"{url}/api/events?device=arm-002&kind=twin")["events"]
            return [e for e in found if e["data"].get("action") == "forgotten"]

        wait_for(told, 30, "the event of it")
        (event,) = told()
        assert event["data"]["by"] == "agent", event
        assert event["message"].startswith("arm-002 forgotten by the agent: silent for "), event
        assert "telemetry.forget_offline_after_s" in event["message"]
        # The arm that publishes stays: never forgotten, and heard (waited on: one read could fall in a stall
        # of its edge's thread on a busy machine, past the 0.3 s after which an arm reads STALE).
        wait_for(
            lambda: agent.state().devices["arm-001"].health.status == "ONLINE", 30, "arm-001 heard, ONLINE"
        )
        gone = _get(f"{url}/api/events?device=arm-001&kind=twin")["events"]
        assert not [e for e in gone if e["data"].get("action") == "forgotten"], gone
    finally:
        retired.stop()
        stays.stop()


def test_a_fault_in_the_forget_sweep_does_not_end_the_supervisor(
    rig: LocalRig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The supervisor thread also restarts workers and keeps the state file: the sweep it runs for
    telemetry.forget_offline_after_s is guarded, so a fault in it is logged and the next sweep comes."""
    monkeypatch.setattr(agent_module, "FORGET_SWEEP_S", 0.1)
    calls: list[int] = []

    def sweep(self: AgentService) -> None:
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("a sweep's fault")

    monkeypatch.setattr(AgentService, "_forget_long_offline", sweep)
    rig.start_agent({"health.offline_after_s": 1.0, "telemetry.forget_offline_after_s": 2.0})
    wait_for(lambda: len(calls) >= 3, 60, "the sweeps after the fault")


def test_an_arm_with_alarms_no_one_saw_is_forgotten_only_after_forget_unseen_after_s() -> None:
    rows = [
        _row("gone", last_seen=1000.0),
        _row("alarmed", last_seen=1000.0, unacknowledged=2),
        _row("alarmed-recent", last_seen=5000.0, unacknowledged=1),
        _row("alarmed-listed", last_seen=1000.0, unacknowledged=1),
    ]
    listed = frozenset({"alarmed-listed"})
    assert long_offline(rows, 10_000.0, 2000.0, 500.0, listed) == [("gone", 9000.0)]  # 0: never
    forgotten = long_offline(rows, 10_000.0, 2000.0, 500.0, listed, unseen_after_s=8000.0)
    assert forgotten == [("gone", 9000.0), ("alarmed", 9000.0)]


@pytest.mark.parametrize("unseen", [1.0, float("inf")])
def test_forget_unseen_after_must_be_at_least_forget_offline_after(unseen: float) -> None:
    with pytest.raises(ConfigError, match="forget_unseen_after_s"):
        load_config(
            None,
            {
                "health.offline_after_s": 1.0,
                "telemetry.forget_offline_after_s": 2.0,
                "telemetry.forget_unseen_after_s": unseen,
            },
        )
    with pytest.raises(ConfigError, match="forget_unseen_after_s = 3600 must be"):
        load_config(None, {"telemetry.forget_unseen_after_s": 3600.0})  # forget_offline_after_s unset
    # Equal is allowed: "at least".
    equal = {"health.offline_after_s": 1.0, "telemetry.forget_offline_after_s": 2.0}
    assert (
        load_config(None, {**equal, "telemetry.forget_unseen_after_s": 2.0}).telemetry.forget_unseen_after_s
        == 2
    )


def _kept(state_file: Path) -> list[dict[str, Any]]:
    """The alarm records the agent's state file keeps ([] before its first write)."""
    return json.loads(state_file.read_text())["alarms"] if state_file.exists() else []


def _publishing(agent: AgentService, arms: list[str], seen: Callable[[], Any]) -> Callable[[], Any]:
    """`seen`, each look after `arms` published again (a hot reading each): they stay ONLINE until the test
    has looked, so a loaded machine that keeps it from looking for the 2 s they have once silent cannot fail
    it."""

    def look() -> Any:
        for arm in arms:
            agent.feed(telemetry_topic(DEFAULT_TOPIC_PREFIX, arm), hot(arm, int(time.time() * 1000), 80))
        return seen()

    return look


@pytest.mark.slow
def test_a_churning_fleet_whose_arms_leave_with_alarms_up_stays_bounded_and_keeps_admitting(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Arms that left with an alarm ACTIVE were kept for good: after max_devices of them every new arm was
    refused (too_many_devices), however many came. With telemetry.forget_unseen_after_s the agent drops them
    once silent that long, each with a WARNING event naming the alarms no one saw; the fleet, its alarms and
    the state file stay within max_devices arms, and every new generation of arms is mirrored."""
    monkeypatch.setattr(agent_module, "FORGET_SWEEP_S", 0.1)
    limit, generations = 4, 5
    state_file = tmp_path / "state.json"
    settings = hot_arm_settings(
        **{
            "telemetry.devices": ["*"],
            "telemetry.max_devices": limit,
            "health.offline_after_s": 1.0,
            "telemetry.forget_offline_after_s": 1.5,
            "telemetry.forget_unseen_after_s": 2.0,
            "twin.state_file": str(state_file),
        }
    )
    agent = AgentService(load_config(None, settings), workers=1)
    agent.start()
    kept_sizes = []
    try:
        for generation in range(generations):
            arms = [f"churn-{generation}-{i}" for i in range(limit)]
            wait_for(
                _publishing(
                    agent,
                    arms,
                    lambda arms=arms: (
                        agent.state().agent.alarms.present.get("critical", 0) >= len(arms)
                        and set(arms) <= set(agent.state().devices)
                    ),
                ),
                60,
                f"generation {generation} admitted, its alarms ACTIVE",
                interval=0.1,
            )
            assert len(agent.state().devices) <= limit
            kept = wait_for(
                _publishing(
                    agent,
                    arms,
                    lambda arms=arms: (
                        {r["device"] for r in _kept(state_file)} == set(arms) and _kept(state_file)
                    ),
                ),
                30,
                f"generation {generation}'s alarms in the state file, and no others",
                interval=0.1,
            )
            kept_sizes.append(len(kept))
            wait_for(lambda arms=arms: not set(arms) & set(agent.state().devices), 60, "generation forgotten")
        state = agent.state()

        def dropped() -> list[Any]:
            found = agent.events(EventQuery(kinds=frozenset({EventKind.TWIN.value}), limit=1000))
            return [e for e in found if e.data.get("action") == "forgotten"]

        # Each arm's once, or more if it came back while the test was kept from looking (_publishing).
        every = {f"churn-{generation}-{i}" for generation in range(generations) for i in range(limit)}
        told = wait_for(lambda: {e.device for e in dropped()} == every and dropped(), 30, "every arm's event")
    finally:
        agent.stop()
    assert state.untracked_rejected.get("too_many_devices", 0) == 0, state.untracked_rejected
    assert max(kept_sizes) == min(kept_sizes) > 0, kept_sizes  # one generation's alarms, never more
    assert not _kept(state_file)
    for event in told:
        assert event.level == "warning" and event.data["by"] == "agent", event
        assert f"dropped unseen: {event.device}/elbow_flex/" in event.message, event.message
        assert "forget_unseen_after_s" in event.message, event.message


def test_forgetting_arms_drops_the_agents_routes_to_their_topics() -> None:
    """The agent remembers where each topic goes (its shard) for MAX_ROUTES topics before it starts over:
    a forgotten arm's route goes with it, so a fleet whose ids come and go does not keep the ones gone."""
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,  # never answers: the test feeds the agent
            "http.listen": "127.0.0.1:0",
            "telemetry.units": "ticks",
            "health.offline_after_s": 1.0,
        },
    )
    agent = AgentService(config)
    agent.start()
    try:
        arms = [f"arm-{i:03d}" for i in range(12)]
        for i, arm in enumerate(arms):
            payload = make_payload(arm, 0.1, "ticks", random.Random(i), timestamp_ms=1_763_000_000_000 + i)
            agent.feed(telemetry_topic(DEFAULT_TOPIC_PREFIX, arm), encode(payload))

        def offline() -> bool:
            devices = agent.state().devices
            return all(a in devices and devices[a].health.status == "OFFLINE" for a in arms)

        wait_for(offline, 30, "every arm tracked, then OFFLINE")
        assert len(agent._routes) == len(arms)
        for arm in arms[4:]:
            agent.forget_arm(arm)
        assert sorted(device for _, device in agent._routes.values()) == arms[:4]
    finally:
        agent.stop()


class _TickingClock(_Clock):
    """A clock that moves on by `step` at each read: whatever the mirror reads after the first, at a
    boundary, is past it."""

    def __init__(self, step: float) -> None:
        super().__init__()
        self.step = step

    def __call__(self) -> float:
        self.now += self.step
        return self.now - self.step


def test_an_arm_pages_forget_answer_is_read_on_the_clock_its_status_was() -> None:
    """A review: Mirror.arm read the arm's status under one hold of the lock and its forget answer under a
    second, on a later read of the clock; at the OFFLINE boundary the page offered Forget beside STALE."""
    clock, rng = _Clock(), random.Random(11)
    mirror = _fleet_mirror(clock, places=3)
    _round(mirror, clock, ["arm-001"], rng, 0.0)
    ticking = _TickingClock(0.01)
    ticking.now = clock.now + OFFLINE_AFTER_S - ticking.step / 2  # the next read is STALE, any later OFFLINE
    mirror._clock = ticking
    reply = mirror.arm("arm-001")
    assert reply.state is not None and reply.state.health.status == "STALE", reply.state
    assert reply.forget is not None and not reply.forget.allowed, reply.forget
    assert "arm-001 is STALE" in reply.forget.why, reply.forget


@contextlib.contextmanager
def _offline_arm_agent(arm: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[AgentService]:
    """An agent with its mirror in this process, fed one message of `arm`, which is OFFLINE by then. Its
    supervisor keeps state only when woken (after a person's act): the test calls `_keep_state` itself."""
    monkeypatch.setattr(agent_module, "CHECKPOINT_EVERY_S", 3600.0)
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,  # never answers: the test feeds the agent
            "http.listen": "127.0.0.1:0",
            "telemetry.units": "ticks",
            "health.offline_after_s": 1.0,
        },
    )
    agent = AgentService(config)
    agent.start()
    try:
        payload = make_payload(arm, 0.1, "ticks", random.Random(1), timestamp_ms=1_763_000_000_000)
        agent.feed(telemetry_topic(DEFAULT_TOPIC_PREFIX, arm), encode(payload))

        def offline() -> bool:
            device = agent.state().devices.get(arm)
            return device is not None and device.health.status == "OFFLINE"

        wait_for(offline, 30, f"{arm} tracked, then OFFLINE")
        yield agent
    finally:
        agent.stop()


def test_a_forget_answered_in_time_settles_an_earlier_one_of_the_arm_that_timed_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A person whose forget timed out forgets the arm again, answered this time: that forget did the
    agent's part, so the supervisor's next checkpoint must not do it again (a false "was made" in the log,
    and the drop count of a new arm of that name wiped)."""
    arm = "arm-007"
    parts: list[str] = []
    forgotten = AgentService._forgotten

    def counted(self: AgentService, shard: Any, device: str) -> None:
        parts.append(device)
        forgotten(self, shard, device)

    monkeypatch.setattr(AgentService, "_forgotten", counted)
    with _offline_arm_agent(arm, monkeypatch) as agent:
        shard = agent._shards[agent.plan.worker_of(arm)]
        with agent._keep_lock:  # as the forget that timed out left it
            agent._forgets_pending[arm] = (shard.index, shard.restarts)
        agent.forget_arm(arm)
        agent._keep_state()  # the supervisor's next checkpoint, if its own, woken by the forget, is not done
        assert arm not in agent._forgets_pending and parts == [arm], parts


def test_a_forget_that_timed_out_is_not_settled_once_its_worker_started_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A worker started again from a restart point without the arm (its unconfirmed messages overflowed)
    did not forget it: the arm's counts must stay, though the next checkpoint finds it gone."""
    arm = "arm-008"
    topic = telemetry_topic(DEFAULT_TOPIC_PREFIX, arm)
    with _offline_arm_agent(arm, monkeypatch) as agent:
        shard = agent._shards[agent.plan.worker_of(arm)]
        assert agent._mirror is not None
        agent._mirror.forget_arm(arm)  # the arm gone, and not by the agent's forget
        with agent._keep_lock:  # a forget asked before the worker's last start
            agent._forgets_pending[arm] = (shard.index, shard.restarts - 1)
        agent._keep_state()
        assert arm not in agent._forgets_pending and topic in agent._routes
        # The same with the restart count unchanged: the forget is taken as made, its route goes.
        with agent._keep_lock:
            agent._forgets_pending[arm] = (shard.index, shard.restarts)
        agent._keep_state()
        assert arm not in agent._forgets_pending and topic not in agent._routes


def test_asking_after_a_forget_that_timed_out_that_fails_keeps_it_for_the_next_checkpoint(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The supervisor asks the mirror whether the arm is still there: a fault in that ask must not end it
    (nothing would start a dead worker again); the forget is asked after again at the next checkpoint."""
    arm = "arm-009"
    topic = telemetry_topic(DEFAULT_TOPIC_PREFIX, arm)
    with _offline_arm_agent(arm, monkeypatch) as agent:
        shard = agent._shards[agent.plan.worker_of(arm)]
        assert agent._mirror is not None
        agent._mirror.forget_arm(arm)  # made by the mirror after its answer was given up on
        answer = shard.request

        def failing(request: Any) -> Any:
            if isinstance(request, agent_module.ArmRequest):
                raise RuntimeError("an ask's fault")
            return answer(request)

        monkeypatch.setattr(shard, "request", failing)
        with agent._keep_lock:
            agent._forgets_pending[arm] = (shard.index, shard.restarts)
        agent._keep_state()
        assert arm in agent._forgets_pending and topic in agent._routes
        monkeypatch.setattr(shard, "request", answer)
        agent._keep_state()
        assert arm not in agent._forgets_pending and topic not in agent._routes
