"""Alarm states over restarts, end to end: servo faults from `twin edge-sim` through a real mosquitto.

- A worker process SIGKILLed while an arm has an ACKNOWLEDGED over-temperature alarm: the restarted worker
  takes back its checkpoint, the alarm is still ACKNOWLEDGED, and the arm never leaves /state (it shows as
  restarting meanwhile).
- The agent stopped and started again (a restart, or a reboot: the state file is all that survives): a
  LATCHED alarm is still LATCHED, and an ACKNOWLEDGED one still ACKNOWLEDGED.
- `twin run` killed (SIGKILL) and started again: no process of it outlives it, the acknowledgement is back,
  and the next start's log says the run before did not stop.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import random
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import Publisher, fill, get_state, http_get, wait_for
from test_servo_alarms_e2e import alarms, by_key, post
from twin.edge.payload import encode, make_payload
from twin.edge.servo_faults import ServoFault
from twin.rig.local import LocalRig
from twin.service.agent import AgentService
from twin.service.shards import WorkerPlan

pytestmark = pytest.mark.slow

FLEET = ["arm-001", "arm-002", "arm-003", "arm-004"]
HOT = ("wrist_roll", "over_temperature")


class HotWrist:
    """An arm whose wrist_roll servo reports 62 C (over the 60 C warning line) in every message, at 10 Hz,
    until stopped: the condition lasts through a restart of its worker."""

    def __init__(self, publisher: Publisher, device: str) -> None:
        self._publisher = publisher
        self._device = device
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        rng = random.Random(3)
        t = 0.0
        while not self._stop.wait(0.1):
            doc = make_payload(self._device, t, "ticks", rng, timestamp_ms=int(time.time() * 1000))
            doc["joints"]["wrist_roll"]["temp"] = 62
            self._publisher.publish(self._device, encode(doc))
            t += 0.1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)


def acknowledge_once_active(url: str, alarm: str, timeout_s: float) -> None:
    """Wait for `alarm` to be ACTIVE, then acknowledge it over HTTP and check the answer says so."""
    wait_for(
        lambda: any(a.alarm_id == alarm and a.state == "ACTIVE" for a in alarms(url).alarms),
        timeout_s,
        f"{alarm} to be raised",
        interval=0.1,
    )
    status, body = post(f"{url}/alarms/{alarm}/ack")
    assert status == 200 and body["alarms"][0]["state"] == "ACKNOWLEDGED", body


def test_a_killed_worker_keeps_an_acknowledged_alarm_and_its_arm_never_leaves_state(
    rig: LocalRig, publisher: Publisher
) -> None:
    plan = WorkerPlan(2, FLEET)
    hot_arm = "arm-002"
    worker = plan.worker_of(hot_arm)
    agent = rig.start_agent({"telemetry.devices": FLEET, "telemetry.units": "ticks"}, workers=2)
    url = agent.http_url
    rig.start_edge([d for d in FLEET if d != hot_arm], variant="ticks", rate_hz=10.0, seed=7)
    hot = HotWrist(publisher, hot_arm)
    try:
        alarm = f"{hot_arm}/{HOT[0]}/{HOT[1]}"
        acknowledge_once_active(url, alarm, 30)
        # The acknowledgement reaches the worker's checkpoint at once (it wakes the agent's supervisor).
        shard = agent._shards[worker]
        wait_for(
            lambda: (
                shard.checkpoint is not None
                and any(r.alarm_id == alarm and r.state == "ACKNOWLEDGED" for r in shard.checkpoint.alarms)
            ),
            30,  # at once when idle; a bound as loose as the other waits' on a loaded host
            "a checkpoint with the acknowledgement",
        )
        victim = get_state(url).agent.workers[worker]
        os.kill(victim.pid, signal.SIGKILL)

        states_seen: set[str] = set()

        def running_again() -> bool:
            state = get_state(url)
            assert set(FLEET) <= set(state.devices), f"an arm left /state: {sorted(state.devices)}"
            states_seen.add(state.devices[hot_arm].mirror)
            info = state.agent.workers[worker]
            return info.alive and info.restarts == 1 and info.pid != victim.pid

        wait_for(running_again, 60, "the worker to run again", interval=0.05)
        assert "restarting" in states_seen
        assert by_key(alarms(url))[HOT] == "ACKNOWLEDGED"
        # Still acknowledged after more hot readings, which the new worker evaluates against the restored one.
        applied = get_state(url).devices[hot_arm].health.counters.applied
        wait_for(
            lambda: get_state(url).devices[hot_arm].health.counters.applied > applied + 20,
            20,
            "more messages",
        )
        assert by_key(alarms(url))[HOT] == "ACKNOWLEDGED"
        assert get_state(url).devices[hot_arm].mirror == "running"
    finally:
        hot.stop()


def test_while_a_worker_restarts_alarms_and_fleet_rows_keep_its_arms_from_its_checkpoint(
    rig: LocalRig, publisher: Publisher, monkeypatch: pytest.MonkeyPatch
) -> None:
    """/alarms and the console's fleet rows read the worker's checkpoint as /state does: an ACKNOWLEDGED
    alarm of a restarting worker's arm is still listed, and the arm's row is there, marked restarting."""
    plan = WorkerPlan(2, FLEET)
    hot_arm = "arm-002"
    worker = plan.worker_of(hot_arm)
    agent = rig.start_agent({"telemetry.devices": FLEET, "telemetry.units": "ticks"}, workers=2)
    url = agent.http_url
    shard = agent._shards[worker]
    # The restart is held where it begins (the supervisor waits to launch the new process), so the readers
    # are asked while the worker is down however quickly the machine would have started it again.
    launching, go_on = threading.Event(), threading.Event()
    launch = shard.launch

    def held_launch() -> None:
        launching.set()
        go_on.wait(120)
        launch()

    monkeypatch.setattr(shard, "launch", held_launch)
    rig.start_edge([d for d in FLEET if d != hot_arm], variant="ticks", rate_hz=10.0, seed=7)
    hot = HotWrist(publisher, hot_arm)
    alarm = f"{hot_arm}/{HOT[0]}/{HOT[1]}"
    try:
        acknowledge_once_active(url, alarm, 30)
        wait_for(
            lambda: (
                shard.checkpoint is not None
                and hot_arm in shard.checkpoint.devices
                and any(r.alarm_id == alarm and r.state == "ACKNOWLEDGED" for r in shard.checkpoint.alarms)
            ),
            30,
            "a checkpoint with the acknowledgement",
        )
        os.kill(get_state(url).agent.workers[worker].pid, signal.SIGKILL)
        assert launching.wait(60), "the supervisor did not start the worker again"
        try:
            assert_listed_from_the_checkpoint(agent, url, hot_arm, worker, plan)
        finally:
            go_on.set()
        wait_for(
            lambda: (
                get_state(url).agent.workers[worker].alive
                and {row.device: row.mirror for row in agent.fleet_rows()}.get(hot_arm) == "running"
            ),
            60,
            "the worker to run again",
            interval=0.1,
        )
        assert by_key(alarms(url))[HOT] == "ACKNOWLEDGED"

        # Running again: healthy once every listed arm is heard from (the edge sends throughout).
        def healthy() -> dict[str, object] | None:
            status_code, _, raw = http_get(url + "/healthz")
            return json.loads(raw) if status_code == 200 else None

        health = wait_for(healthy, 30, "/healthz to be 200 again", interval=0.1)
        assert health["reasons"] == [] and set(health["devices"]) == set(FLEET), health
    finally:
        hot.stop()


def assert_listed_from_the_checkpoint(
    agent: AgentService, url: str, hot_arm: str, worker: int, plan: WorkerPlan
) -> None:
    """While `worker` is down: its arm's acknowledged alarm in /alarms, its row in the fleet's, restarting."""
    listed = {a.alarm_id: a for a in agent.alarms()}
    alarm = f"{hot_arm}/{HOT[0]}/{HOT[1]}"
    assert listed[alarm].state == "ACKNOWLEDGED" and listed[alarm].severity == "warning"
    assert by_key(alarms(url))[HOT] == "ACKNOWLEDGED"
    # Listed, but only its worker can change it: asked again later, not refused as unknown.
    status, body = post(f"{url}/alarms/{alarm}/ack")
    assert status == 503 and body["error"] == "worker_unavailable", body
    rows = {row.device: row for row in agent.fleet_rows()}
    assert set(rows) == set(FLEET)
    assert rows[hot_arm].mirror == "restarting"
    assert {rows[d].mirror for d in FLEET if plan.worker_of(d) != worker} == {"running"}
    worst = next(a for a in agent.alarms() if a.device == hot_arm)
    row = rows[hot_arm]
    assert (row.alarm_severity, row.alarm_state, row.alarm_kind) == (worst.severity, worst.state, worst.kind)
    state = get_state(url)
    assert state.devices[hot_arm].mirror == "restarting"
    # /healthz reads the statuses alone (not the state), and the same rules: the worker is down, its arms
    # are there as the checkpoint left them.
    status_code, _, raw = http_get(url + "/healthz")
    health = json.loads(raw)
    assert status_code == 503 and f"worker {worker} is not running" in health["reasons"], health
    assert set(health["devices"]) == set(FLEET), health
    # The fleet's alarm counts take the restarting worker's from its checkpoint: no dip while it is down.
    summary = state.agent.alarms
    assert summary.by_state["warning"].get("ACKNOWLEDGED", 0) >= 1 and summary.present["warning"] >= 1
    # The console's fleet page gets the same rows, with the column that says so.
    fleet = json.loads(http_get(url + "/api/fleet")[2])
    by_device = {r[0]: dict(zip(fleet["columns"], r, strict=True)) for r in fleet["rows"]}
    assert by_device[hot_arm]["mirror"] == "restarting"
    assert by_device[hot_arm]["alarm_state"] == worst.state


def test_an_agent_restart_keeps_latched_and_acknowledged_alarms(rig: LocalRig, tmp_path: Path) -> None:
    state_file = tmp_path / "state" / "state.json"
    overrides = {
        "telemetry.devices": ["arm-001"],
        "telemetry.units": "ticks",
        "twin.state_file": str(state_file),
        "alarms.temperature_clear_after_s": 2.0,
    }
    agent = rig.start_agent(overrides)
    url = agent.http_url
    # Heat on the wrist for 8 s (raised, then cleared unacknowledged: LATCHED), and an overload on the
    # shoulder that lasts (its over-current alarm acknowledged while present).
    faults = (ServoFault("heat", "wrist_roll", 0.5, 6.0), ServoFault("overload", "shoulder_lift", 0.5, 600.0))
    rig.start_edge(["arm-001"], variant="ticks", rate_hz=10.0, servo_faults=faults, model_loads=True)
    current = "arm-001/shoulder_lift/over_current"
    acknowledge_once_active(url, current, 60)
    wait_for(lambda: by_key(alarms(url)).get(HOT) == "LATCHED", 60, "the heat alarm to latch", interval=0.1)
    before = by_key(alarms(url))
    assert before[("shoulder_lift", "over_current")] == "ACKNOWLEDGED"

    agent.stop()  # the final write of the state file
    kept = {a["alarm_id"]: a["state"] for a in json.loads(state_file.read_text())["alarms"]}
    assert kept["arm-001/wrist_roll/over_temperature"] == "LATCHED"
    assert kept[current] == "ACKNOWLEDGED"

    again = rig.start_agent(overrides)
    url = again.http_url
    # Before any message of the arm: what the file kept.
    after = by_key(alarms(url))
    assert after[HOT] == "LATCHED" and after[("shoulder_lift", "over_current")] == "ACKNOWLEDGED"
    # With the arm's messages flowing again (a cool wrist, the shoulder still overloaded): LATCHED waits for
    # a person, the acknowledged condition stays acknowledged.
    applied = lambda: get_state(url).devices["arm-001"].health.counters.applied  # noqa: E731
    wait_for(lambda: applied() > 30, 30, "the arm mirrored again")
    after = by_key(alarms(url))
    assert after[HOT] == "LATCHED" and after[("shoulder_lift", "over_current")] == "ACKNOWLEDGED"
    status, body = post(f"{url}/alarms/arm-001/wrist_roll/over_temperature/ack")
    assert status == 200 and body["alarms"][0]["state"] == "NORMAL"


def test_stop_keeps_its_budget_and_reports_what_it_could_not_write(
    rig: LocalRig, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """History on a full disk (a real tmpfs) when the agent stops: the workers hand their rows to the history
    writer process, which retries its last commit within the shutdown budget and says how many rows it could
    not write; the agent logs them in one line, and its last CloudWatch document counts them as dropped."""
    from test_emf import validate_emf_line

    disk = tmp_path / "disk"
    disk.mkdir()
    emf = tmp_path / "emf.log"
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(disk)], check=True)
    try:
        budget = 12.0
        agent = rig.start_agent(
            {
                "telemetry.devices": FLEET,
                "telemetry.units": "ticks",
                "history.uri": str(disk / "history"),
                "history.commit_every_s": 0.5,
                "twin.shutdown_budget_s": budget,
                # At the mirrors' priority: at its default (nicer) the writer starved beside the busy
                # processes of `make test-stress`, and its share of the stop ended before it had read its
                # sockets.
                "history.writer_nice": 0,
                "cloudwatch.emf_file": str(emf),
                "cloudwatch.agent_name": "stop",
                "cloudwatch.interval_s": 0.5,
            },
            workers=2,
        )
        rig.start_edge(FLEET, variant="ticks", rate_hz=10.0, seed=3)
        wait_for(lambda: (agent.state().agent.history.commits or 0) >= 2, 30, "history committing")
        fill(disk)
        wait_for(
            lambda: (
                agent.state().agent.history.commit_failures > 0 and agent.state().agent.history.rows_buffered
            ),
            30,
            "commits failing with rows waiting",
            interval=0.2,
        )
        caplog.set_level(logging.INFO, logger="twin.service.agent")
        started = time.monotonic()
        agent.stop()
        took = time.monotonic() - started
        # Not a speed figure: the budget is a promise to systemd, whose stop timeout is longer.
        assert took < budget + 10.0, took
        reports = agent.stop_reports
        assert set(reports) == {0, 1} and all(r is not None for r in reports.values())  # none killed
        # Rows a worker's feed could not hand over (none: the writer process listened to the end), and the
        # rows the writer could not commit.
        handed = sum(r.unwritten.get("history_rows", 0) for r in reports.values() if r is not None)
        assert agent._history is not None
        unwritten = handed + agent._history.unwritten_rows()
        assert unwritten > 0
        line = next(r for r in caplog.records if r.getMessage().startswith("agent stopped"))
        assert line.levelno == logging.ERROR and f"{unwritten} history_rows" in line.getMessage()
        # Every row the feeds wrote to the writer's socket was read (nothing `history_rows_unread`).
        assert line.unwritten == {"history_rows": unwritten}  # type: ignore[attr-defined]
        # The EMF documents, the one written at the stop last, add up to every history row lost: dropped by
        # the writer's full buffer, and not written at the stop.
        history = agent.state().agent.history
        assert history is not None
        docs = [validate_emf_line(text) for text in emf.read_text().splitlines()]
        dropped = sum(d.get("HistoryRowsDropped", 0) for d in docs)
        assert dropped == history.rows_dropped + history.rows_lost + unwritten
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def running(processes: list[psutil.Process]) -> list[psutil.Process]:
    """Those of `processes` that still run (a zombie has ended; one may end between two questions)."""
    alive = []
    for process in processes:
        try:
            if process.is_running() and process.status() != psutil.STATUS_ZOMBIE:
                alive.append(process)
        except psutil.NoSuchProcess:
            pass
    return alive


def _answering(url: str) -> bool:
    try:
        return bool(get_state(url).agent.broker.subscribes)
    except OSError:
        return False


def test_a_killed_agent_leaves_no_process_and_its_next_start_says_it_did_not_stop(
    rig: LocalRig, publisher: Publisher, tmp_path: Path
) -> None:
    state_file, events_file = tmp_path / "state.json", tmp_path / "events.jsonl"
    config = (
        f'[twin]\nstate_file = "{state_file}"\nevents_file = "{events_file}"\nworkers = 2\n'
        '[telemetry]\nunits = "ticks"\n'
    )
    alarm = f"arm-002/{HOT[0]}/{HOT[1]}"

    def kept() -> dict[str, str]:
        document = json.loads(state_file.read_text()) if state_file.exists() else {"alarms": []}
        return {a["alarm_id"]: a["state"] for a in document["alarms"]}

    def journaled() -> dict[str, int]:
        """The alarm's events in the journal, by action: their ids. Read while the agent appends to it, so a
        last line still being written is left out."""
        lines = events_file.read_text().splitlines() if events_file.exists() else []
        events = []
        for text in lines:
            with contextlib.suppress(json.JSONDecodeError):
                events.append(json.loads(text))
        return {e["data"]["action"]: e["id"] for e in events if e["data"].get("alarm_id") == alarm}

    hot = HotWrist(publisher, "arm-002")
    try:
        with rig.agent_process(devices=",".join(FLEET), config_text=config, log_name="killed") as (proc, url):
            wait_for(lambda: _answering(url), 60, "the agent", interval=0.2)
            acknowledge_once_active(url, alarm, 30)
            wait_for(lambda: kept().get(alarm) == "ACKNOWLEDGED", 30, "the acknowledgement in the state file")
            wait_for(lambda: "acknowledged" in journaled(), 30, "the acknowledgement in the event journal")
            family = psutil.Process(proc.pid).children(recursive=True)
            assert len(family) >= 3  # its fork server and two workers at least
            proc.kill()
            proc.wait(10)
            # The workers see their pipes close, flush and exit; the fork server goes with the agent.
            wait_for(lambda: not running(family), 30, "no process of the killed agent left", interval=0.1)
        assert json.loads(state_file.read_text())["stopped"] is False
        killed_log = rig.agent_log(url.rsplit(":", 1)[1], "killed").read_text().splitlines()
        said = [json.loads(t)["msg"] for t in killed_log if t.startswith("{")]
        # Each worker says it stopped, and nothing says the agent did: it was killed.
        assert said.count("worker stopped") == 2 and "agent stopped" not in said, said

        with rig.agent_process(devices=",".join(FLEET), config_text=config, log_name="again") as (_, url):
            wait_for(lambda: _answering(url), 60, "the agent again", interval=0.2)
            assert by_key(alarms(url))[HOT] == "ACKNOWLEDGED"
            log_path = rig.agent_log(url.rsplit(":", 1)[1], "again")
            lines = [json.loads(t) for t in log_path.read_text().splitlines() if t.startswith("{")]
            warned = [ln for ln in lines if ln["level"] == "WARNING" and "did not stop" in ln["msg"]]
            assert [ln["previous_pid"] for ln in warned] == [proc.pid], lines
            # The Events page too: the killed run's alarm events, with their ids, then this run's start,
            # which says the run before did not stop.
            status, _, body = http_get(f"{url}/api/events?limit=1000")
            assert status == 200, body
            listed = json.loads(body)["events"]
            ids = {e["data"]["action"]: e["id"] for e in listed if e["data"].get("alarm_id") == alarm}
            assert {k: ids.get(k) for k in ("raised", "acknowledged")} == {
                k: journaled()[k] for k in ("raised", "acknowledged")
            }, listed
            started = [e for e in listed if e["kind"] == "agent" and e["data"]["action"] == "started"]
            assert [e["level"] for e in started] == ["info", "warning"], started
            assert "did not record a stop" in started[1]["message"]
    finally:
        hot.stop()
    assert json.loads(state_file.read_text())["stopped"] is True  # SIGTERM: the stop's own write


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_an_acknowledgement_is_in_the_state_file_when_it_is_answered(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int
) -> None:
    """A person's acknowledgement must survive a kill that comes right after its answer: the agent writes
    the state file before answering, not at its supervisor's next check (a second or two later at a large
    fleet, with workers). The supervisor's own writes are switched off here, so only that one can write."""
    from test_alerts import hot, hot_arm_settings
    from twin.service.config import load_config

    state_file = tmp_path / "state.json"
    config = load_config(None, hot_arm_settings(**{"twin.state_file": str(state_file)}))
    agent = AgentService(config, workers=workers)
    agent.start()
    try:
        monkeypatch.setattr(agent, "_keep_state", lambda **_: None)
        alarm_id = "arm-003/elbow_flex/over_temperature_critical"

        def active() -> bool:
            agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", int(time.time() * 1000), 68))
            return any(a.alarm_id == alarm_id and a.state == "ACTIVE" for a in agent.alarms())

        wait_for(active, 60, "the critical heat alarm ACTIVE", interval=0.2)
        agent.acknowledge_alarm(alarm_id)
        kept = {a["alarm_id"]: a["state"] for a in json.loads(state_file.read_text())["alarms"]}
        assert kept[alarm_id] == "ACKNOWLEDGED", kept
    finally:
        agent.stop()


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_an_acknowledgement_the_state_file_cannot_keep_is_answered_as_not_saved(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int
) -> None:
    """A walk filled the state file's disk, acknowledged (answered 200 ACKNOWLEDGED), killed the agent and
    found the alarm ACTIVE again. The answer now says the acknowledgement is not kept (503 not_saved, with the
    fix); it holds in memory, the failed writes are a dropped output's, and the next write keeps it."""
    from test_alerts import hot, hot_arm_settings
    from twin.service import persist
    from twin.service.config import load_config

    state_file = tmp_path / "state.json"
    config = load_config(
        None, hot_arm_settings(**{"twin.state_file": str(state_file), "http.listen": "127.0.0.1:0"})
    )
    agent = AgentService(config, workers=workers)
    agent.start()
    try:
        alarm_id = "arm-003/elbow_flex/over_temperature_critical"

        def active() -> bool:
            agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", int(time.time() * 1000), 68))
            return any(a.alarm_id == alarm_id and a.state == "ACTIVE" for a in agent.alarms())

        wait_for(active, 60, "the critical heat alarm ACTIVE", interval=0.2)
        real = persist.write_atomically

        def disk_full(path: Path, text: str) -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(persist, "write_atomically", disk_full)
        status, body = post(f"{agent.http_url}/alarms/{alarm_id}/ack")
        assert status == 503 and body["error"] == "not_saved", body
        assert "could not be written (OSError: [Errno 28] No space left on device)" in body["detail"]
        assert "a restart before it can be would undo it" in body["detail"]
        assert {a.alarm_id: a.state for a in agent.alarms()}[alarm_id] == "ACKNOWLEDGED"

        def sink() -> Any:
            agent._cached = None
            return next(s for s in agent.state().agent.sinks if s.name == "state_file")

        assert sink().dropped >= 1 and sink().pending == 1
        monkeypatch.setattr(persist, "write_atomically", real)

        def kept() -> bool:
            if not state_file.exists():  # the full disk may have come before the run's first write
                return False
            alarms = json.loads(state_file.read_text())["alarms"]
            return {a["alarm_id"]: a["state"] for a in alarms}.get(alarm_id) == "ACKNOWLEDGED"

        wait_for(kept, 30, "the supervisor's next write to keep the acknowledgement", interval=0.2)
        assert wait_for(lambda: sink().pending == 0, 30, "the state file no longer behind")
    finally:
        agent.stop()


def test_arms_read_from_checkpoints_once_the_agent_stops_say_stopping_not_restarting(tmp_path: Path) -> None:
    """A walk kept the Fleet page open through a stop: every card said "restarting", and nothing was."""
    from conftest import unbrokered_agent

    agent = unbrokered_agent(tmp_path, 2, **{"telemetry.devices": ["arm-001", "arm-002"]})
    try:
        rng = random.Random(1)
        sent = itertools.count()

        def online() -> bool:
            # The arms publish while the test waits, as live arms do: a worker slow to start on a busy host
            # handles five messages sent once when they are already old, and arms silent since read STALE.
            i = next(sent)
            for device in ("arm-001", "arm-002"):
                payload = encode(make_payload(device, 0.1 * i, "ticks", rng))
                agent.feed(f"dt/lerobot/{device}/telemetry", payload)
            rows = agent.fleet_rows()
            return len(rows) == 2 and all(r.status == "ONLINE" for r in rows)

        wait_for(online, 30, "both arms ONLINE", interval=0.1)
        # Each worker's checkpoint holds both arms' figures once it has them (taken every second).
        wait_for(lambda: len(agent._checkpoint_devices(agent._shards)) == 2, 30, "the arms in checkpoints")
    finally:
        agent.stop()
    rows = agent.fleet_rows()
    assert {(r.device, r.mirror) for r in rows} == {("arm-001", "stopping"), ("arm-002", "stopping")}, rows
