"""The console's data from a sharded agent (`twin run --workers 2`): the Fleet page's rows come from the
workers without their full states, and the Events page gets each worker's events and the worker restarts."""

from __future__ import annotations

import json
import os
import random
import signal
import urllib.error
import urllib.request
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from conftest import http_get, unbrokered_agent, wait_for
from twin.edge.payload import encode, make_payload
from twin.rig.local import LocalRig
from twin.service import shards
from twin.service.agent import UNHEARD_MIN_REJECTED, AgentService, forget_timed_out
from twin.service.console import FLEET_COLUMNS, ForgetOffer, fleet_parts, fleet_rows
from twin.service.persist import StateFile
from twin.service.shards import WorkerError, WorkerPlan

pytestmark = pytest.mark.slow

DEVICES = ["arm-001", "arm-002", "arm-003", "arm-004"]


def get_json(url: str) -> Any:
    status, _, body = http_get(url)
    assert status == 200, body
    return json.loads(body)


def messages(url: str, **query: str) -> list[str]:
    params = "&".join(f"{k}={v}" for k, v in query.items())
    return [e["message"] for e in get_json(f"{url}/api/events?{params}")["events"]]


def test_a_sharded_agent_serves_the_fleet_rows_and_every_workers_events(rig: LocalRig) -> None:
    agent = rig.start_agent({"telemetry.devices": DEVICES, "telemetry.units": "ticks"}, workers=2)
    url = agent.http_url
    rig.start_edge(DEVICES, rate_hz=10.0, seconds=None)
    wait_for(
        lambda: (
            [r[0] for r in get_json(url + "/api/fleet")["rows"]] == DEVICES
            and all(r[1] == "ONLINE" for r in get_json(url + "/api/fleet")["rows"])
        ),
        60,
        "every arm ONLINE on the fleet page",
    )
    doc = get_json(url + "/api/fleet")
    assert doc["columns"] == list(FLEET_COLUMNS) and len(doc["rows"]) == len(DEVICES)

    def rows_agree_with_state() -> bool:
        # The workers' rows agree with the rows made from the merged state. The two are read one after
        # the other while the arms keep publishing (the hottest servo can change in between), so the
        # test waits for a pair of reads that agree instead of asserting on the first.
        rows = get_json(url + "/api/fleet")["rows"]
        from_state = {r.device: r for r in fleet_rows(agent.state(), agent.alarms())}
        return all(
            (row[1], row[9], row[11])
            == (from_state[row[0]].status, from_state[row[0]].hot_joint, from_state[row[0]].rejected)
            for row in rows
        )

    wait_for(rows_agree_with_state, 60, "the fleet rows agree with the merged state")

    # Each worker's events reach the front within a supervisor round or two.
    wait_for(
        lambda: all(f"{d} is ONLINE (first message)" in messages(url, kind="status") for d in DEVICES),
        30,
        "every arm's first-message event",
    )
    victim = agent.state().agent.workers[1]
    os.kill(victim.pid, signal.SIGKILL)
    wait_for(
        lambda: any("worker 1 running again" in m for m in messages(url, kind="worker")),
        30,
        "the restart events",
    )
    worker_events = messages(url, kind="worker", level="error")
    assert f"worker 1 (pid {victim.pid}) exited, killed by SIGKILL (signal 9)" in " ".join(worker_events)


def test_an_arm_page_is_read_from_its_own_worker_without_the_fleet_state(rig: LocalRig) -> None:
    # The arm page's document, twice a second while it is open, was cut from the whole state of the fleet,
    # built in every worker; it is asked of the arm's own worker now, and says what the whole state says.
    agent = rig.start_agent(
        {"telemetry.devices": DEVICES, "telemetry.units": "ticks", "health.offline_after_s": 600.0}, workers=2
    )
    url = agent.http_url
    edge = rig.start_edge(DEVICES, rate_hz=10.0, seconds=None)
    wait_for(lambda: all(r[1] == "ONLINE" for r in get_json(url + "/api/fleet")["rows"]), 60, "arms ONLINE")
    started_at = get_json(url + "/state")["agent"]["started_at"]
    assert started_at
    whole_reads: list[int] = []
    whole = agent.state

    def counted_state() -> Any:
        whole_reads.append(1)
        return whole()

    agent.state = counted_state  # type: ignore[method-assign]
    for device in DEVICES:
        doc = get_json(f"{url}/api/arm/{device}")
        assert doc["device"]["device_id"] == device and doc["device"]["health"]["status"] == "ONLINE"
        assert doc["calibration_push"]["command"]
        # The arm's counters begin at the agent's start, which the page says.
        assert doc["agent_started_at"] == started_at
    with urllib.request.urlopen(f"{url}/api/stream/arm/{DEVICES[1]}", timeout=30) as stream:
        frame = next(json.loads(line[len(b"data: ") :]) for line in stream if line.startswith(b"data: "))
    assert frame["device"]["device_id"] == DEVICES[1]
    status, _, body = http_get(f"{url}/api/arm/arm-404")
    assert status == 404 and json.loads(body)["error"] == "device_not_found"
    assert whole_reads == []  # neither the page's document nor its stream read the fleet

    # Once the arms are quiet, each arm's view is its part of the whole state, alarms and all.
    edge.stop()
    published = edge.join(30).published

    def every_message_handled() -> bool:
        return sum(d.health.counters.received for d in whole().devices.values()) == published

    wait_for(every_message_handled, 60, "every message published handled")
    state, alarms = whole(), agent.alarms()
    for device in DEVICES:
        view = agent.arm_view(device)
        assert view.state is not None
        mine, got = state.devices[device], view.state
        # (The loss estimate's recent window moves with the clock: its totals are compared.)
        assert (got.health.counters, got.joints_rad, got.servos, got.loss.lost) == (
            mine.health.counters,
            mine.joints_rad,
            mine.servos,
            mine.loss.lost,
        )
        assert [a.alarm_id for a in view.alarms] == [a.alarm_id for a in alarms if a.device == device]

    # Quiet arms are STALE, and an arm's view (what `twin view` follows) marks them all, from the workers'
    # fleet rows.
    def view_attention() -> dict[str, str]:
        with urllib.request.urlopen(f"{url}/stream?device={DEVICES[0]}", timeout=30) as stream:
            frame = next(json.loads(line[len(b"data: ") :]) for line in stream if line.startswith(b"data: "))
        return frame["attention"]

    wait_for(lambda: view_attention() == dict.fromkeys(DEVICES, "STALE"), 60, "every quiet arm marked STALE")


def test_an_arm_whose_worker_does_not_answer_is_shown_from_its_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # One ask per arm and tick, not two: a worker that does not answer is not asked again for the whole state.
    agent = unbrokered_agent(tmp_path, 2)
    try:
        device = next(d for d in DEVICES if agent.plan.worker_of(d) == 1)
        unknown = next(f"arm-{n}" for n in range(500, 600) if agent.plan.worker_of(f"arm-{n}") == 1)
        payload = encode(make_payload(device, 0.0, "ticks", random.Random(2)))
        agent.feed(f"dt/lerobot/{device}/telemetry", payload)
        shard = agent._shards[1]
        wait_for(lambda: (c := shard.checkpoint) is not None and c.taken >= 1, 60, "a checkpoint of the arm")
        # Its worker's answer, which came over the pipe inside the arm's reply: not OFFLINE, not forgotten.
        offer = agent.arm_view(device).forget
        assert isinstance(offer, ForgetOffer) and not offer.allowed, offer
        assert "only an OFFLINE arm" in offer.why, offer
        assert agent.arm_view(unknown).forget is None  # no state, nothing to forget
        asked: list[object] = []

        def silent(request: object) -> Any:
            asked.append(request)
            raise WorkerError("worker 1 did not answer within 10 s")

        shard.request = silent  # type: ignore[method-assign]
        view = agent.arm_view(device)
        assert len(asked) == 1  # the arm's own ask, and no whole state after it
        assert view.state is not None and view.state.device_id == device
        assert view.state.health.counters.received == 1
        # The page says why it cannot forget the arm now, in the words of the failed ask: the worker is not
        # being started again (a review: it said so).
        assert view.forget == ForgetOffer(False, "worker 1 did not answer within 10 s")
        assert agent.arm_view("arm-404").state is None
        assert agent.arm_view(unknown).forget is None
        del shard.request
        # A worker being started again: its checkpoint's arm, with the words forget_arm refuses with.
        monkeypatch.setattr(type(shard), "answering", property(lambda s: s.index != 1))
        view = agent.arm_view(device)
        assert view.state is not None and view.forget == ForgetOffer(False, "worker 1 is being started again")
        with pytest.raises(WorkerError) as refused:
            agent.forget_arm(device)
        assert str(refused.value) == view.forget.why
        assert agent.arm_view(unknown).forget is None
    finally:
        vars(shard).pop("request", None)
        monkeypatch.undo()
        agent.stop()


def test_a_forget_its_worker_does_not_answer_in_time_says_it_is_not_known_and_what_to_do(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A forget whose worker process does not answer within ASK_TIMEOUT_S (here: stopped with SIGSTOP) was
    answered 503 "worker 1 did not answer within 10 s; try again once it runs", of a worker that runs, and
    the page said "was not forgotten" though the request waits in its pipe. The answer is 504
    forget_timed_out with the same words as for a mirror in the agent's process (test_console.py), and the
    arm is forgotten once the worker goes on. Then the agent's own part came never: the arm's drop count
    (copied to a new arm of its name), its route and its state file alarms of unknown kinds stayed, and
    the worker's restart point held it. Its next checkpoint of the worker finds the arm gone and does it."""
    monkeypatch.setattr(shards, "HUNG_AFTER_ASKS", 1_000_000)  # stopped, not killed as hung meanwhile
    device = next(d for d in DEVICES if WorkerPlan(2).worker_of(d) == 1)  # by CRC-32: not listed
    # An alarm of a kind only a newer agent knows, carried for the arm in the state file until it goes.
    state_file = tmp_path / "state.json"
    StateFile(state_file).save([], 0.0, 0.0, stopped=True)
    document = json.loads(state_file.read_text())
    future = {"device": device, "kind": "a_future_kind", "alarm_id": f"{device}/shoulder_pan/a_future_kind"}
    state_file.write_text(json.dumps({**document, "alarms": [future]}))
    agent = unbrokered_agent(tmp_path, 2, **{"health.offline_after_s": 1.5})
    shard = agent._shards[1]
    topic = f"dt/lerobot/{device}/telemetry"
    stopped = False
    try:
        assert agent.plan.worker_of(device) == 1
        agent.feed(topic, encode(make_payload(device, 0.0, "ticks", random.Random(4))))

        def offline() -> bool:
            arm = agent.state().devices.get(device)
            return arm is not None and arm.health.status == "OFFLINE"

        wait_for(offline, 60, f"{device} heard, then OFFLINE")
        with shard._unconfirmed_lock:  # messages of it lost with a worker that died
            shard._lost.add(device, 5)
        assert shard.dropped()[device] == 5 and topic in agent._routes and device in state_file.read_text()
        os.kill(shard.pid, signal.SIGSTOP)
        stopped = True
        request = urllib.request.Request(f"{agent.http_url}/api/arm/{device}/forget", data=b"", method="POST")
        with pytest.raises(urllib.error.HTTPError) as answered:
            urllib.request.urlopen(request, timeout=60.0)
        body = json.loads(answered.value.read())
        assert (answered.value.code, body["error"]) == (504, "forget_timed_out"), body
        assert body["detail"] == forget_timed_out(device, shard), body
        assert body["detail"].startswith(
            f"worker 1, which mirrors {device}, did not answer the forget within 10 s"
        )
        os.kill(shard.pid, signal.SIGCONT)
        stopped = False
        wait_for(
            lambda: device not in agent.state().devices, 60, f"{device} forgotten once its worker went on"
        )

        def finished() -> bool:
            checkpoint = shard.checkpoint
            return (
                device not in shard.dropped()
                and topic not in agent._routes
                and device not in state_file.read_text()
                and checkpoint is not None
                and device not in checkpoint.devices
            )

        wait_for(finished, 60, f"the agent's part of {device}'s forget done: counts, route, state file")
        assert not agent._forgets_pending
    finally:
        if stopped:
            os.kill(shard.pid, signal.SIGCONT)
        agent.stop()


def test_a_listed_held_arm_whose_worker_is_silent_before_its_first_checkpoint_is_named_without_a_card(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The Fleet page names a held arm only when it has no card. A listed arm always has one, but not while
    its worker does not answer and no checkpoint holds the arm (it died or hangs before its first: no
    checkpoint is taken here). Then the notice said "its card says whether any came", of a card not there."""
    monkeypatch.setattr(shards, "HUNG_AFTER_ASKS", 1_000_000)  # stopped, not killed as hung meanwhile
    monkeypatch.setattr(AgentService, "_checkpoint", lambda self, shard, **_: None)
    held = next(d for d in DEVICES if WorkerPlan(2, DEVICES).worker_of(d) == 1)
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / f"{held}.json").write_text('{"shoulder_pan": {}}')
    overrides = {"telemetry.devices": DEVICES, "telemetry.calibrations": str(tmp_path / "cal")}
    agent = unbrokered_agent(tmp_path, 2, **overrides)
    shard = agent._shards[1]
    stopped = False
    try:
        assert agent.plan.worker_of(held) == 1 and held in agent._held_problems()
        parts = fleet_parts(agent)
        assert held in {r.device for r in parts.rows} and not [n for n in parts.notices if held in n]
        os.kill(shard.pid, signal.SIGSTOP)
        stopped = True

        def without_its_card() -> Any:
            # Its worker's rows asked, and not given within ASK_TIMEOUT_S (an answer read before is kept a
            # moment for the next tick).
            parts = fleet_parts(agent)
            return parts if held not in {r.device for r in parts.rows} else None

        parts = wait_for(without_its_card, 60, f"{held}'s worker silent, with no card for it")
        assert shard.checkpoint is None
        (notice,) = [n for n in parts.notices if n.startswith(f"{held}'s calibration")]
        assert "its card, back once its worker answers, says whether any came" in notice, notice
        assert "nothing has been received" not in notice, notice  # listed: tracked, and maybe heard
    finally:
        if stopped:
            os.kill(shard.pid, signal.SIGCONT)
        agent.stop()


def fleet_notices(url: str, frames: int) -> list[list[str]]:
    """The notices of the next `frames` frames of the Fleet page's stream, read as a console reads it."""
    said: list[list[str]] = []
    with urllib.request.urlopen(f"{url}/api/stream/fleet", timeout=60) as stream:
        for line in stream:
            if line.startswith(b"data: "):
                said.append(json.loads(line[len(b"data: ") :])["notices"])
                if len(said) == frames:
                    break
    return said


def test_open_consoles_ask_no_worker_for_the_refused_arms_notice(tmp_path: Path) -> None:
    # The Fleet page's notice naming an arm whose every message is refused asked every worker over its pipe
    # at each console tick, beside the rows; it is read from the checkpoints the agent takes anyway. And the
    # consoles share the tick: three open cost the workers one rows ask per tick each, not three.
    agent = unbrokered_agent(tmp_path, 2)
    asked: Counter[str] = Counter()
    shards = list(agent._shards)
    try:
        for shard in shards:

            def counted(request: Any, ask: Any = shard.request) -> Any:
                asked[type(request).__name__] += 1
                return ask(request)

            shard.request = counted  # type: ignore[method-assign]
        for _ in range(UNHEARD_MIN_REJECTED):
            agent.feed("dt/lerobot/arm-009/telemetry", b"not telemetry")

        def named(notices: list[str]) -> bool:
            return any(n.startswith("arm-009 publishes, but the agent refused all") for n in notices)

        wait_for(lambda: named(agent.notices()), 60, "the notice naming arm-009")
        hub = agent._http._hub  # type: ignore[union-attr]
        assert hub is not None and hub.clients == 0
        asked.clear()
        ticks = hub.ticks
        with ThreadPoolExecutor(3) as pool:
            consoles = list(pool.map(lambda _: fleet_notices(agent.http_url, 4), range(3)))
        wait_for(lambda: hub.clients == 0, 30, "the consoles' streams closed")
        ticked = hub.ticks - ticks
        assert all(named(notices) for frames in consoles for notices in frames), consoles
        assert asked["UnheardRequest"] == 0, asked
        # One ask per worker and tick (one more for a tick under way as the count was read).
        assert 0 < asked["FleetRowsRequest"] <= len(shards) * (ticked + 1), (asked, ticked)
    finally:
        for shard in shards:
            shard.__dict__.pop("request", None)
        agent.stop()
